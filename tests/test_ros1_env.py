"""Reaching Debian's ROS 1 from the project's Python (brave6d.ros_interface.ros1.ros_env) and the
``brave6d ros1`` command's one-line errors; fast, and most of it without ROS installed."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from brave6d.ros_interface.ros1 import ros_env
from brave6d.ros_interface.ros1.cli import master_uri_of
from brave6d.core.errors import BraveError

ROOT = Path(__file__).resolve().parent.parent


def test_missing_packages_are_named_without_importing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ros_env, "DEBIAN_DIST_PACKAGES", str(tmp_path))
    monkeypatch.setattr(ros_env, "ROSMASTER", str(tmp_path / "rosmaster"))
    missing = ros_env.missing_ros1(import_modules=False)
    assert "python3-rospy" in missing and "python3-sensor-msgs" in missing and "python3-rosmaster" in missing
    (tmp_path / "rospy").mkdir()
    (tmp_path / "rospy" / "__init__.py").write_text("")
    assert "python3-rospy" not in ros_env.missing_ros1(import_modules=False)
    assert str(tmp_path) not in sys.path


def test_loopback_environment_keeps_a_users_address() -> None:
    env = ros_env.loopback_environment("http://127.0.0.1:11411", {"PATH": "/bin"})
    assert env == {"PATH": "/bin", "ROS_MASTER_URI": "http://127.0.0.1:11411", "ROS_IP": "127.0.0.1"}
    mine = ros_env.loopback_environment("http://127.0.0.1:1", {"ROS_HOSTNAME": "robot.lan"})
    assert "ROS_IP" not in mine and mine["ROS_HOSTNAME"] == "robot.lan"


def test_a_bad_master_uri_is_one_line() -> None:
    with pytest.raises(BraveError, match="--master-uri: must look like http://HOST:PORT"):
        master_uri_of("127.0.0.1:11311")
    assert master_uri_of("http://localhost:11311") == "http://localhost:11311"


@pytest.mark.skipif(bool(ros_env.missing_ros1(import_modules=False)), reason="ROS 1 not installed")
def test_ros1_without_a_master_says_how_to_start_one(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-c", "import sys; from brave6d.cli import main; sys.exit(main(sys.argv[1:]))",
                          "ros1", str(tmp_path), "--master-uri", "http://127.0.0.1:9"], capture_output=True,
                         text=True, cwd=ROOT, timeout=120,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))})
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        "brave6d ros1: error: no ROS master answers at http://127.0.0.1:9: start one ('rosmaster --core -p PORT', "
        "or roscore) or pass --start-master"]

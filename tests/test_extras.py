"""Optional worlds are extras (#33 item 2): the base install pulls no robot drivers, DDS or Slurm
tooling, a command that needs a missing extra says which one in one line, and the installed
distribution holds exactly one top-level package."""

from __future__ import annotations

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from brave6d.core.extras import EXTRAS, MissingExtra, require

ROOT = Path(__file__).resolve().parent.parent
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _names(requirements: list[str]) -> set[str]:
    return {r.split(";")[0].split("[")[0].split("=")[0].split(">")[0].split("<")[0].strip().lower()
            for r in requirements}


def test_the_base_install_leaves_the_optional_worlds_out() -> None:
    base = _names(PROJECT["dependencies"])
    for extra, packages in EXTRAS.items():
        assert not base & set(packages), f"{extra}'s {packages} are in the base dependencies"
        assert _names(PROJECT["optional-dependencies"][extra]) == set(packages), extra
    # ros2's wheels put ROS 2's std_msgs ... at the top level, shadowing Debian's ROS 1 for the ROS 1
    # node: `all` leaves them out, and scripts/setup.sh installs them in .venv-ros2
    assert PROJECT["optional-dependencies"]["all"] == [f"brave6d[{','.join(e for e in EXTRAS if e != 'ros2')}]"]
    assert "brave6d[all]" in PROJECT["optional-dependencies"]["test"]  # the README's test command installs all


@pytest.mark.parametrize(("argv", "module", "extra"), [
    (["dataset", "run", "DATASET", "WORK"], "submitit", "cluster"),
    (["ros2", "BUNDLE"], "rclpy", "ros2"),
])
def test_a_command_names_the_missing_extra(argv: list[str], module: str, extra: str, tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.cli import main

    monkeypatch.setitem(sys.modules, module, None)  # as if not installed: importing it raises ImportError
    args = [str(tmp_path / a) if a.isupper() else a for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"needs the '{extra}' extra" in err and f"pip install 'brave6d[{extra}]'" in err


@pytest.mark.parametrize(("opener", "module"), [("robot", "rtde_control"), ("camera", "depthai")])
def test_the_real_rig_names_the_robot_extra(opener: str, module: str, monkeypatch: pytest.MonkeyPatch) -> None:
    from brave6d.capture import oak_camera, ur_robot

    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(MissingExtra, match=r"needs the 'robot' extra .*pip install 'brave6d\[robot\]'"):
        ur_robot.rtde_interfaces("192.0.2.1") if opener == "robot" else oak_camera.OakCamera(width=64, height=48)


def test_require_returns_the_module_and_refuses_an_unknown_extra() -> None:
    assert require("json", "cuda", "x").dumps([1]) == "[1]"
    with pytest.raises(ValueError, match="unknown extra"):
        require("json", "gpu", "x")


@pytest.mark.slow
def test_the_wheel_has_one_top_level_package(tmp_path: Path) -> None:
    """``pip wheel .``: every file under ``brave6d/`` (and its dist-info), ``top_level.txt`` says ``brave6d``,
    and the viewer's files and the ROS message definitions travel with it."""
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                          str(tmp_path), str(ROOT)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    (wheel,) = tmp_path.glob("brave6d-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        info = next(n for n in names if n.endswith(".dist-info/RECORD")).rsplit("/", 1)[0]
        tops = {n.split("/", 1)[0] for n in names} - {info}
        top_level = [n for n in names if n.endswith("top_level.txt")]
        assert tops == {"brave6d"}, tops
        if top_level:  # setuptools writes it into the wheel's metadata only on some versions
            assert zf.read(top_level[0]).decode().split() == ["brave6d"]
    for needed in ("brave6d/serve/viewer/index.html", "brave6d/ros_interface/ros2/msg/ObjectEstimate.msg",
                   "brave6d/ros_interface/ros2/srv/Reset.srv", "brave6d/ros_interface/ros2/tf2_msgs/msg/TFMessage.msg",
                   "brave6d/ros_interface/ros1/srv", "brave6d/py.typed", "brave6d/core/extras.py"):
        assert any(n.startswith(needed) for n in names), needed

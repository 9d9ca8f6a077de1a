"""The rclpy tests (tests/ros2) run in the ROS 2 environment, ``.venv-ros2`` (scripts/setup.sh --with-ros2 makes
it: the ROS 2 wheels layered over .venv, apart from Debian's ROS 1 packages that other tests use).
This test runs them there as one pytest process and fails with their output when one fails; none
of them may skip."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
ROS2_PYTHON = Path(os.environ.get("BRAVE6D_ROS2_PYTHON", REPO / ".venv-ros2" / "bin" / "python"))


@pytest.mark.slow
def test_the_rclpy_suite_passes_in_the_ros2_environment() -> None:
    if not ROS2_PYTHON.exists():
        pytest.skip(f"{ROS2_PYTHON}: no ROS 2 environment (run 'bash scripts/setup.sh --with-ros2', which makes .venv-ros2)")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_", "FASTDDS_", "_ROS_WHEELS"))}
    out = subprocess.run([str(ROS2_PYTHON), "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/ros2"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=1500)
    tail = (out.stdout + out.stderr)[-6000:]
    print(tail)
    assert out.returncode == 0, tail
    summary = out.stdout.strip().splitlines()[-1]
    assert re.search(r"\d+ passed", summary) and "skipped" not in summary and "xfail" not in summary, summary

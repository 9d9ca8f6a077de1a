"""An agent in an environment of its own (docs/ROS.md, "An agent in its own environment"): a fresh venv with
nothing but the ROS 2 runtime wheels, numpy and the interfaces wheel (no brave6d, no torch) runs
the docs' minimal agent against ``brave6d ros2`` to a scored AR. The wheel is built by
``interfaces.py`` run by path with brave6d made unimportable, as where only the ROS 2 wheels are
installed. The venv's wheels come from the package index (pip's cache when warm)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
from conftest import REPO, NodeProcess

pytestmark = pytest.mark.slow

INTERFACES = REPO / "src" / "brave6d" / "ros_interface" / "ros2" / "interfaces.py"
EXAMPLE = REPO / "src" / "brave6d" / "ros_interface" / "ros2" / "example_agent.py"
#: What the minimal agent imports besides the interfaces (the wheel requires rclpy and the rest itself).
AGENT_WHEELS = ("ros-rclpy", "ros-rmw-fastrtps-cpp", "ros-sensor-msgs")


def plain_env() -> dict[str, str]:
    """This environment without ROS, loader or Python path variables: a user who set nothing."""
    return {k: v for k, v in os.environ.items()
            if not k.startswith(("ROS_", "RMW_", "AMENT_", "FASTDDS_", "FASTRTPS_", "_ROS_WHEELS"))
            and k not in ("LD_LIBRARY_PATH", "PYTHONPATH", "VIRTUAL_ENV")}


def pinned(names: tuple[str, ...]) -> list[str]:
    """``names`` as pinned in pyproject.toml's ros2 extra (the versions the node uses)."""
    extra = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]["ros2"]
    pins = {re.split(r"[=<>~]", spec)[0]: spec for spec in extra}
    return [pins[name] for name in names]


def run_checked(cmd: list[str], what: str, timeout: float = 600, **kwargs: object) -> str:
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=plain_env(), **kwargs)
    assert out.returncode == 0, f"{what} failed:\n{(out.stdout + out.stderr)[-4000:]}"
    return out.stdout


@pytest.fixture(scope="session")
def interfaces_wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel, written by interfaces.py run by path with ``brave6d`` unimportable."""
    out = tmp_path_factory.mktemp("interfaces_wheel")
    code = ("import runpy, sys; sys.modules['brave6d'] = None; "
            f"sys.argv = [{str(INTERFACES)!r}, '--wheel-dir', {str(out)!r}]; "
            f"runpy.run_path({str(INTERFACES)!r}, run_name='__main__')")
    start = time.perf_counter()
    run_checked([sys.executable, "-c", code], "the standalone wheel build")
    wheels = list(out.glob("brave6d_ros2_interfaces-*.whl"))
    assert len(wheels) == 1, wheels
    print(f"interfaces wheel built standalone in {time.perf_counter() - start:.1f} s")
    return wheels[0]


@pytest.fixture(scope="session")
def agent_python(interfaces_wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh venv (no system site-packages) with the agent's ROS 2 wheels, numpy and the interfaces wheel."""
    venv = tmp_path_factory.mktemp("agent") / "venv"
    start = time.perf_counter()
    base = getattr(sys, "_base_executable", sys.executable)  # the interpreter the wheel was built for
    run_checked([base, "-m", "venv", str(venv)], "python -m venv")
    python = venv / "bin" / "python"
    run_checked([str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                 *pinned(AGENT_WHEELS), "numpy", str(interfaces_wheel)], "pip install into the agent venv")
    print(f"agent venv made in {time.perf_counter() - start:.1f} s")
    return python


def test_an_agent_venv_with_only_ros2_wheels_and_the_interfaces_wheel_scores_an_episode(
        node: NodeProcess, agent_python: Path, tmp_path: Path) -> None:
    probe = ("import importlib.util, json; print(json.dumps({m: importlib.util.find_spec(m) is not None "
             "for m in ('brave6d', 'torch', 'rclpy', 'brave6d_msgs', 'tf2_msgs')}))")
    found = json.loads(run_checked([str(agent_python), "-c", probe], "the module probe").strip().splitlines()[-1])
    assert found == {"brave6d": False, "torch": False, "rclpy": True, "brave6d_msgs": True, "tf2_msgs": True}
    agent = tmp_path / "agent.py"  # copied, as the docs say
    agent.write_text(EXAMPLE.read_text())
    start = time.perf_counter()
    result = json.loads(run_checked([str(agent_python), str(agent)], "the minimal agent", timeout=300, cwd=tmp_path))
    print(f"minimal agent episode in {time.perf_counter() - start:.1f} s")
    assert result["ar"] == pytest.approx(1.0) and result["submitted"] == 1

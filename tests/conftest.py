"""Shared pytest configuration: hypothesis profiles and small fixtures."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from brave6d.core.runtime import prepare_process

# As the CLI does: OpenMP threads sleep while they wait (spinning teams of torch and numba slow
# each other down several times on a small machine) and numba stays off its TBB threading layer
# (it can hang at exit). Must run before torch / numba load.
prepare_process()

import matplotlib
import pytest
from hypothesis import HealthCheck, settings

matplotlib.use("Agg")

# Shared, noisy machines: no per-example deadline. CI is derandomised so that a red run can be
# reproduced exactly; locally hypothesis explores new examples each run.
settings.register_profile("ci", deadline=None, derandomize=True, max_examples=60,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", deadline=None, max_examples=100,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))

# A render server signs its episode logs with a key it makes on first use (~/.config/brave6d): the
# tests use a key file of their own, which the servers, nodes and commands they start inherit.
os.environ.setdefault("BRAVE6D_LOG_KEY", str(Path(tempfile.mkdtemp(prefix="brave6d-test-key-")) / "episode-log.key"))

REPO_ROOT = Path(__file__).resolve().parent.parent
DEMO_SPEC = REPO_ROOT / "data" / "demo" / "scene.yaml"


@pytest.fixture(scope="session")
def demo_spec_path() -> Path:
    return DEMO_SPEC


# The rclpy tests (tests/ros2) run in the ROS 2 environment (.venv-ros2, scripts/setup.sh): where
# rclpy is not importable they are not collected, and test_ros2_suite.py runs them there instead.
import importlib.util as _importlib_util  # noqa: E402

collect_ignore_glob = [] if _importlib_util.find_spec("rclpy") else ["ros2/*"]

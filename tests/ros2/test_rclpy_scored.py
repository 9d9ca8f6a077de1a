"""Scored and training mode over ROS 2: an rclpy agent that searches every answer, status, image
header, camera info and /tf message of an episode for the target's true pose (within 1 mm and 1
degree, :mod:`truth_search`) finds nothing from a node in its default, scored mode (its own process
on a domain of its own), and finds it from the session's node started with ``--training``."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import agent_on_own_node
from truth_search import target_truths, truth_found

from brave6d.core.transforms import look_at
from brave6d.ros_interface import Estimate
from brave6d.ros_interface.ros2.agent import Ros2Agent
from brave6d.serve import load_bundle

pytestmark = pytest.mark.slow

SCORED_DOMAIN = 61
FREE2 = look_at((0.30, 0.10, 0.35), (0.46, 0.0, 0.01))


@pytest.fixture(scope="module")
def scored_agent(bundle_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ros2Agent]:
    with agent_on_own_node(bundle_dir, tmp_path_factory.mktemp("ros2_scored_logs"), SCORED_DOMAIN,
                           "scored_agent") as agent:
        yield agent


def play(agent: Ros2Agent) -> tuple[list[Any], list[np.ndarray]]:
    """A seeded episode (reset, set_pose, move, submit): everything received, and the camera poses."""
    views = [agent.reset(target="cube_red", seed=3), agent.set_pose(FREE2), agent.move([0.0, 0.0, 0.02], [0, 0.1, 0])]
    result = agent.submit([Estimate(1, np.eye(4), 1.0)])
    replies: list[Any] = []
    for v in views:
        replies += [v.status, v.step, v.messages, v.ground_truth]
    replies.append(result)
    return replies, [v.world_T_cam for v in views]


@pytest.mark.parametrize("mode", ["scored", "training"])
def test_ros2_agent_finds_the_truth_only_in_training_mode(mode: str, request: pytest.FixtureRequest,
                                                          bundle_dir: Path) -> None:
    agent = request.getfixturevalue("scored_agent" if mode == "scored" else "agent")
    replies, cameras = play(agent)
    world_T_obj = next(o.world_T_obj for o in load_bundle(bundle_dir).objects if o.name == "cube_red")
    found = truth_found(replies, target_truths(world_T_obj, cameras))
    statuses = [r for r in replies if isinstance(r, dict) and "stamp_ns" in r]
    assert [s["mode"] for s in statuses] == [mode] * 3 and replies[-1]["mode"] == mode
    assert all(s["target"]["obj_id"] == 1 and s["target"]["name"] == "cube_red" for s in statuses)
    if mode == "scored":
        assert found == [], f"scored mode: the target's true pose is in {found}"
        assert all(s["objects"] == [] and s["target"]["frame"] is None for s in statuses)
        steps = [r for r in replies if hasattr(r, "target_frame")]
        assert [s.target_frame for s in steps] == [""] * 3 and [s.target_obj_id for s in steps] == [1] * 3
        tf_children = {t.child_frame_id for r in replies if isinstance(r, dict) and "tf" in r for t in r["tf"].transforms}
        assert tf_children == {"brave6d_camera_optical_frame"}
        json.dumps(replies[-1])
    else:
        assert found, "training mode: the search found no true pose (it cannot fail?)"


def test_the_docs_oracle_agent_says_it_needs_training_mode(scored_agent: Ros2Agent) -> None:
    """docs/ROS.md's minimal agent reads the gt/ frames: against a scored node it stops at once, saying so."""
    import os
    import subprocess
    import sys

    from conftest import REPO

    source = (REPO / "src" / "brave6d" / "ros_interface" / "ros2" / "example_agent.py").read_text()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_", "FASTDDS_"))}
    env["ROS_DOMAIN_ID"] = str(SCORED_DOMAIN)
    out = subprocess.run([sys.executable, "-c", source], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode != 0 and "start it with 'brave6d ros2 BUNDLE --training'" in out.stderr, out.stderr[-2000:]

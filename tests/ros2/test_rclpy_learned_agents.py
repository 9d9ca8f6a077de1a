"""The same agent objects play over ROS 2 as over HTTP: the Protocol-only detector and pose estimator
of tests/test_estimator_protocol.py drive learned-static and learned-active (RGB-only and with the
node's depth) through an rclpy
:class:`~brave6d.ros_interface.ros2.agent.Ros2Agent` against ``brave6d ros2`` in its default, scored
mode (:class:`~brave6d.ros_interface.episode_clients.Ros2EpisodeClient`), each submission is scored by
the node, and the scores equal the HTTP client's run for the same seeds."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import agent_on_own_node
from test_estimator_protocol import make_detector, make_pose_estimator

from brave6d.core.errors import BraveError
from brave6d.evaluation.agents import (
    LEARNED_ACTIVE_AGENT,
    LEARNED_ACTIVE_DEPTH_AGENT,
    LEARNED_AGENTS,
    LEARNED_STATIC_AGENT,
    LEARNED_STATIC_DEPTH_AGENT,
    AgentSetup,
    make_agent,
    run_episode,
)

pytestmark = pytest.mark.slow

DOMAIN = 63
AGENTS = list(LEARNED_AGENTS)  # RGB-only static and active, then with depth
ACTIVE = {LEARNED_ACTIVE_AGENT, LEARNED_ACTIVE_DEPTH_AGENT}
WIDTH, HEIGHT = 160, 120  # the node's images (--width/--height): quick, and the HTTP run's at width 160


@pytest.fixture(scope="module")
def ros_client(bundle_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    from brave6d.ros_interface import Ros2EpisodeClient

    with agent_on_own_node(bundle_dir, tmp_path_factory.mktemp("ros2_learned_logs"), DOMAIN, "learned_agent",
                           "--width", str(WIDTH), "--height", str(HEIGHT)) as agent:
        yield Ros2EpisodeClient(agent, bundle_dir)


def test_the_learned_agents_play_a_users_estimator_over_ros2_as_over_http(ros_client: Any, bundle_dir: Path,
                                                                          tmp_path: Path) -> None:
    from brave6d.evaluation.demo import run_baselines
    from brave6d.serve import load_bundle

    setup = AgentSetup(detector=make_detector(), pose_estimator=make_pose_estimator())
    players = [make_agent(name, ros_client, setup) for name in AGENTS]
    ros = [run_episode(ros_client, agent, obj.gt_id, seed=obj.gt_id, width=WIDTH, height=HEIGHT)
           for obj in load_bundle(bundle_dir).objects for agent in players]
    http = run_baselines(bundle_dir, tmp_path, device="cpu", width=WIDTH, agents=AGENTS,
                         setup=AgentSetup(detector=make_detector(), pose_estimator=make_pose_estimator()))
    ros_ar = {(o.agent, o.target): o.submission["ar"] for o in ros}
    http_ar = {(e.episode.agent, e.episode.target.name): e.scores.ar for e in http.board.episodes}
    print({"ros2": ros_ar, "http": http_ar})  # the figures, for a failing run's log
    assert all(o.submission["mode"] == "scored" and o.submission["submitted"] == 1 for o in ros)
    assert any(ar > 0.0 for ar in ros_ar.values())  # scored, not all zero
    assert all((o.adjustments >= 2) == (o.agent in ACTIVE) for o in ros)  # only the active ones moved
    # the ROS depth image reached the -depth agents' estimator: above their RGB-only twins
    assert sum(ar for (a, _), ar in ros_ar.items() if a == LEARNED_STATIC_DEPTH_AGENT) > \
        sum(ar for (a, _), ar in ros_ar.items() if a == LEARNED_STATIC_AGENT)
    assert [(o.agent, o.target, o.adjustments) for o in ros] == [(o.agent, o.target, o.adjustments) for o in http.outcomes]
    assert ros_ar == pytest.approx(http_ar, abs=1e-9)
    for r, h in zip(ros, http.outcomes, strict=True):  # poses travel as quaternions over ROS: equal to rounding
        np.testing.assert_allclose(r.estimates[0].cam_T_obj, h.estimates[0].cam_T_obj, atol=1e-9)


def test_a_view_over_ros2_is_the_http_view(ros_client: Any, bundle_dir: Path) -> None:
    """The same seeded start over ROS 2 and HTTP: the same image, the same depth (no data 0, not
    REP 118's NaN: what the estimators' interface promises), K and camera pose."""
    from brave6d.serve import BraveClient, ServerThread, create_app, load_bundle

    ros = ros_client.reset(target=1, width=WIDTH, height=HEIGHT, seed=0).observation
    ros_client.ros.close()
    with ServerThread(create_app(load_bundle(bundle_dir), device="cpu", warm_up=False)) as server, \
            BraveClient(server.url) as client:
        http = client.reset(target=1, width=WIDTH, height=HEIGHT, seed=0).observation
    assert (http.depth == 0).any()  # the start view has pixels without depth
    np.testing.assert_array_equal(ros.rgb, http.rgb)
    np.testing.assert_array_equal(ros.depth, http.depth)
    np.testing.assert_allclose(ros.K, http.K, atol=1e-9)
    np.testing.assert_allclose(ros.world_T_cam, http.world_T_cam, atol=1e-9)


def test_the_ros2_client_refuses_another_image_size_in_one_line(ros_client: Any) -> None:
    with pytest.raises(BraveError, match=f"serves {WIDTH}x{HEIGHT} images") as info:
        ros_client.reset(target=1, width=320, height=240, seed=0)
    assert "\n" not in str(info.value)
    assert ros_client.bundle()["objects"] and "world_T_obj" not in ros_client.bundle()["objects"][0]  # scored: no truth

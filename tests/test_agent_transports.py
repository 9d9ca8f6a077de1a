"""The same agent objects play over gym as over HTTP: the Protocol-only detector and pose estimator
of test_estimator_protocol drive learned-static and learned-active, RGB-only and with the served
depth, through a scored
:class:`~brave6d.serve.BraveEnv` (:class:`~brave6d.evaluation.agents.transports.GymEpisodeClient`),
are scored from the episode logs, and score what the HTTP client's run scores for the same seeds,
every estimate equal; a ROS depth image becomes the served depth (ROS 2 and ROS 1:
tests/ros2/test_rclpy_learned_agents.py, tests/test_ros1_learned_agents.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
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
AGENTS = list(LEARNED_AGENTS)  # RGB-only static and active, then with depth
ACTIVE = {LEARNED_ACTIVE_AGENT, LEARNED_ACTIVE_DEPTH_AGENT}
WIDTH = 160


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.serve import make_synthetic_bundle

    return make_synthetic_bundle(tmp_path_factory.mktemp("transports"), n_gaussians=20_000)


def play_over_gym(bundle_dir: Path, logs: Path) -> tuple[list, object]:
    """run_baselines' episodes (every object, seed gt_id, WIDTH wide) played through a scored BraveEnv."""
    from brave6d.evaluation.agents.transports import GymEpisodeClient
    from brave6d.evaluation.metrics import models_from_bundle, read_episodes, score_episodes
    from brave6d.serve import SCORED, BraveEnv, ServerThread, create_app, load_bundle

    bundle = load_bundle(bundle_dir)
    height = max(16, round(WIDTH * bundle.render.height / bundle.render.width))
    setup = AgentSetup(detector=make_detector(), pose_estimator=make_pose_estimator())
    outcomes = []
    with ServerThread(create_app(bundle, device="cpu", log_dir=logs, mode=SCORED)) as server:
        env = BraveEnv(server.url, mode=SCORED)
        try:
            client = GymEpisodeClient(env)
            players = [make_agent(name, client, setup) for name in AGENTS]
            for obj in bundle.objects:
                for agent in players:
                    outcomes.append(run_episode(client, agent, obj.gt_id, seed=obj.gt_id, width=WIDTH, height=height))
        finally:
            env.close()
    board = score_episodes(read_episodes([logs]), models_from_bundle(bundle, {o.obj_id for o in bundle.objects}),
                           mode=SCORED)
    return outcomes, board


def test_the_learned_agents_play_a_users_estimator_over_gym_as_over_http(bundle_dir: Path, tmp_path: Path) -> None:
    from brave6d.evaluation.demo import run_baselines

    gym_outcomes, gym_board = play_over_gym(bundle_dir, tmp_path / "gym" / "episodes")
    http = run_baselines(bundle_dir, tmp_path / "http", device="cpu", width=WIDTH, agents=AGENTS,
                         setup=AgentSetup(detector=make_detector(), pose_estimator=make_pose_estimator()))
    gym_ar = {a.agent: a.ar for a in gym_board.agents}
    http_ar = {a.agent: a.ar for a in http.board.agents}
    print({"gym": gym_ar, "http": http_ar})  # the figures, for a failing run's log
    assert not gym_board.not_ranked and set(gym_ar) == set(AGENTS)  # scored mode: every episode ranked
    assert all(a.episodes == 2 for a in gym_board.agents)
    assert gym_ar[LEARNED_STATIC_AGENT] > 0.0 or gym_ar[LEARNED_ACTIVE_AGENT] > 0.0  # it was scored, not all zero
    # the served depth reached the -depth agents' estimator: above their RGB-only twins (the cube's centre)
    assert gym_ar[LEARNED_STATIC_DEPTH_AGENT] > gym_ar[LEARNED_STATIC_AGENT]
    # the active agent moved (the cube is ~8 px at 160 px wide), the static one did not
    assert all((o.adjustments >= 2) == (o.agent in ACTIVE) for o in gym_outcomes)
    # the same seeds over HTTP: the same moves, every estimate and the AR equal
    assert gym_ar == http_ar
    assert [(o.agent, o.target, o.adjustments) for o in gym_outcomes] == \
        [(o.agent, o.target, o.adjustments) for o in http.outcomes]
    for g, h in zip(gym_outcomes, http.outcomes, strict=True):
        assert len(g.estimates) == len(h.estimates) == 1
        np.testing.assert_array_equal(g.estimates[0].cam_T_obj, h.estimates[0].cam_T_obj)


def test_the_gym_client_refuses_a_scene_and_a_truncated_episode_in_one_line(bundle_dir: Path, tmp_path: Path) -> None:
    from brave6d.evaluation.agents.transports import GymEpisodeClient
    from brave6d.serve import SCORED, BraveEnv, ServerThread, create_app, load_bundle

    with ServerThread(create_app(load_bundle(bundle_dir), device="cpu", log_dir=tmp_path, mode=SCORED)) as server:
        env = BraveEnv(server.url, mode=SCORED, max_steps=1)
        try:
            client = GymEpisodeClient(env)
            with pytest.raises(BraveError, match="one scene") as info:
                client.reset(target=1, width=WIDTH, height=120, seed=0, scene="other")
            assert "\n" not in str(info.value)
            step = client.reset(target=1, width=WIDTH, height=120, seed=0)
            assert step.action == "reset" and step.target["gt_id"] == 1 and step.observation.rgb.shape == (120, WIDTH, 3)
            with pytest.raises(BraveError, match="max_steps=1") as info:
                client.set_pose(step.observation.world_T_cam)
            assert "\n" not in str(info.value)
        finally:
            env.close()


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.float32, hnp.array_shapes(min_dims=2, max_dims=2, max_side=6),
                  elements=st.floats(width=32, allow_nan=True, allow_infinity=True)))
def test_a_ros_depth_image_becomes_the_served_depth(depth: np.ndarray) -> None:
    """REP 118's NaN (and any other non-depth: inf, 0, negative) is the server's 0; every positive
    finite depth passes unchanged."""
    from brave6d.ros_interface.episode_clients import served_depth

    out = served_depth(depth)
    valid = np.isfinite(depth) & (depth > 0)
    assert out.dtype == np.float32 and out.shape == depth.shape and np.isfinite(out).all()
    np.testing.assert_array_equal(out[valid], depth[valid])
    assert (out[~valid] == 0).all()

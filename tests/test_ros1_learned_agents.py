"""The same agent objects play over ROS 1 as over HTTP: the Protocol-only detector and pose estimator
of test_estimator_protocol drive learned-static and learned-active (RGB-only and with the node's
depth) through a rospy
:class:`~brave6d.ros_interface.ros1.client.Ros1Client` against ``brave6d ros1`` in its default, scored
mode (:class:`~brave6d.ros_interface.episode_clients.Ros1EpisodeClient`, tests/ros1_learned_player.py),
each submission is scored by the node, and the scores equal the HTTP client's run for the same seeds;
a start view over ROS 1 is the HTTP view (image, depth, K, pose).
Skipped, naming the Debian packages, when ROS 1 is absent."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_estimator_protocol import make_detector, make_pose_estimator
from test_ros1_e2e import MISSING, ROOT, _env, _stop

from brave6d.evaluation.agents import (
    LEARNED_ACTIVE_AGENT,
    LEARNED_ACTIVE_DEPTH_AGENT,
    LEARNED_AGENTS,
    LEARNED_STATIC_AGENT,
    LEARNED_STATIC_DEPTH_AGENT,
    AgentSetup,
)
from brave6d.ros_interface.ros1.ros_env import loopback_environment

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(bool(MISSING), reason="ROS 1 not installed: apt-get install " + " ".join(MISSING))]
AGENTS = list(LEARNED_AGENTS)  # RGB-only static and active, then with depth
ACTIVE = {LEARNED_ACTIVE_AGENT, LEARNED_ACTIVE_DEPTH_AGENT}
WIDTH, HEIGHT = 160, 120


def test_the_learned_agents_play_a_users_estimator_over_ros1_as_over_http(tmp_path: Path) -> None:
    from brave6d.evaluation.demo import run_baselines
    from brave6d.ros_interface.ros1.master import RosMaster
    from brave6d.serve import make_synthetic_bundle

    bundle_dir = make_synthetic_bundle(tmp_path / "scene", n_gaussians=20_000)
    node = None
    with RosMaster(log_file=tmp_path / "rosmaster.log") as master:
        env = {**_env(), **loopback_environment(master.uri)}
        try:
            node = subprocess.Popen(
                [sys.executable, "-c", "import sys; from brave6d.cli import main; sys.exit(main(sys.argv[1:]))",
                 "ros1", str(bundle_dir), "--master-uri", master.uri, "--device", "cpu", "--log-dir",
                 str(tmp_path / "ros_episodes"), "--width", str(WIDTH), "--height", str(HEIGHT)],
                env=env, cwd=ROOT, stdout=open(tmp_path / "node.log", "wb"), stderr=subprocess.STDOUT,
                start_new_session=True)
            player = subprocess.run([sys.executable, str(ROOT / "tests" / "ros1_learned_player.py"), str(bundle_dir),
                                     str(WIDTH), str(HEIGHT), str(tmp_path / "ros.json")], env=env, cwd=ROOT,
                                    capture_output=True, text=True, timeout=300, start_new_session=True)
            assert player.returncode == 0, player.stdout[-3000:] + player.stderr[-3000:] + \
                (tmp_path / "node.log").read_text(errors="replace")[-3000:]
        finally:
            if node is not None:
                _stop(node)
    record = json.loads((tmp_path / "ros.json").read_text(encoding="utf-8"))
    ros = record["outcomes"]
    http = run_baselines(bundle_dir, tmp_path / "http", device="cpu", width=WIDTH, agents=AGENTS,
                         setup=AgentSetup(detector=make_detector(), pose_estimator=make_pose_estimator()))
    ros_ar = {(o["agent"], o["target"]): o["ar"] for o in ros}
    http_ar = {(e.episode.agent, e.episode.target.name): e.scores.ar for e in http.board.episodes}
    print({"ros1": ros_ar, "http": http_ar})  # the figures, for a failing run's log
    assert all(o["mode"] == "scored" and o["submitted"] == 1 for o in ros)
    assert any(ar > 0.0 for ar in ros_ar.values())  # scored, not all zero
    assert all((o["adjustments"] >= 2) == (o["agent"] in ACTIVE) for o in ros)  # only the active ones moved
    # the ROS depth image reached the -depth agents' estimator: above their RGB-only twins
    assert sum(ar for (a, _), ar in ros_ar.items() if a == LEARNED_STATIC_DEPTH_AGENT) > \
        sum(ar for (a, _), ar in ros_ar.items() if a == LEARNED_STATIC_AGENT)
    assert [(o["agent"], o["target"], o["adjustments"]) for o in ros] == \
        [(o.agent, o.target, o.adjustments) for o in http.outcomes]
    assert ros_ar == pytest.approx(http_ar, abs=1e-9)
    for r, h in zip(ros, http.outcomes, strict=True):  # poses travel as quaternions over ROS: equal to rounding
        np.testing.assert_allclose(np.asarray(r["cam_T_obj"][0]), h.estimates[0].cam_T_obj, atol=1e-9)
    # the same seeded start over HTTP: the same image, depth (no data 0, not REP 118's NaN), K and pose
    from brave6d.serve import BraveClient, ServerThread, create_app, load_bundle

    ros_view = np.load(tmp_path / "ros.npz")
    with ServerThread(create_app(load_bundle(bundle_dir), device="cpu", warm_up=False)) as server, \
            BraveClient(server.url) as client:
        view = client.reset(target=1, width=WIDTH, height=HEIGHT, seed=0).observation
    assert (view.depth == 0).any()  # the start view has pixels without depth
    np.testing.assert_array_equal(ros_view["rgb"], view.rgb)
    np.testing.assert_array_equal(ros_view["depth"], view.depth)
    np.testing.assert_allclose(ros_view["K"], view.K, atol=1e-9)
    np.testing.assert_allclose(ros_view["world_T_cam"], view.world_T_cam, atol=1e-9)
    refusal = record["size_refusal"]
    assert refusal is not None and f"serves {WIDTH}x{HEIGHT} images" in refusal and "\n" not in refusal, refusal

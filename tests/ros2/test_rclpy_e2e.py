"""``brave6d ros2`` end to end with real rclpy: the node as its own process (the real CLI) on a
synthetic 640x480 bundle, ROS 2's defaults (domain 0, no variable set), and an rclpy agent in this
process that resets, teleports (one refused move into the scene's collision box), moves, reads
images, camera info and tf with sensor-data and with default QoS, submits, and gets a scored
result equal to the one the HTTP API gives for the same actions. The docs' minimal agent runs as a
third process, and an agent that leaves mid-episode does not disturb the node."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import HEIGHT, REPO, WIDTH, NodeProcess
from fastapi.testclient import TestClient

from brave6d.core.transforms import look_at, make_transform
from brave6d.ros_interface import EpisodeScorer, Estimate, gt_frame, matrix_to_pose, pose_to_matrix
from brave6d.ros_interface.ros2.agent import Ros2Agent
from brave6d.ros_interface.ros2.defaults import DEFAULT_TWIST_DURATION_S
from brave6d.serve import load_bundle
from brave6d.serve.app import ServerLimits, create_app
from brave6d.serve.client import decode_step

pytestmark = pytest.mark.slow

FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
FREE2 = look_at((0.30, 0.10, 0.35), (0.46, 0.0, 0.01))
IN_POST = look_at((0.30, 0.25, 0.15), (0.46, 0.0, 0.01))  # inside the synthetic scene's "post" box
TWIST = ([0.0, 0.0, 0.02], [0.0, 0.1, 0.0])  # camera frame, for the node's twist duration


def over_ros(T: np.ndarray) -> np.ndarray:
    """The pose the node receives for ``T`` (through a geometry_msgs/Pose quaternion)."""
    return pose_to_matrix(*matrix_to_pose(T))


def http_episode(bundle_dir: Path, log_dir: Path, estimates_from: Any) -> tuple[list[Any], dict, Path]:
    """The same actions through the HTTP API; (steps, submit reply, log path)."""
    app = create_app(load_bundle(bundle_dir), device="cpu", log_dir=log_dir, limits=ServerLimits(max_episodes=4),
                     mode="training")
    with TestClient(app, base_url="http://localhost") as client:
        r = client.post("/episodes", json={"target": "cube_red", "start": {"world_T_cam": over_ros(FREE).tolist()},
                                           "agent": "ros-test"})
        assert r.status_code == 201, r.text
        steps = [decode_step(r.json())]
        eid = steps[0].message.episode_id
        for T in (over_ros(FREE2), over_ros(IN_POST)):
            r = client.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": T.tolist()}})
            steps.append(decode_step(r.json()))
        r = client.post(f"/episodes/{eid}/move", json={"linear": TWIST[0], "angular": TWIST[1],
                                                       "duration": DEFAULT_TWIST_DURATION_S, "frame": "camera"})
        steps.append(decode_step(r.json()))
        estimates = estimates_from(steps[-1])
        r = client.post(f"/episodes/{eid}/estimates", json={"estimates": [
            {"obj_id": e.obj_id, "R": e.cam_T_obj[:3, :3].reshape(-1).tolist(), "t_m": e.cam_T_obj[:3, 3].tolist(),
             "score": e.score} for e in estimates]})
        assert r.status_code == 200, r.text
    return steps, r.json(), log_dir / f"{eid}.jsonl"


def test_an_episode_over_ros2_scores_as_over_http(agent: Ros2Agent, node: NodeProcess, bundle_dir: Path,
                                                  tmp_path: Path) -> None:
    bundle = load_bundle(bundle_dir)
    views = [agent.reset(target="cube_red", start=FREE)]
    views += [agent.set_pose(FREE2), agent.set_pose(IN_POST), agent.move(*TWIST)]
    first, moved, refused, twisted = views

    # counters and refusal, as the episode manager decides them
    assert [v.step.accepted for v in views] == [True, True, False, True]
    assert [v.step.adjustments for v in views] == [0, 1, 1, 2]
    assert refused.status["refusal"]["box"] == "post" and refused.step.refusal
    assert first.status["target"] == {"name": "cube_red", "obj_id": 1, "gt_id": 0, "frame": gt_frame("cube_red", 0)}
    assert (first.step.target_frame, first.step.target_obj_id) == (gt_frame("cube_red", 0), 1)
    # the refused move answers the previous view under a new stamp
    np.testing.assert_array_equal(refused.rgb, moved.rgb)
    assert refused.status["stamp_ns"] > moved.status["stamp_ns"]

    # images (640x480), camera info and tf, all under the step's stamp
    for v in views:
        assert v.rgb.shape == (HEIGHT, WIDTH, 3) and v.rgb.dtype == np.uint8
        assert v.depth_m.shape == (HEIGHT, WIDTH) and v.depth_m.dtype == np.float32
        assert np.all(np.isnan(v.depth_m) | (v.depth_m > 0))  # REP 118: NaN = no data, never 0
        assert np.isfinite(v.depth_m).mean() > 0.5
        np.testing.assert_allclose(v.K, bundle.camera.K)
        np.testing.assert_allclose(v.world_T_cam, np.asarray(v.status["world_T_cam"]), atol=1e-9)
        assert set(v.ground_truth) == {gt_frame(o.name, o.gt_id) for o in bundle.objects}
        info = v.messages["rgb_info"]
        assert (info.width, info.height, info.header.frame_id) == (WIDTH, HEIGHT, "brave6d_camera_optical_frame")
    np.testing.assert_allclose(moved.world_T_cam, over_ros(FREE2), atol=1e-9)
    for o in bundle.objects:
        np.testing.assert_allclose(first.ground_truth[gt_frame(o.name, o.gt_id)], o.world_T_obj, atol=1e-9)

    # estimates: the target 1 cm off, the other cube exact (ground truth from the final view's tf)
    def estimates_from(view_truth: dict[int, np.ndarray]) -> list[Estimate]:
        truth = dict(view_truth)
        truth[1] = truth[1] @ make_transform(np.eye(3), [0.01, 0.0, 0.0])
        return [Estimate(obj_id, T, 1.0) for obj_id, T in sorted(truth.items())]

    ros_truth = {o.obj_id: twisted.cam_T_gt(gt_frame(o.name, o.gt_id)) for o in bundle.objects}
    result = agent.submit(estimates_from(ros_truth))

    steps, http_reply, http_log = http_episode(
        bundle_dir, tmp_path, lambda s: estimates_from({o.obj_id: np.asarray(o.cam_T_obj)
                                                        for o in s.message.observation.objects}))
    # the same views, bit for bit, and the same counters
    for v, s in zip(views, steps):
        assert (v.step.accepted, v.step.collided, v.step.adjustments, v.step.step) == (
            s.message.accepted, s.message.collided, s.message.adjustments, s.message.step)
        np.testing.assert_array_equal(v.rgb, s.observation.rgb)
        np.testing.assert_array_equal(np.nan_to_num(v.depth_m, nan=0.0), s.observation.depth)
        np.testing.assert_allclose(v.world_T_cam, np.asarray(s.message.observation.world_T_cam), atol=1e-9)
    # the same score
    http_score = EpisodeScorer().score(http_log, bundle)
    assert (result["ar"], result["ar_vsd"], result["ar_mssd"], result["ar_mspd"]) == pytest.approx(
        (http_score.ar, http_score.ar_vsd, http_score.ar_mssd, http_score.ar_mspd), abs=1e-12)
    assert 0.0 < result["ar"] < 1.0  # 1 cm off a 20 mm cube: some thresholds pass, some fail
    assert (result["adjustments"], result["steps"], result["refusals"], result["submitted"]) == (
        http_reply["adjustments"], http_reply["steps"], http_reply["refusals"], 2) == (2, 3, 1, 2)
    assert Path(result["log"]).parent == node.log_dir


def test_a_default_qos_agent_gets_every_image_too(node: NodeProcess, context: Any) -> None:
    """Images are published reliably: a default-QoS (reliable) subscriber matches and gets each step."""
    reliable = Ros2Agent(timeout_s=60, context=context, qos="default", node_name="reliable_agent")
    try:
        reliable.wait_until_connected(timeout_s=60)
        views = [reliable.reset(seed=3), reliable.set_pose(FREE2), reliable.move(*TWIST)]
        assert all(v.rgb.shape == (HEIGHT, WIDTH, 3) and v.depth_m.shape == (HEIGHT, WIDTH) for v in views)
        assert len({v.step.stamp.nanosec + 10**9 * v.step.stamp.sec for v in views}) == 3
        reliable.close()
    finally:
        reliable.destroy()


def test_the_docs_minimal_agent_runs_an_episode_on_ros2_defaults(node: NodeProcess) -> None:
    """docs/ROS.md's agent, copied as a user would, in its own process with no ROS variable set."""
    docs = (REPO / "docs" / "ROS.md").read_text()
    source = (REPO / "src" / "brave6d" / "ros_interface" / "ros2" / "example_agent.py").read_text()
    assert "python -m brave6d.ros_interface.ros2.example_agent" in docs
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_", "FASTDDS_"))}
    out = subprocess.run([sys.executable, "-c", source], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout)
    assert result["ar"] == pytest.approx(1.0) and result["adjustments"] == 1 and result["submitted"] == 1


def test_an_agent_that_leaves_mid_episode_leaves_the_node_serving(node: NodeProcess, agent: Ros2Agent) -> None:
    script = textwrap.dedent("""
        import sys, time, rclpy
        from brave6d.ros_interface.ros2.agent import Ros2Agent
        rclpy.init()
        a = Ros2Agent(timeout_s=60, node_name="leaving_agent")
        a.wait_until_connected(60)
        a.reset(seed=5)
        print("reset", flush=True)
        time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "reset", proc.stderr
        proc.send_signal(signal.SIGKILL)  # gone without a goodbye, mid-episode
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    view = agent.reset(target="cube_red", start=FREE)
    assert view.step.accepted and agent.submit([])["submitted"] == 0
    assert "Traceback" not in node.output()


def test_a_mismatched_subscriber_gets_rclpys_warning_naming_the_policy(node: NodeProcess) -> None:
    """A latched (TRANSIENT_LOCAL) image subscriber, as a ROS 1 habit, cannot match the node's volatile
    publisher: rclpy says so, naming the policy, instead of silently receiving nothing."""
    script = textwrap.dedent("""
        import time, rclpy
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from sensor_msgs.msg import Image
        rclpy.init()
        n = rclpy.create_node("latched_agent")
        n.create_subscription(Image, "/brave6d_sim/rgb/image_raw", lambda m: None,
                              QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        end = time.monotonic() + 8
        while time.monotonic() < end:
            rclpy.spin_once(n, timeout_sec=0.2)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout + out.stderr
    assert "incompatible QoS" in text and "DURABILITY" in text, text[-2000:]

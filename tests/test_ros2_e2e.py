"""``brave6d ros2`` end to end: the node as its own process (the real CLI) on a synthetic bundle,
DDS on loopback with a random domain id, and a DDS test agent in this process that resets, moves
(one refused move into the scene's collision box), reads images, camera info and tf, submits, and
gets a scored result equal to the one the HTTP API gives for the same actions."""

from __future__ import annotations

import os
import random
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from fastapi.testclient import TestClient  # noqa: E402

from brave6d.core.transforms import look_at, make_transform  # noqa: E402
from brave6d.ros_interface import EpisodeScorer, Estimate, gt_frame, matrix_to_pose, pose_to_matrix  # noqa: E402
from brave6d.ros_interface.ros2.agent import AgentError, Ros2Agent  # noqa: E402
from brave6d.ros_interface.ros2.dds import DdsDomain  # noqa: E402
from brave6d.ros_interface.ros2.defaults import DEFAULT_TWIST_DURATION_S  # noqa: E402
from brave6d.serve import load_bundle, make_synthetic_bundle  # noqa: E402
from brave6d.serve.app import ServerLimits, create_app  # noqa: E402
from brave6d.serve.client import decode_step  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
FREE2 = look_at((0.30, 0.10, 0.35), (0.46, 0.0, 0.01))
IN_POST = look_at((0.30, 0.25, 0.15), (0.46, 0.0, 0.01))  # inside the synthetic scene's "post" box
TWIST = ([0.0, 0.0, 0.02], [0.0, 0.1, 0.0])  # camera frame, for the node's twist duration


def over_ros(T: np.ndarray) -> np.ndarray:
    """The pose the node receives for ``T`` (through a geometry_msgs/Pose quaternion)."""
    return pose_to_matrix(*matrix_to_pose(T))


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_synthetic_bundle(tmp_path_factory.mktemp("ros2_scene"), n_gaussians=4000, width=160, height=120)


@pytest.fixture(scope="module")
def node(bundle_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Any:
    """``brave6d ros2`` in a subprocess; yields (domain id, its log dir)."""
    domain_id = random.randrange(10, 230)
    log_dir = tmp_path_factory.mktemp("ros2_logs")
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.Popen([sys.executable, "-m", "brave6d.cli", "ros2", str(bundle_dir), "--domain-id",
                             str(domain_id), "--device", "cpu", "--log-dir", str(log_dir), "--agent", "ros-test"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        yield domain_id, log_dir, proc
    finally:
        proc.terminate()
        try:
            out, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        print(out[-3000:])


@pytest.fixture(scope="module")
def agent(node: Any) -> Any:
    domain_id, _, proc = node
    with DdsDomain(domain_id) as dds:
        a = Ros2Agent(dds, timeout_s=120)
        try:
            a.wait_until_connected(timeout_s=120)
        except AgentError:
            proc.terminate()
            raise AssertionError(f"the node did not come up: {proc.communicate(timeout=30)[0][-2000:]}") from None
        yield a


def http_episode(bundle_dir: Path, log_dir: Path, estimates_from: Any) -> tuple[list[Any], dict, Path]:
    """The same actions through the HTTP API; (steps, submit reply, log path)."""
    bundle = load_bundle(bundle_dir)
    app = create_app(bundle, device="cpu", log_dir=log_dir, limits=ServerLimits(max_episodes=4))
    with TestClient(app, base_url="http://localhost") as client:
        r = client.post("/episodes", json={"target": "cube_red", "start": {"world_T_cam": FREE.tolist()},
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


@pytest.mark.slow
def test_an_episode_over_ros2_scores_as_over_http(agent: Ros2Agent, node: Any, bundle_dir: Path,
                                                  tmp_path: Path) -> None:
    bundle = load_bundle(bundle_dir)
    views = [agent.reset(target="cube_red", start=FREE)]
    views += [agent.set_pose(FREE2), agent.set_pose(IN_POST), agent.twist(*TWIST)]
    first, moved, refused, twisted = views

    # counters and refusal, as the episode manager decides them
    assert [v.status["accepted"] for v in views] == [True, True, False, True]
    assert [v.status["adjustments"] for v in views] == [0, 1, 1, 2]
    assert refused.status["refusal"]["box"] == "post"
    assert first.status["target"] == {"name": "cube_red", "obj_id": 1, "gt_id": 0, "frame": gt_frame("cube_red", 0)}
    # the refused move answers the previous view under a new stamp
    np.testing.assert_array_equal(refused.rgb, moved.rgb)
    assert refused.status["stamp_ns"] > moved.status["stamp_ns"]

    # images, camera info and tf
    for v in views:
        assert v.rgb.shape == (120, 160, 3) and v.rgb.dtype == np.uint8
        assert v.depth_m.shape == (120, 160) and v.depth_m.dtype == np.float32
        assert np.all(np.isnan(v.depth_m) | (v.depth_m > 0))  # REP 118: NaN = no data, never 0
        np.testing.assert_allclose(v.K, bundle.camera.K)
        np.testing.assert_allclose(v.world_T_cam, np.asarray(v.status["world_T_cam"]), atol=1e-9)
        assert set(v.ground_truth) == {gt_frame(o.name, o.gt_id) for o in bundle.objects}
        info = v.messages["rgb_info"]
        assert (info.width, info.height, info.header.frame_id) == (160, 120, "brave6d_camera_optical_frame")
    np.testing.assert_allclose(moved.world_T_cam, FREE2, atol=1e-9)
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
        assert (v.status["accepted"], v.status["collided"], v.status["adjustments"], v.status["step"]) == (
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
    assert Path(result["log"]).parent == node[1]


@pytest.mark.slow
def test_commands_without_an_episode_or_with_bad_values_are_answered_with_one_line(agent: Ros2Agent) -> None:
    agent.reset(start=FREE)
    agent.submit([])  # ends the episode
    with pytest.raises(AgentError, match="call reset"):
        agent.set_pose(FREE2)
    with pytest.raises(AgentError, match="unknown field"):
        agent.send_json("reset", {"colour": "red"})
    agent.reset(start=FREE)
    with pytest.raises(AgentError, match="start pose refused"):
        agent.reset(start=IN_POST)

"""The ROS-agnostic bridge (brave6d.ros_interface.bridge): an episode through the bridge logs and scores
exactly as the same actions through brave6d.serve.EpisodeManager; refusals are reported; estimates and
poses round-trip through the (position, quaternion x-y-z-w) helpers, also near singular rotations."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.core.errors import BraveError
from brave6d.core.transforms import check_rigid, look_at, make_transform
from brave6d.evaluation.metrics import EvalConfig, models_from_bundle, read_episode, score_episodes
from brave6d.ros_interface import (
    FRAME_CAMERA_OPTICAL,
    FRAME_WORLD,
    BridgeError,
    EpisodeBridge,
    EpisodeScorer,
    Estimate,
    camera_info_arrays,
    depth_to_rep118,
    gt_frame,
    matrix_to_pose,
    pose_to_matrix,
)
from brave6d.serve import EpisodeManager, SceneServer, load_bundle, make_synthetic_bundle

FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
FREE2 = look_at((0.30, 0.10, 0.35), (0.46, 0.0, 0.01))
IN_POST = look_at((0.30, 0.25, 0.15), (0.46, 0.0, 0.01))  # the synthetic scene's "post" collision box
VOLATILE = {"time", "timings_ms", "episode_id", "elapsed_s", "duration_s", "render_ms_median", "depth_file",
            "digest"}  # the digest covers the episode id


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Any:
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("ros_scene"), n_gaussians=4000,
                                             width=160, height=120))


@pytest.fixture(scope="module")
def scene(bundle: Any) -> SceneServer:
    return SceneServer(bundle, device="cpu")


@pytest.fixture(scope="module")
def scorer() -> EpisodeScorer:
    return EpisodeScorer()


def _manager(scene: SceneServer, tmp_path: Path, name: str, mode: str = "training") -> EpisodeManager:
    """A manager in training mode by default: these tests compare the ground truth the bridge passes on."""
    return EpisodeManager(scene, tmp_path / name, max_episodes=4, mode=mode)


def _stable(value: Any) -> Any:
    """A log record without the fields that differ between two runs of the same actions."""
    if isinstance(value, dict):
        return {k: _stable(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [_stable(v) for v in value]
    return value


def _log_lines(path: Path) -> list[dict[str, Any]]:
    return [_stable(json.loads(line)) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def _truth_estimates(cam_T_obj_by_obj: dict[int, np.ndarray]) -> list[Estimate]:
    out = []
    for obj_id, T in cam_T_obj_by_obj.items():
        position, quaternion = matrix_to_pose(T)  # through the ROS form, as an agent would send it
        out.append(Estimate.from_pose(obj_id, position, quaternion, score=0.9))
    return out


# ----------------------------------------------------------------------------- the bridge = the manager
@pytest.mark.slow
def test_an_episode_through_the_bridge_logs_and_scores_as_the_manager(scene: SceneServer, scorer: EpisodeScorer,
                                                                      tmp_path: Path) -> None:
    bridge = EpisodeBridge(_manager(scene, tmp_path, "bridge"), agent="ros-test", scorer=scorer)
    direct = _manager(scene, tmp_path, "direct")

    b0 = bridge.reset(target="cube_red", start=FREE)
    d0 = direct.reset(target="cube_red", start=FREE, agent="ros-test")
    b_steps = [bridge.set_pose(FREE2), bridge.set_pose(IN_POST), bridge.move([0.0, 0.0, 0.02], [0.0, 0.1, 0.0], 0.5)]
    eid = d0.episode_id
    d_steps = [direct.set_pose(eid, FREE2), direct.set_pose(eid, IN_POST),
               direct.move(eid, [0.0, 0.0, 0.02], [0.0, 0.1, 0.0], 0.5)]
    for b, d in zip([b0, *b_steps], [d0, *d_steps]):
        assert (b.accepted, b.collided, b.adjustments, b.step) == (d.accepted, d.collided, d.adjustments, d.step)
        np.testing.assert_array_equal(b.rgb, d.observation.rgb)
        np.testing.assert_array_equal(b.depth_m, d.observation.depth)
        np.testing.assert_allclose(b.world_T_cam, d.observation.world_T_cam, atol=1e-12)
    # a target estimate off by 1 cm, and the other cube exact
    truth = {o.obj_id: o.cam_T_obj for o in b_steps[-1].objects}
    target = b_steps[-1].target()
    assert target is not None and target.name == "cube_red"
    truth[target.obj_id] = truth[target.obj_id] @ make_transform(np.eye(3), [0.01, 0.0, 0.0])
    estimates = _truth_estimates(truth)
    result = bridge.submit(estimates)
    direct.submit(eid, [{"obj_id": e.obj_id, "R": e.cam_T_obj[:3, :3].reshape(-1).tolist(),
                         "t_m": e.cam_T_obj[:3, 3].tolist(), "score": e.score} for e in estimates], "ros-test")

    bridge_log = Path(result.log or "")
    assert _log_lines(bridge_log) == _log_lines(tmp_path / "direct" / f"{eid}.jsonl")
    models = models_from_bundle(scene.bundle)
    board = score_episodes([read_episode(tmp_path / "direct" / f"{eid}.jsonl")], models, EvalConfig())
    ref = board.episodes[0].scores
    assert (result.ar, result.ar_vsd, result.ar_mssd, result.ar_mspd) == (ref.ar, ref.ar_vsd, ref.ar_mssd, ref.ar_mspd)
    assert 0.0 < result.ar < 1.0  # 1 cm off a 20 mm cube: some thresholds pass, some fail
    assert (result.adjustments, result.steps, result.refusals, result.submitted) == (2, 3, 1, 2)


@pytest.mark.slow
def test_exact_estimates_score_one_and_wrong_ones_zero(scene: SceneServer, scorer: EpisodeScorer,
                                                       tmp_path: Path) -> None:
    bridge = EpisodeBridge(_manager(scene, tmp_path, "eps"), scorer=scorer)
    step = bridge.reset(target="cube_blue", start=FREE2)
    exact = bridge.submit(_truth_estimates({o.obj_id: o.cam_T_obj for o in step.objects}))
    assert exact.ar == pytest.approx(1.0) and exact.adjustments == 0 and exact.steps == 0
    step = bridge.reset(target="cube_blue", start=FREE2)
    far = {o.obj_id: o.cam_T_obj @ make_transform(np.eye(3), [0.0, 0.0, 0.2]) for o in step.objects}
    assert bridge.submit(_truth_estimates(far)).ar == 0.0


# ----------------------------------------------------------------------------- refusals, ground truth, errors
@pytest.mark.slow
def test_a_refused_pose_is_reported_and_changes_nothing(scene: SceneServer, tmp_path: Path) -> None:
    bridge = EpisodeBridge(_manager(scene, tmp_path, "refusal"))
    first = bridge.reset(start=FREE)
    moved = bridge.set_pose(FREE2)
    refused = bridge.set_pose(IN_POST)
    assert moved.accepted and moved.adjustments == 1 and moved.refusal is None
    assert not refused.accepted and refused.collided and refused.adjustments == 1 and refused.step == 2
    assert refused.refusal is not None and "post" in refused.refusal
    assert refused.refusal_detail == {"reason": "collision", "message": refused.refusal, "box": "post"}
    np.testing.assert_array_equal(refused.world_T_cam, moved.world_T_cam)
    np.testing.assert_array_equal(refused.rgb, moved.rgb)
    assert refused.stamp_ns > moved.stamp_ns > first.stamp_ns  # one fresh stamp per answered action
    status = refused.status()
    assert status["refusal"]["box"] == "post" and status["accepted"] is False and status["adjustments"] == 1
    json.dumps(status)  # the status message is JSON
    bridge.close()


@pytest.mark.slow
def test_ground_truth_frames_and_poses(scene: SceneServer, tmp_path: Path) -> None:
    bridge = EpisodeBridge(_manager(scene, tmp_path, "gt"), width=80, height=60)
    step = bridge.reset(target="cube_blue", start=FREE)
    assert step.rgb.shape == (60, 80, 3) and step.depth_m.shape == (60, 80) and (step.width, step.height) == (80, 60)
    by_name = {o.name: o for o in step.objects}
    for o in scene.bundle.objects:
        np.testing.assert_allclose(by_name[o.name].world_T_obj, o.world_T_obj, atol=1e-9)
        assert by_name[o.name].frame == gt_frame(o.name, o.gt_id) == f"gt/{o.name}_{o.gt_id}"
    assert [o.name for o in step.objects if o.is_target] == ["cube_blue"]
    assert FRAME_WORLD == "world" and FRAME_CAMERA_OPTICAL == "brave6d_camera_optical_frame"
    bridge.close()


@pytest.mark.slow
def test_a_scored_bridge_passes_on_no_ground_truth(scene: SceneServer, scorer: EpisodeScorer, tmp_path: Path) -> None:
    """Scored: no objects (so no gt/ frame on /tf), the target named without a frame; the score after submit."""
    bridge = EpisodeBridge(_manager(scene, tmp_path, "scored", mode="scored"), scorer=scorer)
    for step in (bridge.reset(target="cube_blue", start=FREE), bridge.set_pose(FREE2)):
        assert step.objects == () and step.target() is None and step.target_frame == "" and step.mode == "scored"
        status = step.status()
        assert status["objects"] == [] and status["mode"] == "scored"
        assert status["target"] == {"name": "cube_blue", "obj_id": 2, "gt_id": 1, "frame": None}
    result = bridge.submit([Estimate(2, make_transform(np.eye(3), [0.0, 0.0, 0.3]))])
    assert result.mode == "scored" and 0.0 <= result.ar <= 1.0
    assert read_episode(Path(result.log or "")).mode == "scored"
    trained = EpisodeBridge(_manager(scene, tmp_path, "training"))
    step = trained.reset(target="cube_blue", start=FREE)
    assert step.target_frame == "gt/cube_blue_1" and step.status()["target"]["frame"] == "gt/cube_blue_1"
    trained.close()


def test_actions_without_an_open_episode_are_refused_in_one_line() -> None:
    bridge = EpisodeBridge(object())  # the guard answers before the manager is asked anything
    with pytest.raises(BridgeError, match="call reset first"):
        bridge.set_pose(FREE)
    with pytest.raises(BridgeError, match="call reset first"):
        bridge.submit([])
    assert bridge.close()["reason"] == "no open episode"


@pytest.mark.slow
def test_a_bad_estimate_names_its_field_and_keeps_the_episode_open(scene: SceneServer, tmp_path: Path) -> None:
    bridge = EpisodeBridge(_manager(scene, tmp_path, "bad"))
    bridge.reset(start=FREE)
    skewed = np.eye(4)
    skewed[0, 1] = 0.5
    with pytest.raises(BraveError, match=r"estimates\.0\.R"):
        bridge.submit([Estimate(1, skewed)])
    assert bridge.set_pose(FREE2).accepted  # still open
    bridge.close()
    with pytest.raises(BridgeError, match="has ended"):
        bridge.set_pose(FREE)


# ----------------------------------------------------------------------------- ROS conventions as numpy
def test_camera_info_arrays_and_rep118_depth() -> None:
    K = np.array([[100.0, 0, 79.5], [0, 101.0, 59.5], [0, 0, 1]])
    info = camera_info_arrays(K)
    assert info["distortion_model"] == "plumb_bob" and info["D"] == [0.0] * 5
    assert info["K"] == K.reshape(-1).tolist() and info["R"] == np.eye(3).reshape(-1).tolist()
    assert info["P"] == [100.0, 0, 79.5, 0, 0, 101.0, 59.5, 0, 0, 0, 1, 0]
    d = depth_to_rep118(np.array([[0.0, 0.5], [1.25, 0.0]], dtype=np.float32))
    assert d.dtype == np.float32 and np.isnan(d[0, 0]) and np.isnan(d[1, 1]) and d[0, 1] == 0.5 and d[1, 0] == 1.25


def test_pose_to_matrix_refuses_bad_quaternions_naming_the_field() -> None:
    with pytest.raises(BraveError, match=r"set_pose\.orientation: .*not a unit quaternion"):
        pose_to_matrix([0, 0, 0], [0, 0, 0, 0], "set_pose")
    with pytest.raises(BraveError, match=r"est\.orientation: a quaternion \(x, y, z, w\) must be 4 finite"):
        pose_to_matrix([0, 0, 0], [0, 0, math.nan, 1], "est")
    with pytest.raises(BraveError, match=r"p\.position"):
        pose_to_matrix([0, math.inf, 0], [0, 0, 0, 1], "p")
    # slightly off unit (float32 round trip) is accepted and normalised
    T = pose_to_matrix([1, 2, 3], np.array([0, 0, 0.7071068, 0.7071068], dtype=np.float32))
    check_rigid(T)
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)


def test_quaternion_order_is_ros_xyzw() -> None:
    T = make_transform(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [0.1, 0.2, 0.3])
    position, q = matrix_to_pose(T)
    np.testing.assert_allclose(position, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(q, [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)


unit_axes = st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3).filter(
    lambda v: float(np.linalg.norm(v)) > 1e-3)
positions = st.lists(st.floats(-5, 5, allow_nan=False), min_size=3, max_size=3)


def _round_trip(R: np.ndarray, t: list[float]) -> None:
    T = make_transform(R, t)
    position, q = matrix_to_pose(T)
    assert np.all(np.isfinite(q)) and abs(float(np.linalg.norm(q)) - 1.0) < 1e-12 and q[3] >= 0.0
    back = pose_to_matrix(position, q)
    check_rigid(back, atol=1e-9)
    np.testing.assert_allclose(back, T, atol=1e-9)


@given(unit_axes, st.floats(-1e-3, 1e-3), positions)
def test_round_trip_near_pi(axis: list[float], eps: float, t: list[float]) -> None:
    """Rotations by pi (w = 0: the quaternion's sign is ambiguous) and within a milliradian of it."""
    a = np.asarray(axis) / np.linalg.norm(axis)
    _round_trip(Rotation.from_rotvec(a * (math.pi - abs(eps))).as_matrix(), t)


@given(unit_axes, st.floats(0.0, 1e-6), positions)
def test_round_trip_tiny_angles(axis: list[float], angle: float, t: list[float]) -> None:
    a = np.asarray(axis) / np.linalg.norm(axis)
    _round_trip(Rotation.from_rotvec(a * angle).as_matrix(), t)


@given(st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: float(np.linalg.norm(q)) > 1e-3), positions)
def test_quaternion_to_matrix_to_quaternion(q: list[float], t: list[float]) -> None:
    qn = np.asarray(q) / np.linalg.norm(q)
    T = pose_to_matrix(t, qn)
    check_rigid(T, atol=1e-9)
    _, q2 = matrix_to_pose(T)
    assert min(np.abs(q2 - qn).max(), np.abs(q2 + qn).max()) < 1e-9  # q and -q are the same rotation

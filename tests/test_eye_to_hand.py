"""Eye-to-hand calibration (static camera, board on the tool) against the truth and OpenCV's
independent solvers; the intrinsics' full covariance against OpenCV's 1-sigmas; intrinsics
refined jointly with the hand-eye transform; hand-eye files of a static camera."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.core.board import board_size_m
from brave6d.core.calibration_io import read_handeye
from brave6d.core.errors import DataError, DegenerateGeometryError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import invert, make_transform, rpy_deg_to_matrix
from brave6d.calibration import (
    CharucoDetection,
    EyeToHandResult,
    HandEyeOptions,
    HandEyeView,
    board_corner_points,
    calibrate_eye_to_hand,
    calibrate_handeye,
    calibrate_intrinsics,
)
from brave6d.calibration.known_truth import (
    default_board,
    default_K,
    make_handeye_dataset,
    perturb_pose,
    project_corners,
)
from brave6d.calibration.plan import board_T_cam_view

SPEC = default_board()
OBJ = board_corner_points(SPEC)
K = default_K()
SIZE = (640, 480)
CENTER = np.array([board_size_m(SPEC)[0] / 2, board_size_m(SPEC)[1] / 2, 0.0])
#: The static camera 1.2 m from the base, looking back at the robot; the board 10 cm off the flange.
BASE_T_CAM = make_transform(rpy_deg_to_matrix([-110.0, 2.0, 178.0]), [0.05, 1.2, 0.35])
TCP_T_BOARD = make_transform(rpy_deg_to_matrix([0.0, 90.0, 45.0]), [0.06, -0.03, 0.10])


def _eye_to_hand_views(n: int, seed: int, pixel_noise: float = 0.1, robot_mm: float = 0.05, robot_deg: float = 0.005,
                       span: float = 30.0) -> tuple[list[HandEyeView], list[np.ndarray], list[np.ndarray]]:
    """Views of a board on the tool seen by the static camera: ``(views with measured robot poses,
    true robot poses, true cam_T_board)``."""
    rng = np.random.default_rng(seed)
    views, G_true, C_true = [], [], []
    for k in range(n):
        board_T_cam = board_T_cam_view(CENTER + np.r_[rng.uniform(-0.04, 0.04, 2), 0.0], rng.uniform(0.55, 0.7),
                                       rng.uniform(-span, span), rng.uniform(0, 180), rng.uniform(-span, span))
        C = invert(board_T_cam)
        G = BASE_T_CAM @ C @ invert(TCP_T_BOARD)  # base_T_tcp that puts the board there
        ids, px = project_corners(OBJ, C, K, (), SIZE)
        px = px + rng.normal(0.0, pixel_noise, px.shape)
        G_meas = perturb_pose(G, robot_mm * 1e-3, robot_deg, rng)
        views.append(HandEyeView(G_meas, ids, px, f"img{k:02d}"))
        G_true.append(G)
        C_true.append(C)
    return views, G_true, C_true


def _errors(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    return (1000.0 * float(np.linalg.norm(A[:3, 3] - B[:3, 3])),
            math.degrees(Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).magnitude()))


def test_eye_to_hand_recovers_the_static_camera_within_its_uncertainty() -> None:
    views, _, _ = _eye_to_hand_views(15, seed=1)
    res = calibrate_eye_to_hand(views, OBJ, K)
    assert isinstance(res, EyeToHandResult) and res.setup == "eye-to-hand"
    u = res.solution.uncertainty
    assert u is not None
    mm, deg = _errors(res.base_T_cam, BASE_T_CAM)
    assert mm < 3 * u.translation_sigma_norm_mm and deg < 3 * u.rotation_sigma_norm_deg, (mm, deg, u)
    mm_b, _ = _errors(res.tcp_T_board, TCP_T_BOARD)
    assert mm_b < 3.0
    assert np.allclose(res.camera_pose(np.eye(4)), res.base_T_cam)
    # the same data given to the eye-in-hand solver is refused, not silently solved
    with pytest.raises(DegenerateGeometryError):
        calibrate_handeye(views, OBJ, K)


def test_eye_to_hand_agrees_with_opencvs_independent_solvers() -> None:
    """OpenCV's calibrateHandEye on the inverted poses gives the same closed form as ours; its
    calibrateRobotWorldHandEye (no inversion at all) finds the camera too; the refined answer is
    within 3 sigma of the truth and nearer to it than OpenCV's closed forms."""
    views, _, _ = _eye_to_hand_views(15, seed=2)
    res = calibrate_eye_to_hand(views, OBJ, K)
    u = res.solution.uncertainty
    assert u is not None
    R_t2c, t_t2c = [], []
    for v in views:
        ok, rvec, tvec = cv2.solvePnP(OBJ[v.corner_ids], v.corners_px, K, None)
        assert ok
        R_t2c.append(cv2.Rodrigues(rvec)[0])
        t_t2c.append(tvec.reshape(3))
    G = [v.base_T_tcp for v in views]
    # world = board, "base2gripper" = the tool's pose in the base: the outputs are board_T_tcp, cam_T_base
    _, _, R_c, t_c = cv2.calibrateRobotWorldHandEye(R_t2c, t_t2c, [g[:3, :3] for g in G], [g[:3, 3] for g in G],
                                                    method=cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH)
    shah = invert(make_transform(R_c, t_c.reshape(3)))
    Gi = [invert(g) for g in G]
    R_x, t_x = cv2.calibrateHandEye([g[:3, :3] for g in Gi], [g[:3, 3] for g in Gi], R_t2c, t_t2c,
                                    method=cv2.CALIB_HAND_EYE_PARK)
    park = make_transform(R_x, t_x.reshape(3))
    ours_park = res.solution.method_result("park").tcp_T_cam
    assert ours_park is not None
    mm, deg = _errors(ours_park, park)
    assert mm < 0.05 and deg < 0.005, (mm, deg)
    refined = _errors(res.base_T_cam, BASE_T_CAM)
    assert refined[0] < 3 * u.translation_sigma_norm_mm and refined[1] < 3 * u.rotation_sigma_norm_deg, (refined, u)
    for other in (shah, park):
        err = _errors(other, BASE_T_CAM)
        assert err[0] < 6.0 and err[1] < 0.5, err  # OpenCV finds the camera (a convention slip would be cm, deg)
        assert refined[0] < err[0] and refined[1] < err[1]


@given(cone_deg=st.floats(0.0, 20.0), n=st.integers(0, 8), duplicate=st.booleans(), seed=st.integers(0, 500))
@example(cone_deg=0.0, n=4, duplicate=False, seed=6)  # CI's find: img2 and img3 drawn 8 um and 0.036 deg apart
@example(cone_deg=0.0, n=4, duplicate=True, seed=6)
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_eye_to_hand_hard_cases_give_a_clear_error_or_a_finite_answer(cone_deg, n, duplicate, seed) -> None:
    """Near-parallel rotation axes, too few poses, duplicated poses."""
    rng = np.random.default_rng(seed)
    axis = np.array([0.0, 0.0, 1.0])
    views = []
    for k in range(n):
        tilt = Rotation.from_rotvec(math.radians(rng.uniform(0, cone_deg)) * np.r_[np.cos(k), np.sin(k), 0.0])
        C = invert(board_T_cam_view(CENTER, 0.6, 0.0, 0.0, rng.uniform(-40, 40)))
        C[:3, :3] = tilt.as_matrix() @ C[:3, :3]
        G = BASE_T_CAM @ C @ invert(TCP_T_BOARD)
        ids, px = project_corners(OBJ, C, K, (), SIZE)
        views.append(HandEyeView(G, ids, px + rng.normal(0, 0.1, px.shape), f"img{k}"))
    if duplicate and len(views) > 2:
        views.append(HandEyeView(views[1].base_T_tcp.copy(), views[1].corner_ids, views[1].corners_px, "copy_of_img1"))
    try:
        res = calibrate_eye_to_hand(views, OBJ, K)
    except DegenerateGeometryError as exc:
        text = str(exc)
        assert any(c in text for c in ("too few poses", "duplicated poses", "near-parallel", "rotation span",
                                       "pure translations", "poorly determined", "rank deficient")), text
        if "duplicated" in text:  # the copy, or two random poses that fell within the thresholds by chance
            by_name = {v.name: v.base_T_tcp for v in views}
            listed = text.split("views ", 1)[1].split(" have the same", 1)[0].split(" (and ")[0]
            for pair in listed.split("; "):
                first, second = (by_name[name] for name in pair.split(" and "))
                rel = invert(first) @ second
                assert np.linalg.norm(rel[:3, 3]) <= 0.0005 and Rotation.from_matrix(rel[:3, :3]).magnitude() <= \
                    math.radians(0.1), f"{pair} named as duplicates but they differ"
        if "turn the direction" in text:
            assert "(base frame)" in text and "TCP" not in text  # eye-to-hand motions lie in the base frame
        return
    assert np.all(np.isfinite(res.base_T_cam)) and np.all(np.isfinite(res.tcp_T_board))


def test_eye_to_hand_file_names_base_T_cam_and_scenes_refuse_it(tmp_path) -> None:
    views, _, _ = _eye_to_hand_views(12, seed=4)
    res = calibrate_eye_to_hand(views, OBJ, K)
    path = res.save(tmp_path / "handeye.json")
    data = json.loads(path.read_text())
    assert data["setup"] == "eye-to-hand" and "tcp_T_cam" not in json.dumps(data)
    assert np.allclose(data["base_T_cam"], res.base_T_cam) and np.allclose(data["tcp_T_board"], res.tcp_T_board)
    back = EyeToHandResult.load(path)
    assert np.allclose(back.base_T_cam, res.base_T_cam)
    assert back.solution.uncertainty is not None
    scene = SceneDir(tmp_path)
    scene.handeye_path.parent.mkdir(parents=True, exist_ok=True)
    scene.handeye_path.write_text(path.read_text())
    with pytest.raises(DataError, match="eye-to-hand calibration"):
        read_handeye(scene)


# ----------------------------------------------------------------------------- intrinsics
def _detections(n: int, seed: int, noise: float) -> tuple[list[CharucoDetection], list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    dets, cams = [], []
    dist = np.array([-0.12, 0.05, 0.0, 0.0, 0.0])
    for k in range(n):
        C = invert(board_T_cam_view(CENTER + np.r_[rng.uniform(-0.03, 0.03, 2), 0.0], rng.uniform(0.3, 0.5),
                                    rng.uniform(-40, 40), rng.uniform(0, 180), rng.uniform(-30, 30)))
        ids, px = project_corners(OBJ, C, K, dist, SIZE)
        dets.append(CharucoDetection(ids, px + rng.normal(0, noise, px.shape)))
        cams.append(C)
    return dets, cams


def test_intrinsics_covariance_matches_opencvs_one_sigmas_and_keeps_correlations() -> None:
    dets, _ = _detections(14, seed=5, noise=0.2)
    res = calibrate_intrinsics(dets, OBJ, SIZE, distortion="radial")
    assert res.covariance is not None
    assert res.covariance.names == ("fx", "fy", "cx", "cy", "k1", "k2", "k3")
    mine = res.covariance.std()
    for name, sigma in mine.items():
        assert sigma == pytest.approx(res.std[name], rel=1e-3), name  # OpenCV's calibrateCameraExtended
    m = res.covariance.matrix
    corr = m / np.sqrt(np.outer(np.diag(m), np.diag(m)))
    assert corr[0, 1] > 0.5  # fx and fy move together
    assert abs(corr[4, 5]) > 0.5  # so do the radial terms
    back = type(res).from_json(json.loads(json.dumps(res.to_json())))
    assert back.covariance is not None and np.allclose(back.covariance.matrix, m)


def test_refining_intrinsics_jointly_recovers_wrong_ones() -> None:
    """Intrinsics 8 px off in fx and 5 px in cx: held, the hand-eye answer is biased; refined with
    the robot's motions, K and tcp_T_cam come back to the truth."""
    ds = make_handeye_dataset(15, 35, seed=6, pixel_noise_px=0.1, robot_translation_noise_m=2e-5,
                              robot_rotation_noise_deg=0.002)
    K_wrong = ds.K.copy()
    K_wrong[0, 0] += 8.0
    K_wrong[0, 2] += 5.0
    loose = HandEyeOptions(max_sigma_mm=None, max_sigma_deg=None)
    held = calibrate_handeye(ds.views, ds.object_points, K_wrong, options=loose)
    joint = calibrate_handeye(ds.views, ds.object_points, K_wrong,
                              options=HandEyeOptions(refine_intrinsics=("fx", "fy", "cx", "cy")))
    assert joint.intrinsics_std is not None and set(joint.intrinsics_std) == {"fx", "fy", "cx", "cy"}
    assert abs(joint.K[0, 0] - ds.K[0, 0]) < 4 * joint.intrinsics_std["fx"] + 0.5
    assert abs(joint.K[0, 2] - ds.K[0, 2]) < 4 * joint.intrinsics_std["cx"] + 0.5
    err_held = held.errors_against(ds.tcp_T_cam)["refined"]
    err_joint = joint.errors_against(ds.tcp_T_cam)["refined"]
    assert err_joint[1] < err_held[1] / 3  # the principal point error no longer turns the camera
    u = joint.uncertainty
    assert u is not None and err_joint[0] < 3 * u.translation_sigma_norm_mm and err_joint[1] < 3 * u.rotation_sigma_norm_deg
    assert np.trace(u.covariance_intrinsics) > 0  # the intrinsics' share is reported
    with pytest.raises(ValueError, match="not a parameter of this camera model"):
        calibrate_handeye(ds.views, ds.object_points, K_wrong, options=HandEyeOptions(refine_intrinsics=("k1",)))

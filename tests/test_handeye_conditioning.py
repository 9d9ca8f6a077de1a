"""Conditioning check: degenerate pose sets fail with a message naming the cause."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from brave6d.core.board import board_size_m
from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.transforms import invert, make_transform
from brave6d.calibration.conditioning import ConditioningThresholds, check_handeye_conditioning
from brave6d.calibration.plan import board_T_cam_view, plan_for_board, plan_pairs
from brave6d.calibration.known_truth import default_board, default_tcp_T_cam

SPEC = default_board()
W = SPEC.pose.matrix()
X = default_tcp_T_cam()
CENTER = np.array([board_size_m(SPEC)[0] / 2, board_size_m(SPEC)[1] / 2, 0.0])


def _pairs(board_T_cams):
    G = [W @ bc @ invert(X) for bc in board_T_cams]
    C = [invert(bc) for bc in board_T_cams]
    return G, C


def _rotated(axis, angles_deg, offsets=None):
    """Cameras turned about a fixed axis through the board centre."""
    base = board_T_cam_view(CENTER, 0.4, 0.0, 0.0, 0.0)
    out = []
    for k, a in enumerate(angles_deg):
        R = make_transform(Rotation.from_rotvec(np.radians(a) * np.asarray(axis, float)).as_matrix(), np.zeros(3))
        T = make_transform(np.eye(3), CENTER) @ R @ make_transform(np.eye(3), -CENTER) @ base
        if offsets is not None:
            T[:3, 3] += offsets[k]
        out.append(T)
    return out


def test_a_good_plan_passes_without_warnings() -> None:
    poses = plan_for_board(SPEC, 0.4, X, 20, max_tilt_deg=35.0)
    report = check_handeye_conditioning(*plan_pairs(poses, W))
    assert report.n_poses == 20
    assert report.rotation_span_deg > 45 and report.max_axis_angle_deg > 60
    assert report.weakest_rotation_deg is not None and report.weakest_rotation_deg > 25
    assert report.median_angle_mismatch_deg == pytest.approx(0.0, abs=1e-9)
    assert report.warnings == ()


def test_two_poses_are_too_few() -> None:
    G, C = _pairs(_rotated([1, 0, 0], [0, 30]))
    with pytest.raises(DegenerateGeometryError, match=r"too few poses.*2 usable pose\(s\), at least 3"):
        check_handeye_conditioning(G, C)


def test_pure_translations() -> None:
    base = board_T_cam_view(CENTER, 0.4, 0.0, 0.0, 0.0)
    cams = []
    for d in np.random.default_rng(0).normal(0, 0.05, (6, 3)):
        T = base.copy()
        T[:3, 3] += d
        cams.append(T)
    with pytest.raises(DegenerateGeometryError, match=r"pure translations.*0\.00 deg < 1 deg"):
        check_handeye_conditioning(*_pairs(cams))


def test_rotations_about_a_single_axis() -> None:
    offsets = np.random.default_rng(1).normal(0, 0.03, (6, 3))
    G, C = _pairs(_rotated([0.3, 0.9, 0.1] / np.linalg.norm([0.3, 0.9, 0.1]), [-30, -15, 0, 10, 20, 35], offsets))
    with pytest.raises(DegenerateGeometryError, match=r"near-parallel rotation axes.*0\.0 deg < 10 deg"):
        check_handeye_conditioning(G, C)


def test_one_dominant_axis_with_a_small_second_rotation() -> None:
    """Axes 15 deg apart and a 60 deg span pass the axis and span checks, but one 8 deg turn
    about the second axis leaves the direction of the first turned by ~1 deg (RMS): the
    camera offset along it would carry 50x the noise. It used to pass without a warning."""
    first = np.array([1.0, 0.0, 0.0])
    second = np.array([math.cos(math.radians(15)), math.sin(math.radians(15)), 0.0])
    offsets = np.random.default_rng(2).normal(0, 0.03, (8, 3))
    G, C = _pairs(_rotated(first, [-30, -20, -10, 0, 10, 20, 30], offsets[:7]) + _rotated(second, [8], offsets[7:]))
    with pytest.raises(DegenerateGeometryError, match=r"near-parallel rotation axes: the robot motions turn the "
                       r"direction .* by only 1\.\d\d deg \(RMS over view pairs\) < 3 deg"):
        check_handeye_conditioning(G, C)
    relaxed = check_handeye_conditioning(G, C, ConditioningThresholds(min_weakest_rotation_deg=0.5))
    assert relaxed.weakest_rotation_deg == pytest.approx(1.0, abs=0.1)
    assert any("by only 1.0 deg (RMS; recommended 10 deg+)" in w for w in relaxed.warnings)


def test_small_rotation_span_names_span_and_threshold() -> None:
    cams = [board_T_cam_view(CENTER, 0.4, t, az, r) for t, az, r in [(0, 0, 0), (3, 0, 2), (3, 90, -2), (2, 45, 3)]]
    with pytest.raises(DegenerateGeometryError, match=r"rotation span too small: .* is \d+\.\d deg < 15 deg"):
        check_handeye_conditioning(*_pairs(cams))


def test_duplicated_poses_name_the_views() -> None:
    poses = plan_for_board(SPEC, 0.4, X, 8)
    G, C = plan_pairs(poses, W)
    G.insert(5, G[2].copy())
    C.insert(5, C[2].copy())
    names = [f"img{k}" for k in range(len(G))]
    with pytest.raises(DegenerateGeometryError, match=r"duplicated poses: views img2 and img5"):
        check_handeye_conditioning(G, C, names=names)


def test_robot_and_camera_disagree() -> None:
    """Eye-to-hand data (or shuffled images) given to the eye-in-hand solver."""
    G, C = plan_pairs(plan_for_board(SPEC, 0.4, X, 10), W)
    shuffled = C[1:] + C[:1]
    with pytest.raises(DegenerateGeometryError, match="robot and camera motions disagree"):
        check_handeye_conditioning(G, shuffled)


def test_thresholds_are_parameters_and_warnings_are_soft() -> None:
    cams = [board_T_cam_view(CENTER, 0.4, t, az, r) for t, az, r in [(0, 0, 0), (12, 0, 6), (12, 90, -6), (10, 45, 8)]]
    G, C = _pairs(cams)
    report = check_handeye_conditioning(G, C, ConditioningThresholds(min_rotation_span_deg=5.0))
    assert any("only 4 poses" in w for w in report.warnings)
    assert any("rotation span" in w for w in report.warnings)
    with pytest.raises(DegenerateGeometryError, match="too few poses"):
        check_handeye_conditioning(G, C, ConditioningThresholds(min_poses=5))


def test_non_rigid_input_is_named() -> None:
    G, C = plan_pairs(plan_for_board(SPEC, 0.4, X, 5), W)
    G[3] = G[3].copy()
    G[3][:3, :3] *= 1.001  # millimetre/metre mix-ups and scaled matrices are refused
    with pytest.raises(Exception, match="base_T_tcp of view 3"):
        check_handeye_conditioning(G, C)

"""Calibration capture plan: diverse rotations, board in view, consistent TCP poses."""

from __future__ import annotations

import numpy as np
import pytest

from brave6d.core.board import board_size_m
from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.transforms import invert
from brave6d.calibration.conditioning import check_handeye_conditioning
from brave6d.calibration.plan import (
    board_T_cam_view,
    plan_calibration_poses,
    plan_for_board,
    plan_pairs,
)
from brave6d.calibration.known_truth import default_board, default_K, default_tcp_T_cam

SPEC = default_board()
W = SPEC.pose.matrix()
X = default_tcp_T_cam()
K = default_K()


def test_board_view_geometry() -> None:
    c = np.array([0.1, 0.07, 0.0])
    frontal = board_T_cam_view(c, 0.4, 0.0, 0.0, 0.0)
    assert frontal[:3, :3] == pytest.approx(np.eye(3))  # image upright, camera on the printed side
    assert frontal[:3, 3] == pytest.approx(c - [0, 0, 0.4])
    for tilt, az, roll in [(30, 0, 0), (35, 120, 25), (20, 250, -30)]:
        T = board_T_cam_view(c, 0.4, tilt, az, roll)
        centre_cam = invert(T)[:3, :3] @ c + invert(T)[:3, 3]
        assert centre_cam[:2] == pytest.approx([0, 0], abs=1e-12)  # the aim point is on the optical axis
        assert centre_cam[2] == pytest.approx(0.4)
        assert np.degrees(np.arccos(T[2, 2])) == pytest.approx(tilt)  # optical axis tilted from the normal


def test_plan_poses_are_consistent_and_well_conditioned() -> None:
    poses = plan_for_board(SPEC, 0.4, X, 20, max_tilt_deg=35.0)
    assert len(poses) == 20 and len({p.name for p in poses}) == 20
    for p in poses:
        assert p.base_T_tcp @ X == pytest.approx(p.base_T_cam, abs=1e-12)
    report = check_handeye_conditioning(*plan_pairs(poses, W))
    assert report.rotation_span_deg >= 2 * 35 * 0.8  # tilts of +-35 deg in different directions
    assert report.max_axis_angle_deg > 60 and report.warnings == ()
    assert {round(p.roll_deg) for p in poses} >= {30, -30, 15, -15}


def test_plan_keeps_the_board_in_the_image() -> None:
    w, h = board_size_m(SPEC)
    outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], float)
    margin = 10.0
    # 0.25 m is too close for the oblique views: those are moved back until the board fits
    poses = plan_for_board(SPEC, 0.25, X, 16, K=K, image_size=(640, 480), fit_margin_px=margin)
    assert max(p.distance_m for p in poses) > 0.25 * 1.1
    for p in poses:
        cam_T_board = invert(p.base_T_cam) @ W
        pts = outline @ cam_T_board[:3, :3].T + cam_T_board[:3, 3]
        uv = (pts @ K.T)[:, :2] / pts[:, 2:3]
        assert np.all(pts[:, 2] > 0)
        assert np.all((uv >= margin - 1e-6) & (uv <= np.array([639, 479]) - margin + 1e-6))


def test_plan_rejects_impossible_requests() -> None:
    with pytest.raises(DegenerateGeometryError, match="at least 3"):
        plan_for_board(SPEC, 0.4, X, 2)
    with pytest.raises(DegenerateGeometryError, match="max_tilt_deg"):
        plan_calibration_poses(W, (0.1, 0.07, 0), 0.4, X, 10, max_tilt_deg=85.0)
    tiny_lens = np.array([[3000.0, 0, 319.5], [0, 3000.0, 239.5], [0, 0, 1]])
    with pytest.raises(DegenerateGeometryError, match="does not fit in the image"):
        plan_for_board(SPEC, 0.1, X, 5, K=tiny_lens, image_size=(640, 480))

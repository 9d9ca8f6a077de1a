"""Pinhole camera with OpenCV distortion: projection round trips, undistortion, resize/crop."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError

CAM = PinholeCamera(640, 400, 457.0, 455.0, 321.3, 198.7, (0.04, -0.08, 0.001, -0.0005, 0.01))


@given(st.floats(-0.55, 0.55), st.floats(-0.35, 0.35), st.floats(0.05, 5.0))
def test_project_unproject_round_trip_with_distortion(x: float, y: float, z: float) -> None:
    point = np.array([[x * z, y * z, z]])
    proj = CAM.project(point)
    assert proj.valid[0]
    back = CAM.unproject(proj.uv, [z])
    np.testing.assert_allclose(back, point, atol=1e-9 * max(1.0, z) + 1e-10)


def test_project_matches_pinhole_formula_without_distortion() -> None:
    cam = CAM.without_distortion()
    pts = np.array([[0.1, -0.05, 0.5], [0.0, 0.0, 1.0]])
    uv = cam.project(pts).uv
    np.testing.assert_allclose(uv[:, 0], cam.fx * pts[:, 0] / pts[:, 2] + cam.cx)
    np.testing.assert_allclose(uv[:, 1], cam.fy * pts[:, 1] / pts[:, 2] + cam.cy)


def test_points_behind_camera_are_invalid_not_nan() -> None:
    proj = CAM.project([[0.0, 0.0, -1.0], [0.1, 0.1, 0.0], [np.nan, 0, 1], [0.0, 0.0, 1.0]])
    assert proj.valid.tolist() == [False, False, False, True]
    assert np.all(np.isfinite(proj.uv))


def test_undistort_image_moves_features_to_pinhole_positions() -> None:
    cam = PinholeCamera(320, 200, 230.0, 230.0, 159.5, 99.5, (0.15, -0.1, 0.0, 0.0, 0.0))
    pts = np.array([[0.25, 0.15, 1.0], [-0.3, 0.1, 1.0], [0.1, -0.2, 1.0]])
    img = np.zeros((200, 320), np.uint8)
    for u, v in cam.project(pts).uv:  # draw where the distorted lens images the points
        img[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2] = 255
    und = cam.undistort_image(img)
    for u, v in cam.without_distortion().project(pts).uv:
        patch = und[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2]
        assert patch.max() > 100, "feature not found at its undistorted position"


def test_scaled_and_cropped_keep_rays() -> None:
    pts = np.array([[0.05, -0.02, 0.7]])
    uv = CAM.project(pts).uv[0]
    half = CAM.scaled(320, 200)
    uv_half = half.project(pts).uv[0]
    np.testing.assert_allclose(uv_half, (uv + 0.5) / 2 - 0.5, atol=1e-9)
    crop = CAM.cropped(100, 50, 300, 200)
    np.testing.assert_allclose(crop.project(pts).uv[0], uv - [100, 50], atol=1e-9)


def test_json_round_trip_and_hfov() -> None:
    assert PinholeCamera.from_json(CAM.to_json()) == CAM
    cam = PinholeCamera.from_hfov(640, 400, 70.0)
    assert abs(cam.hfov_deg - 70.0) < 1e-9


@pytest.mark.parametrize("kwargs", [
    {"fx": 0.0}, {"fx": float("nan")}, {"width": 0}, {"dist": (0.1, 0.2, 0.3)},
])
def test_invalid_intrinsics_rejected(kwargs: dict) -> None:
    base = {"width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0, "dist": ()}
    with pytest.raises(BraveError):
        PinholeCamera(**{**base, **kwargs})


def test_crop_outside_image_rejected() -> None:
    with pytest.raises(BraveError, match="outside"):
        CAM.cropped(600, 0, 100, 100)

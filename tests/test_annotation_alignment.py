"""Rigid alignment of 3D-DAT camera poses to the captured ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.annotation.alignment import (
    AlignmentError,
    AlignmentOptions,
    align_camera_poses,
    apply_alignment,
    rigid_alignment,
)
from brave6d.core.transforms import invert, look_at, make_transform, rotation_distance


def _ring(n: int, radius: float = 0.4, seed: int = 0) -> list[np.ndarray]:
    """Camera poses on a ring looking at a table-top target (like a capture)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = [0.45 + radius * math.cos(a), radius * math.sin(a), 0.25 + 0.05 * rng.standard_normal()]
        out.append(look_at(eye, [0.45, 0.0, 0.01]))
    return out


rigid = st.tuples(st.floats(-math.pi, math.pi), st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1),
                  st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2))


def _transform(params) -> np.ndarray:
    angle, ax, ay, az, x, y, z = params
    axis = np.array([ax, ay, az])
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    return make_transform(Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix(), [x, y, z])


@settings(max_examples=40)
@given(rigid, st.integers(3, 12))
def test_random_rigid_offset_is_recovered(params, n) -> None:
    base_T_dat = _transform(params)
    base = _ring(n)
    dat = [invert(base_T_dat) @ T for T in base]
    estimate = rigid_alignment(base, dat)
    assert rotation_distance(estimate, base_T_dat) < 1e-9
    np.testing.assert_allclose(estimate[:3, 3], base_T_dat[:3, 3], atol=1e-9)
    report = align_camera_poses(base, dat, [str(i) for i in range(n)])
    if report.applied:
        assert report.rms_mm < 1e-6 and report.rms_deg < 1e-6
        np.testing.assert_allclose(report.target_T_source, base_T_dat, atol=1e-9)


def test_recovered_with_noise_and_residual_reported() -> None:
    rng = np.random.default_rng(3)
    base_T_dat = make_transform(Rotation.from_euler("xyz", [10, -20, 95], degrees=True).as_matrix(), [0.3, -0.2, 0.1])
    base = _ring(30)
    noisy = []
    for T in base:
        N = make_transform(Rotation.from_rotvec(rng.normal(0, math.radians(0.05), 3)).as_matrix(),
                           rng.normal(0, 0.0005, 3))
        noisy.append(invert(base_T_dat) @ T @ N)
    report = align_camera_poses(base, noisy, [f"f{i}" for i in range(30)])
    assert report.applied and report.frames == 30
    assert 0.3 < report.rms_mm < 3.0 and report.rms_deg < 0.2
    assert rotation_distance(report.target_T_source, base_T_dat) < math.radians(0.05)
    assert np.linalg.norm(report.target_T_source[:3, 3] - base_T_dat[:3, 3]) < 0.001
    data = report.to_json()
    assert len(data["residuals"]) == 30 and data["applied"] is True


def test_identical_frames_skip_the_estimate() -> None:
    base = _ring(5)
    report = align_camera_poses(base, [T.copy() for T in base], list("abcde"))
    assert not report.applied
    np.testing.assert_array_equal(report.target_T_source, np.eye(4))
    assert "not needed" in report.summary()


def test_large_residual_is_refused_naming_the_worst_frames() -> None:
    base = _ring(8)
    dat = [make_transform(np.eye(3), [1.0, 0, 0]) @ T for T in base]
    dat[5] = make_transform(np.eye(3), [0, 0, 0.05]) @ dat[5]  # one view 5 cm off
    with pytest.raises(AlignmentError) as info:
        align_camera_poses(base, dat, [f"view{i}" for i in range(8)])
    assert "'view5'" in str(info.value) and "worst frames" in str(info.value)


def test_scale_mismatch_is_refused() -> None:
    base = _ring(10)
    dat = [make_transform(T[:3, :3], T[:3, 3] * 1.1) for T in base]
    with pytest.raises(AlignmentError, match="rigid transform"):
        align_camera_poses(base, dat, [str(i) for i in range(10)])


def test_too_few_views_to_estimate() -> None:
    base = _ring(2)
    dat = [make_transform(np.eye(3), [0.1, 0, 0]) @ T for T in base]
    with pytest.raises(AlignmentError, match="at least 3"):
        align_camera_poses(base, dat, ["0", "1"], AlignmentOptions(min_frames=3))


def test_collinear_centres_still_determined_by_orientations() -> None:
    base_T_dat = make_transform(Rotation.from_euler("z", 40, degrees=True).as_matrix(), [0.1, 0.2, 0.0])
    base = [look_at([0.1 * k, 0, 0.5], [0.1 * k + 0.01 * (k % 2), 0.3, 0.0]) for k in range(4)]
    dat = [invert(base_T_dat) @ T for T in base]
    np.testing.assert_allclose(rigid_alignment(base, dat), base_T_dat, atol=1e-9)


def test_apply_alignment_composes() -> None:
    T = _transform((0.3, 0, 0, 1, 0.1, 0.2, 0.3))
    P = _transform((1.0, 1, 0, 0, 0.0, 0.1, 0.0))
    np.testing.assert_allclose(apply_alignment(T, [P])[0], T @ P)

"""A refused hand-eye result names its real cause: each cause fed alone (intrinsics uncertainty,
pose conditioning, detection count, reprojection error) is the one the refusal names, with its
share, and the acceptance limits are parameters (their defaults: 2 mm / 0.2 deg)."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.board import board_size_m
from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.transforms import invert
from brave6d.calibration import (
    HandEyeOptions,
    HandEyeRefusedError,
    IntrinsicsCovariance,
    board_corner_points,
    calibrate_handeye,
    explain_uncertainty,
)
from brave6d.calibration.handeye_result import Uncertainty
from brave6d.calibration.known_truth import default_board, default_K, default_tcp_T_cam, simulate_views
from brave6d.calibration.plan import board_T_cam_view
from brave6d.calibration.refusal import CAUSES

SPEC = default_board()
W = SPEC.pose.matrix()
X = default_tcp_T_cam()
K = default_K()
CENTER = np.array([board_size_m(SPEC)[0] / 2, board_size_m(SPEC)[1] / 2, 0.0])
OBJ = board_corner_points(SPEC)
#: A good capture: 15 views, tilts up to 30 deg about different in-plane axes and rolls.
GOOD = [(30 * np.cos(k), 36.0 * k, 25 * np.sin(1.7 * k)) for k in range(15)]


def _views(poses: list[tuple[float, float, float]], pixel_noise: float, seed: int = 0, distance: float = 0.45):
    cams = [board_T_cam_view(CENTER, distance, t, az, r) for t, az, r in poses]
    G = [W @ bc @ invert(X) for bc in cams]
    return simulate_views(G, X, W, OBJ, K, (), pixel_noise_px=pixel_noise, robot_translation_noise_m=2e-5,
                          robot_rotation_noise_deg=0.002, rng=np.random.default_rng(seed))


def _refused_at_half(views, **kwargs) -> HandEyeRefusedError:
    """Solve without limits, then with limits at half the 1-sigma reached: the refusal."""
    free = calibrate_handeye(views, OBJ, K, options=HandEyeOptions(max_sigma_mm=None, max_sigma_deg=None), **kwargs)
    u = free.uncertainty
    assert u is not None
    opts = HandEyeOptions(max_sigma_mm=u.translation_sigma_norm_mm / 2, max_sigma_deg=u.rotation_sigma_norm_deg / 2)
    with pytest.raises(HandEyeRefusedError) as info:
        calibrate_handeye(views, OBJ, K, options=opts, **kwargs)
    return info.value


def _check(err: HandEyeRefusedError, cause: str) -> None:
    b = err.breakdown
    assert b.dominant == cause, (b.shares, b.factors)
    assert b.shares[cause] > 0.6, b.shares
    assert abs(sum(b.shares.values()) - 1.0) < 1e-9
    text = str(err)
    assert f"Dominant cause: {cause}, {b.shares[cause]:.0%}" in text
    assert "poorly determined" in text and "--max-sigma-mm" in text
    for other in CAUSES:
        assert f"{other} " in text  # every share is listed


def test_intrinsics_uncertainty_alone_is_named_with_the_default_limits() -> None:
    """The issue's case: good poses, but intrinsics known only to 10-15 px."""
    views = _views(GOOD, 0.1)
    cov = IntrinsicsCovariance(("fx", "fy", "cx", "cy"), np.diag([15.0, 15.0, 10.0, 10.0]) ** 2)
    good = calibrate_handeye(views, OBJ, K)  # the same poses with exact intrinsics are accepted
    assert good.uncertainty is not None and good.uncertainty.translation_sigma_norm_mm < 2.0
    with pytest.raises(HandEyeRefusedError) as info:
        calibrate_handeye(views, OBJ, K, intrinsics_cov=cov)
    _check(info.value, "intrinsics uncertainty")
    b = info.value.breakdown
    assert (b.limit_mm, b.limit_deg) == (2.0, 0.2)  # today's defaults
    assert b.poses_mm < 2.0 and b.poses_deg < 0.2  # the poses alone would pass
    assert "refine them jointly" in str(info.value)
    assert "larger rotations" not in str(info.value)  # not the old advice


def test_pose_conditioning_alone_is_named() -> None:
    """Rotations nearly all about the optical axis (rolls), tilts of a few degrees only."""
    poses = [(4.0 * (-1) ** k, 90.0 * (k % 2) + 45.0 * (k % 3), -40 + 80 * k / 14) for k in range(15)]
    err = _refused_at_half(_views(poses, 0.1))
    _check(err, "pose conditioning")
    assert err.breakdown.weakest_rotation_deg < 10.0
    assert "larger rotations about different axes" in str(err)


def test_detection_count_alone_is_named() -> None:
    """Four views of the whole board, well spread in rotation, sharp corners."""
    poses = [(30.0, 0.0, -25.0), (30.0, 90.0, 25.0), (30.0, 180.0, 25.0), (30.0, 270.0, -25.0)]
    err = _refused_at_half(_views(poses, 0.1))
    _check(err, "detection count")
    assert err.breakdown.n_views == 4
    assert "add views" in str(err)


def test_reprojection_error_alone_is_named() -> None:
    """A good capture whose corners are found with 1.5 px noise (blur, a wrong board)."""
    err = _refused_at_half(_views(GOOD, 1.5, seed=3))
    _check(err, "reprojection error")
    assert err.breakdown.pixel_sigma_px > 1.0
    assert "check focus" in str(err)


def test_limits_are_parameters_and_none_disables_them() -> None:
    views = _views(GOOD, 0.3)
    res = calibrate_handeye(views, OBJ, K)
    u = res.uncertainty
    assert u is not None
    with pytest.raises(HandEyeRefusedError, match="exceeds the limits 0.01 mm / none deg"):
        calibrate_handeye(views, OBJ, K, options=HandEyeOptions(max_sigma_mm=0.01, max_sigma_deg=None))
    assert issubclass(HandEyeRefusedError, DegenerateGeometryError)
    loose = dataclasses.replace(HandEyeOptions(), max_sigma_mm=None, max_sigma_deg=None)
    assert np.allclose(calibrate_handeye(views, OBJ, K, options=loose).tcp_T_cam, res.tcp_T_cam)


def test_correlated_intrinsics_are_propagated_with_their_correlation() -> None:
    """fx and fy move together: the covariance with correlation 0.99 gives a different share than
    the same 1-sigmas taken as independent (the old propagation)."""
    views = _views(GOOD, 0.1)
    std = np.array([8.0, 8.0])
    corr = np.array([[1.0, 0.99], [0.99, 1.0]])
    full = IntrinsicsCovariance(("fx", "fy"), corr * np.outer(std, std))
    opts = HandEyeOptions(max_sigma_mm=None, max_sigma_deg=None)
    with_corr = calibrate_handeye(views, OBJ, K, options=opts, intrinsics_cov=full).uncertainty
    independent = calibrate_handeye(views, OBJ, K, options=opts, intrinsics_std={"fx": 8.0, "fy": 8.0}).uncertainty
    assert with_corr is not None and independent is not None
    a = np.trace(with_corr.covariance_intrinsics[3:, 3:])
    b = np.trace(independent.covariance_intrinsics[3:, 3:])
    assert a > 0 and b > 0 and abs(a / b - 1.0) > 0.2


@given(diag=st.lists(st.floats(0.0, 1e-2), min_size=18, max_size=18), pixel=st.floats(0.0, 50.0),
       corners=st.integers(0, 5000), weakest=st.floats(0.0, 180.0))
@settings(max_examples=200, deadline=None)
def test_the_breakdown_is_finite_and_complete_for_any_figures(diag, pixel, corners, weakest) -> None:
    d = np.asarray(diag)
    unc = Uncertainty.from_covariances(np.diag(d[:6]), np.diag(d[6:12]), np.diag(d[12:]))
    b = explain_uncertainty(unc, limit_mm=2.0, limit_deg=0.2, pixel_sigma_px=pixel, n_corners=corners, n_views=3,
                            n_input_views=5, board_corners=24, weakest_rotation_deg=weakest)
    shares = np.array(list(b.shares.values()))
    assert np.all(np.isfinite(shares)) and np.all(shares >= 0) and abs(shares.sum() - 1.0) < 1e-9
    assert b.dominant in CAUSES and set(b.shares) == set(CAUSES)
    assert not re.search(r"\b(nan|inf)\b", b.message())

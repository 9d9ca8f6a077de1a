"""End to end on rendered images: plan -> render -> detect -> intrinsics -> hand-eye -> files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from brave6d.core.transforms import invert
from brave6d.calibration import (
    HandEyeView,
    board_corner_points,
    calibrate_handeye,
    calibrate_intrinsics,
    detect_charuco,
    plan_for_board,
    write_report,
)
from brave6d.calibration.known_truth import (
    default_board,
    default_tcp_T_cam,
    perturb_pose,
    render_board_view,
)

SPEC = default_board()
X_TRUE = default_tcp_T_cam()
K_TRUE = np.array([[600.0, 0.0, 321.0], [0.0, 600.0, 238.5], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.08, 0.03, 0.0, 0.0, 0.0])
SIZE = (640, 480)


@pytest.mark.slow
def test_rendered_capture_calibrates_to_the_truth(tmp_path) -> None:
    rng = np.random.default_rng(0)
    # The plan uses a rough mounting guess; the robot then reaches the poses with the true mounting.
    guess = X_TRUE.copy()
    guess[:3, 3] += [0.005, -0.004, 0.01]
    plan = plan_for_board(SPEC, 0.32, guess, K=K_TRUE, image_size=SIZE)  # default: 30 views, tilts to 40 deg
    W = SPEC.pose.matrix()
    obj = board_corner_points(SPEC)
    detections, views = [], []
    for p in plan:
        true_cam = p.base_T_tcp @ X_TRUE  # where the camera really is
        img = render_board_view(SPEC, K_TRUE, invert(true_cam) @ W, SIZE, DIST_TRUE, noise_sigma=2.0, rng=rng)
        det = detect_charuco(img, SPEC)
        detections.append(det)
        measured = perturb_pose(p.base_T_tcp, 1e-4, 0.01, rng)  # robot pose error on
        views.append(HandEyeView.from_detection(measured, det, p.name))
    assert sum(d.count == len(obj) for d in detections) >= 25

    intrinsics = calibrate_intrinsics(detections, obj, SIZE, names=[p.name for p in plan])
    assert intrinsics.K[0, 0] == pytest.approx(600.0, rel=0.005)
    result = calibrate_handeye(views, obj, intrinsics.K, intrinsics.dist, intrinsics_std=intrinsics.std)
    errors = result.errors_against(X_TRUE)
    mm, deg = errors["refined"]
    assert mm <= 0.5 and deg <= 0.05
    unc = result.uncertainty
    assert unc is not None and np.any(unc.covariance_intrinsics != 0)
    assert mm < 3 * unc.translation_sigma_norm_mm and deg < 3 * unc.rotation_sigma_norm_deg
    # Here the error is dominated by the intrinsics (principal point from the same images), which
    # every method shares: the refinement is as good as the best closed form, not worse.
    for m in ("tsai", "park", "daniilidis"):
        assert mm <= errors[m][0] + 0.05 and deg <= errors[m][1] + 0.005, m

    out = tmp_path / "calibration"
    intrinsics.save(out / "intrinsics.json")
    result.save(out / "handeye.json")
    paths = write_report(out, result, intrinsics, truth_tcp_T_cam=X_TRUE)
    assert json.loads((out / "handeye.json").read_text())["method"].startswith("refined")
    assert "## Intrinsics" in paths.markdown.read_text() and paths.plot is not None and paths.plot.exists()

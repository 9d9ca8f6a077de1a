"""Intrinsics from rendered ChArUco views: recovery, outlier views, factory intrinsics, JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from brave6d.core.board import board_size_m
from brave6d.core.calibration_io import read_intrinsics
from brave6d.core.errors import BraveError, DegenerateGeometryError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import invert
from brave6d.calibration.board import CharucoDetection, board_corner_points, detect_charuco
from brave6d.calibration.intrinsics import (
    IntrinsicsResult,
    calibrate_intrinsics,
    evaluate_intrinsics,
)
from brave6d.calibration.plan import board_T_cam_view
from brave6d.calibration.known_truth import default_board, render_board_view

SPEC = default_board()
K_TRUE = np.array([[610.0, 0.0, 322.0], [0.0, 605.0, 236.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])
SIZE = (640, 480)
OBJ = board_corner_points(SPEC)


def _render_views(n: int, dist: np.ndarray, seed: int = 1) -> list[CharucoDetection]:
    rng = np.random.default_rng(seed)
    w, h = board_size_m(SPEC)
    dets = []
    for k in range(n):
        tilt = 0.0 if k == 0 else 25.0 + 15.0 * (k % 2)
        aim = (w / 2 + rng.uniform(-0.05, 0.05), h / 2 + rng.uniform(-0.04, 0.04), 0.0)
        board_T_cam = board_T_cam_view(aim, rng.uniform(0.3, 0.4), tilt, k * 137.5, rng.uniform(-30, 30))
        img = render_board_view(SPEC, K_TRUE, invert(board_T_cam), SIZE, dist, noise_sigma=2.0, rng=rng)
        dets.append(detect_charuco(img, SPEC))
    return dets


@pytest.fixture(scope="module")
def detections() -> list[CharucoDetection]:
    return _render_views(12, DIST_TRUE)


def test_calibration_recovers_the_intrinsics(detections) -> None:
    assert all(d.count >= 18 for d in detections)
    res = calibrate_intrinsics(detections, OBJ, SIZE)
    assert res.source == "charuco" and res.distortion_model == "5" and len(res.dist) == 5
    assert res.K[0, 0] == pytest.approx(K_TRUE[0, 0], rel=0.005)
    assert res.K[1, 1] == pytest.approx(K_TRUE[1, 1], rel=0.005)
    assert res.K[0, 2] == pytest.approx(K_TRUE[0, 2], abs=2.0)
    assert res.K[1, 2] == pytest.approx(K_TRUE[1, 2], abs=2.0)
    assert res.dist[0] == pytest.approx(DIST_TRUE[0], abs=0.02)
    assert res.rms_px < 0.2
    assert len(res.views) == len(detections)
    assert all(v.used and v.rms_px is not None and v.rms_px < 0.3 for v in res.views)
    assert set(res.std) >= {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    assert res.std["fx"] < 2.0


def test_distortion_models(detections) -> None:
    four = calibrate_intrinsics(detections, OBJ, SIZE, distortion="4")
    assert len(four.dist) == 4
    none = calibrate_intrinsics(detections, OBJ, SIZE, distortion="0")
    assert len(none.dist) == 0
    assert none.rms_px > 3 * four.rms_px  # ignoring real distortion shows in the residuals
    with pytest.raises(ValueError, match="unknown distortion model"):
        calibrate_intrinsics(detections, OBJ, SIZE, distortion="7")


def test_outlier_views_are_dropped_with_a_reason(detections) -> None:
    dets = list(detections)
    rng = np.random.default_rng(3)
    bad = dets[4]
    dets[4] = CharucoDetection(bad.corner_ids, bad.corners_px + rng.normal(0, 3.0, bad.corners_px.shape))
    dets.append(CharucoDetection(dets[1].corner_ids[:5], dets[1].corners_px[:5]))
    dets.append(CharucoDetection.empty())
    names = [f"frame{k}" for k in range(len(dets))]
    res = calibrate_intrinsics(dets, OBJ, SIZE, names=names)
    dropped = {v.name: v.reason for v in res.dropped_views}
    assert set(dropped) == {"frame4", "frame12", "frame13"}
    assert "reprojection RMS" in dropped["frame4"] and "x median" in dropped["frame4"]
    assert dropped["frame12"] == "only 5 ChArUco corners (< 8)"
    assert dropped["frame13"] == "no board detected"
    assert res.K[0, 0] == pytest.approx(K_TRUE[0, 0], rel=0.005)
    assert res.rounds >= 2
    bad_view = next(v for v in res.views if v.name == "frame4")
    assert bad_view.rms_px is not None and bad_view.rms_px > 1.0  # measured with the final intrinsics


def test_too_few_views_raise(detections) -> None:
    with pytest.raises(DegenerateGeometryError, match="2 usable views of 3, at least 4 needed"):
        calibrate_intrinsics([*detections[:2], CharucoDetection.empty()], OBJ, SIZE)


def test_factory_intrinsics_are_only_evaluated(detections) -> None:
    good = evaluate_intrinsics(detections, OBJ, SIZE, K_TRUE, DIST_TRUE)
    assert good.source == "factory"
    assert good.K == pytest.approx(K_TRUE) and good.dist == pytest.approx(DIST_TRUE)
    assert good.rms_px < 0.2
    no_dist = evaluate_intrinsics(detections, OBJ, SIZE, K_TRUE, ())
    assert no_dist.rms_px > 3 * good.rms_px
    with pytest.raises(ValueError, match="coefficients"):
        evaluate_intrinsics(detections, OBJ, SIZE, K_TRUE, [0.1, 0.2, 0.3])


def test_json_round_trip_and_kernel_reader(tmp_path, detections) -> None:
    res = calibrate_intrinsics(detections, OBJ, SIZE)
    scene = SceneDir(tmp_path)
    path = res.save(scene.intrinsics_path)
    doc = json.loads(path.read_text())
    assert doc["schema"] == "brave6d.intrinsics/1" and len(doc["views"]) == len(detections)
    back = IntrinsicsResult.load(path)
    assert back.to_json() == res.to_json()
    assert read_intrinsics(scene) == res.camera()  # what every later stage reads
    path.write_text(json.dumps({**doc, "camera": {**doc["camera"], "K": [[1, 2], [3, 4]]}}))
    with pytest.raises(BraveError, match="intrinsics.json"):
        IntrinsicsResult.load(path)


def test_the_same_views_give_the_same_bits_every_time() -> None:
    """Detection and calibration run OpenCV on one thread: with its thread pool, identical board
    images gave intrinsics that differed in the 10th-13th digit from run to run, and those digits
    reached the trained splat of the next stages (docs/BENCHMARKS.md)."""
    import cv2

    threads = cv2.getNumThreads()
    results = [calibrate_intrinsics(_render_views(12, DIST_TRUE), OBJ, SIZE) for _ in range(4)]
    first = results[0]
    for other in results[1:]:
        assert first.K.tobytes() == other.K.tobytes() and first.dist.tobytes() == other.dist.tobytes()
    assert cv2.getNumThreads() == threads  # the pool is given back

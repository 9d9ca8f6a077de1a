"""Intrinsics held or refined jointly with the hand-eye transform: accuracy, 1-sigma and time.

Two inputs, each solved three ways after detection (which is the same for all):

* ``held-std``: intrinsics from the board views alone, held; their 1-sigmas propagated as if
  independent (the behaviour before issue #36);
* ``held-cov``: the same, their full covariance propagated (correlations included);
* ``joint``: refined jointly with the hand-eye transform (``brave6d calibrate folder``'s default).

1. The real eye-to-hand set ``tests/data/real/ric_charuco_eye_to_hand`` (no truth): 1-sigma and
   solve time, and the distance to OpenCV's calibrateHandEye (Park) given the same intrinsics.
2. Synthetic eye-in-hand captures (``brave6d.calibration.known_truth``: 15 views, +-30 deg, 0.2 px corner
   noise, 0.1 mm / 0.01 deg robot error, lens k1 -0.1; the intrinsics calibrated from the same
   noisy corners): error against the truth, 1-sigma and time, medians over seeds.

OpenBLAS runs single-threaded for stable timings; times are medians of ``--repeats`` runs.

    python benchmarks/handeye_folder.py [--seeds 8] [--repeats 3]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(ROOT / "src"))

from brave6d.core.spec import BoardSpec
from brave6d.core.transforms import invert, make_transform
from brave6d.calibration.board import CharucoDetection, board_corner_points
from brave6d.calibration.eye_to_hand import calibrate_eye_to_hand
from brave6d.calibration.folder import detect_folder
from brave6d.calibration.handeye import HandEyeOptions, HandEyeView, calibrate_handeye
from brave6d.calibration.intrinsics import calibrate_intrinsics_auto
from brave6d.calibration.known_truth import make_handeye_dataset
from brave6d.calibration.pairing import pair_images_with_poses

REAL = ROOT / "tests" / "data" / "real" / "ric_charuco_eye_to_hand"
REAL_BOARD = BoardSpec(squares_x=5, squares_y=7, square_length_m=0.036195, marker_length_m=0.018256,
                       dictionary="DICT_6X6_250")
MODES = ("held-std", "held-cov", "joint")


def _solve(solver: Any, views: list[HandEyeView], obj: np.ndarray, intr: Any, mode: str) -> Any:
    opts = HandEyeOptions(max_sigma_mm=None, max_sigma_deg=None)
    if mode == "joint":
        opts = HandEyeOptions(max_sigma_mm=None, max_sigma_deg=None, refine_intrinsics=intr.covariance.names)
        return solver(views, obj, intr.K, intr.dist, opts)
    if mode == "held-cov":
        return solver(views, obj, intr.K, intr.dist, opts, intrinsics_cov=intr.covariance)
    return solver(views, obj, intr.K, intr.dist, opts, intrinsics_std=intr.std)


def _timed(fn: Any, repeats: int) -> tuple[Any, float]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def _err(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    from scipy.spatial.transform import Rotation

    return (1000.0 * float(np.linalg.norm(A[:3, 3] - B[:3, 3])),
            math.degrees(Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).magnitude()))


def real_set(repeats: int) -> None:
    inputs = pair_images_with_poses(REAL / "images", REAL / "poses")
    detections, size = detect_folder(inputs, REAL_BOARD)
    obj = board_corner_points(REAL_BOARD)
    intr = calibrate_intrinsics_auto(detections, obj, size, names=inputs.names)
    views = [HandEyeView.from_detection(G, d, n) for G, d, n in zip(inputs.poses, detections, inputs.names)]
    print(f"\n1. real eye-to-hand set ({len(views)} images {size[0]}x{size[1]}, {REAL.relative_to(ROOT)})")
    print(f"{'mode':10s} {'1-sigma mm':>10s} {'of it intr.':>11s} {'1-sigma deg':>11s} {'vs OpenCV mm':>12s} "
          f"{'vs OpenCV deg':>13s} {'time s':>7s}")
    for mode in MODES:
        res, dt = _timed(lambda: _solve(calibrate_eye_to_hand, views, obj, intr, mode), repeats)
        sol = res.solution
        u = sol.uncertainty
        # OpenCV's Park on the inverted robot poses with OpenCV's PnP under the same intrinsics
        R_c, t_c, R_g, t_g = [], [], [], []
        for v in views:
            if len(v.corner_ids) < 6:
                continue
            ok, rvec, tvec = cv2.solvePnP(obj[v.corner_ids], v.corners_px, sol.K, sol.dist)
            Gi = invert(v.base_T_tcp)
            R_c.append(cv2.Rodrigues(rvec)[0]), t_c.append(tvec.reshape(3)), R_g.append(Gi[:3, :3]), t_g.append(Gi[:3, 3])
        R, t = cv2.calibrateHandEye(R_g, t_g, R_c, t_c, method=cv2.CALIB_HAND_EYE_PARK)
        mm, deg = _err(make_transform(R, t.reshape(3)), res.base_T_cam)
        intr_mm = 1000.0 * math.sqrt(max(float(np.trace(u.covariance_intrinsics[3:, 3:])), 0.0))
        print(f"{mode:10s} {u.translation_sigma_norm_mm:10.3f} {intr_mm:11.3f} {u.rotation_sigma_norm_deg:11.4f} "
              f"{mm:12.3f} {deg:13.4f} {dt:7.2f}")


def synthetic(seeds: int, repeats: int) -> None:
    rows: dict[str, list[tuple[float, float, float, float, float]]] = {m: [] for m in MODES}
    for seed in range(seeds):
        ds = make_handeye_dataset(15, 30.0, seed=100 + seed, pixel_noise_px=0.2, robot_translation_noise_m=1e-4,
                                  robot_rotation_noise_deg=0.01, dist=(-0.1, 0.02, 0.0, 0.0, 0.0))
        dets = [CharucoDetection(v.corner_ids, v.corners_px) for v in ds.views]
        intr = calibrate_intrinsics_auto(dets, ds.object_points, ds.image_size)
        for mode in MODES:
            res, dt = _timed(lambda: _solve(calibrate_handeye, ds.views, ds.object_points, intr, mode), repeats)
            mm, deg = res.errors_against(ds.tcp_T_cam)["refined"]
            u = res.uncertainty
            rows[mode].append((mm, deg, u.translation_sigma_norm_mm, u.rotation_sigma_norm_deg, dt))
    print(f"\n2. synthetic eye-in-hand, 15 views, intrinsics from the same corners; medians over {seeds} seeds")
    print(f"{'mode':10s} {'error mm':>9s} {'error deg':>9s} {'1-sigma mm':>10s} {'1-sigma deg':>11s} {'time s':>7s}")
    for mode, r in rows.items():
        med = [statistics.median(c) for c in zip(*r)]
        print(f"{mode:10s} {med[0]:9.3f} {med[1]:9.4f} {med[2]:10.3f} {med[3]:11.4f} {med[4]:7.2f}")
    base = statistics.median(r[4] for r in rows["held-cov"])
    print(f"time ratio joint / held-cov: {statistics.median(r[4] for r in rows['joint']) / base:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, OpenCV {cv2.__version__}, "
          f"numpy {np.__version__}")
    real_set(args.repeats)
    synthetic(args.seeds, args.repeats)


if __name__ == "__main__":
    main()

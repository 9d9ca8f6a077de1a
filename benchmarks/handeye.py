"""Hand-eye accuracy against the number of poses and the rotation span, with solve time.

Synthetic eye-in-hand captures (brave6d.calibration.known_truth: the spec's default board 0.45 m from
the camera, 640x480 camera with f = 600 px, corner noise and robot pose error as given) are
solved by every closed-form method and by the joint refinement. The conditioning check runs
with relaxed thresholds so that poor geometry is measured instead of refused; the column
"refused" counts the trials that the default check would refuse. Times: closed-form = the
solver alone; refined = everything after PnP (all solvers, board fits, refinement); OpenBLAS
runs single-threaded for stable timings.

    python benchmarks/handeye.py [--quick] [--json out.json] [--pixel-noise 0.2]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(ROOT / "src"))

from brave6d.core.errors import DegenerateGeometryError
from brave6d.calibration.conditioning import ConditioningThresholds, check_handeye_conditioning
from brave6d.calibration.handeye import HandEyeOptions, calibrate_handeye, estimate_board_pose
from brave6d.calibration.known_truth import make_handeye_dataset

METHODS = ("tsai", "park", "daniilidis", "refined")


def _default_check_refuses(ds: Any) -> str | None:
    """The cause the default conditioning check would name, or None if it accepts."""
    G, C = [], []
    for v in ds.views:
        pnp = estimate_board_pose(v.corner_ids, v.corners_px, ds.object_points, ds.K, ds.dist)
        if pnp is not None and len(v.corner_ids) >= 6:
            G.append(v.base_T_tcp)
            C.append(pnp[0])
    try:
        check_handeye_conditioning(G, C)
    except DegenerateGeometryError as exc:
        return str(exc).split(":")[0]
    return None


def run_cell(n_poses: int, span: float, trials: int, args: argparse.Namespace) -> dict[str, Any]:
    opts = HandEyeOptions(conditioning=ConditioningThresholds.relaxed(), max_sigma_mm=None, max_sigma_deg=None)
    errs: dict[str, list[tuple[float, float]]] = {m: [] for m in METHODS}
    times: dict[str, list[float]] = {m: [] for m in METHODS}
    refused, failures, sigmas = 0, [], []
    for trial in range(trials):
        ds = make_handeye_dataset(
            n_poses, span, seed=1000 * n_poses + 10 * int(span) + trial, pixel_noise_px=args.pixel_noise,
            robot_translation_noise_m=args.robot_noise_mm * 1e-3, robot_rotation_noise_deg=args.robot_noise_deg,
            distance_m=args.distance,
        )
        refused += _default_check_refuses(ds) is not None
        try:
            res = calibrate_handeye(ds.views, ds.object_points, ds.K, ds.dist, opts)
        except DegenerateGeometryError as exc:
            failures.append(str(exc)[:120])
            continue
        for method, e in res.errors_against(ds.tcp_T_cam).items():
            errs[method].append(e)
        for m in res.methods:
            times[m.method].append(m.time_s)
        if res.uncertainty is not None:
            sigmas.append((res.uncertainty.translation_sigma_norm_mm, res.uncertainty.rotation_sigma_norm_deg))
    out: dict[str, Any] = {"n_poses": n_poses, "span_deg": span, "trials": trials, "refused_by_default_check": refused,
                           "failures": failures, "methods": {}}
    for m in METHODS:
        if not errs[m]:
            continue
        a = np.asarray(errs[m])
        out["methods"][m] = {
            "median_mm": float(np.median(a[:, 0])), "median_deg": float(np.median(a[:, 1])),
            "p90_mm": float(np.percentile(a[:, 0], 90)), "p90_deg": float(np.percentile(a[:, 1], 90)),
            "median_time_ms": 1000.0 * statistics.median(times[m]),
        }
    if errs["refined"]:
        r = np.asarray(errs["refined"])
        best_cf = np.min(np.stack([np.asarray(errs[m]) for m in METHODS[:3]]), axis=0)
        out["refined_wins_mm"] = float(np.mean(r[:, 0] < best_cf[:, 0]))
        out["refined_wins_deg"] = float(np.mean(r[:, 1] < best_cf[:, 1]))
        s = np.asarray(sigmas)
        out["median_sigma_mm"], out["median_sigma_deg"] = float(np.median(s[:, 0])), float(np.median(s[:, 1]))
    return out


def print_table(cells: list[dict[str, Any]]) -> None:
    head = f"{'poses':>5} {'span':>5} {'ref.':>4} |" + "".join(f" {m:>22} |" for m in METHODS) + " wins(mm,deg) | 1-sigma"
    print(head)
    print(f"{'':>5} {'deg':>5} {'':>4} |" + "".join(f" {'mm':>6} {'deg':>7} {'ms':>6}  |" for _ in METHODS))
    print("-" * len(head))
    for c in cells:
        row = f"{c['n_poses']:>5} {c['span_deg']:>5.0f} {c['refused_by_default_check']:>2}/{c['trials']:<1} |"
        for m in METHODS:
            s = c["methods"].get(m)
            row += (f" {s['median_mm']:6.3f} {s['median_deg']:7.4f} {s['median_time_ms']:6.1f}  |" if s
                    else f" {'failed':>22} |")
        if "refined_wins_mm" in c:
            row += f"  {c['refined_wins_mm']:.2f} {c['refined_wins_deg']:.2f}  | {c['median_sigma_mm']:.3f} mm {c['median_sigma_deg']:.4f} deg"
        if c["failures"]:
            row += f"  ({len(c['failures'])} refused: {c['failures'][0][:60]})"
        print(row)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="3 trials per cell instead of 10")
    parser.add_argument("--trials", type=int, default=None, help="trials per cell (overrides --quick)")
    parser.add_argument("--poses", type=int, nargs="+", default=[5, 10, 20, 40])
    parser.add_argument("--spans", type=float, nargs="+", default=[5, 15, 30, 60], help="+- rotation span, deg")
    parser.add_argument("--pixel-noise", type=float, default=0.2, help="corner noise, px (1-sigma per axis)")
    parser.add_argument("--robot-noise-mm", type=float, default=0.1, help="robot translation error, mm per axis")
    parser.add_argument("--robot-noise-deg", type=float, default=0.01, help="robot rotation error, deg per axis")
    parser.add_argument("--distance", type=float, default=0.45, help="camera to board, m")
    parser.add_argument("--json", type=Path, default=None, help="write the results as JSON here")
    args = parser.parse_args(argv)
    trials = args.trials or (3 if args.quick else 10)

    t0 = time.perf_counter()
    cells = [run_cell(n, s, trials, args) for n in args.poses for s in args.spans]
    elapsed = time.perf_counter() - t0
    print(f"hand-eye benchmark: median over {trials} trials per cell; pixel noise {args.pixel_noise} px, robot "
          f"error {args.robot_noise_mm} mm / {args.robot_noise_deg} deg per axis, board at {args.distance} m; "
          f"'ref.' = trials the default conditioning check refuses")
    print_table(cells)
    print(f"total {elapsed:.1f} s")
    if args.json is not None:
        doc = {
            "benchmark": "handeye",
            "config": {"trials": trials, "pixel_noise_px": args.pixel_noise, "robot_noise_mm": args.robot_noise_mm,
                       "robot_noise_deg": args.robot_noise_deg, "distance_m": args.distance,
                       "machine": platform.platform(), "python": platform.python_version()},
            "cells": cells,
            "elapsed_s": elapsed,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

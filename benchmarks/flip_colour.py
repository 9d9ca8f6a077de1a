"""What colour buys the static estimator, and what it costs: the realism sweep (captured frames vs the
splat's renders of the same poses) once per colour weight, per ring: AR on each side, the gap with
its standard error, and the median time of one estimate.

    python benchmarks/flip_colour.py runs/demo [--weights 0,0.1] [--holdout-per-level 8]
                                     [--train-per-level 22] [--device cpu] [--time-every 15]

Weight 0 is depth alone: a near-symmetric object and its 180 degree flip explain the depth alike
and the winner follows noise (on the splat, its training noise). The agents' default weight is
``brave6d.evaluation.agents.registration.COLOR_WEIGHT``. The weights run one after the other on the
same views; the splat is rendered once per weight. Their times per estimate are therefore not side by
side; ``--time-every K`` then times the estimator on every K-th captured frame's targets, the weights
alternating target by target (which goes first alternates too), and prints the medians and the median
ratio against the first weight (0 skips it).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np

from brave6d.core.layout import SceneDir
from brave6d.evaluation.report.measurements import MeasurementStore
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.sections.realism import RealismSweep, gap_rows, measure_realism, targets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdir", type=Path, help="a directory holding scene/ (e.g. runs/demo)")
    parser.add_argument("--weights", default="0,0.1", help="comma-separated colour weights (0: depth alone)")
    parser.add_argument("--holdout-per-level", type=int, default=8)
    parser.add_argument("--train-per-level", type=int, default=22)
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--time-every", type=int, default=15, help="interleaved timing on every K-th frame (0: none)")
    args = parser.parse_args()
    weights = [float(w) for w in args.weights.split(",") if w.strip()]
    if not weights or any(not w >= 0 for w in weights):
        parser.error(f"--weights must be non-negative numbers, got {args.weights!r}")
    print("| weight | cm | targets | AR captured | AR splat | gap ± SE | estimate s (median, captured / splat) |")
    print("|---|---|---|---|---|---|---|")
    for weight in weights:
        sweep = RealismSweep(holdout_per_level=args.holdout_per_level, train_per_level=args.train_per_level,
                             device=args.device, color_weight=weight)
        with tempfile.TemporaryDirectory() as cache:
            inputs = MeasureInputs(args.workdir, SceneDir(args.workdir / "scene"),
                                   MeasurementStore(cache, refresh=True))
            measured = measure_realism(inputs, sweep)
        objects = targets(measured.points)
        for r in gap_rows(measured.points):
            ring = [o for o in objects if abs(o["distance_m"] - r["distance_m"]) < 1e-9]
            real_s = statistics.median(o["real_estimate_s"] for o in ring) if ring else float("nan")
            splat_s = statistics.median(o["splat_estimate_s"] for o in ring) if ring else float("nan")
            print(f"| {weight:g} | {100 * r['distance_m']:.0f} | {r['targets']} | {r['ar_real']:.3f} | "
                  f"{r['ar_splat']:.3f} | {r['gap']:.3f} ± {r['gap_se']:.3f} | {real_s:.2f} / {splat_s:.2f} |",
                  flush=True)

    if args.time_every > 0:
        times = interleaved_times(args.workdir / "scene", weights, args.time_every)
        base = np.asarray(times[weights[0]])
        for weight in weights:
            ratio = float(np.median(np.asarray(times[weight]) / base))
            print(f"weight {weight:g}: {len(base)} targets, median {statistics.median(times[weight]):.3f} s per "
                  f"estimate, median ratio to weight {weights[0]:g}: {ratio:.3f}")


def interleaved_times(scene_dir: Path, weights: list[float], every: int) -> dict[float, list[float]]:
    """Seconds per estimate of each weight on the targets of every ``every``-th captured frame of the
    BOP export, the weights taking turns target by target (and rotating which goes first)."""
    from brave6d.annotation import BopLayout, read_models_info, read_scene_camera, read_scene_gt, read_scene_gt_info
    from brave6d.core.atomic import read_png
    from brave6d.core.transforms import invert
    from brave6d.evaluation.report.real_vs_splat import depth_png_to_m
    from brave6d.evaluation.report.single_view import MIN_VISIB_FRACT, StaticEstimator, model_centre_m, project

    layout = BopLayout.of_scene(SceneDir(scene_dir))
    cams, gts = read_scene_camera(layout.scene_camera_path), read_scene_gt(layout.scene_gt_path)
    infos, info = read_scene_gt_info(layout.scene_gt_info_path), read_models_info(layout.models_info_path)
    models = {k: (layout.model_path(k), float(info[k]["diameter"])) for k in sorted({g.obj_id for i in gts for g in gts[i]})}
    estimators = {w: StaticEstimator(models, w) for w in weights}
    times: dict[float, list[float]] = {w: [] for w in weights}
    turn = 0
    for im_id in sorted(gts)[::every]:
        cam = cams[im_id]
        world_T_cam, K = invert(cam.cam_T_world()), cam.cam_K
        rgb = read_png(layout.rgb_path(im_id), "rgb")
        depth = depth_png_to_m(read_png(layout.depth_path(im_id), "depth"), cam.depth_scale)
        for g, gi in zip(gts[im_id], infos[im_id]):
            if gi.visib_fract < MIN_VISIB_FRACT:
                continue
            cam_T_obj = g.cam_T_model()
            centre = model_centre_m(estimators[weights[0]].cloud(g.obj_id).points * 1000.0)  # the sample in mm
            pixel = project(cam_T_obj[:3, :3] @ centre + cam_T_obj[:3, 3], K)
            for weight in weights[turn % len(weights):] + weights[:turn % len(weights)]:
                times[weight].append(estimators[weight].estimate(depth, K, world_T_cam, g.obj_id, pixel, rgb).seconds)
            turn += 1
    return times


if __name__ == "__main__":
    main()

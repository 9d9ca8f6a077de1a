"""Accuracy against time of the single-frame estimator's settings (``brave6d estimate``), on real data.

Run: ``.venv/bin/python benchmarks/estimate_frame.py [--split DIR --models DIR] [--repeats 3]``.
Default data: the real LM-O frame shipped in ``tests/data/real/lmo_scene2_im3`` (objects 5 and 8);
any BOP split works (every instance with visib_fract >= 0.1, hinted by its ``bbox_visib``).
For the default settings and for each setting lowered and raised alone, prints BOP19 AR (pooled over
the instances), its VSD / MSSD / MSPD parts, the mean MSSD (mm), the refusals, and the median
estimation time per instance with its ratio to the default's, the settings interleaved round by round.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace
from pathlib import Path

from brave6d.annotation import model_file, read_models_info, read_scene_camera, read_scene_gt, read_scene_gt_info
from brave6d.evaluation.agents import (
    BoxHint,
    EstimateRefused,
    FrameOptions,
    estimate_pose,
    prepare_model,
    read_depth_png,
)
from brave6d.evaluation.estimate_bop import MIN_VISIB_FRACT, scene_folders
from brave6d.evaluation.metrics import Estimate, evaluate_bop19, load_models, load_scene_gt_instances

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "tests" / "data" / "real" / "lmo_scene2_im3"

#: (label, model points, registration overrides, perception overrides): the default, then one setting
#: lowered / raised at a time (a plane fit's iterations: the "up" fit gets twice as many, as by default).
SETTINGS: list[tuple[str, int, dict[str, object], dict[str, object]]] = [
    ("default", 2000, {}, {}),
    ("plane_voxel_m=0.01", 2000, {}, {"plane_voxel_m": 0.01}),
    ("plane_voxel_m=0.002", 2000, {}, {"plane_voxel_m": 0.002}),
    ("plane_iterations=200", 2000, {}, {"plane_iterations": 200}),
    ("plane_iterations=1000", 2000, {}, {"plane_iterations": 1000}),
    ("plane_voxel_m=0.01, iterations=200", 2000, {}, {"plane_voxel_m": 0.01, "plane_iterations": 200}),
    ("model_points=500", 500, {}, {}),
    ("model_points=5000", 5000, {}, {}),
    ("ransac_seeds=0 (resting only)", 2000, {"ransac_seeds": ()}, {}),
    ("ransac_seeds=1", 2000, {"ransac_seeds": (0,)}, {}),
    ("ransac_seeds=8", 2000, {"ransac_seeds": tuple(range(8))}, {}),
    ("ransac_iterations=5000", 2000, {"ransac_iterations": 5000}, {}),
    ("ransac_iterations=80000", 2000, {"ransac_iterations": 80000}, {}),
    ("icp_iterations=10", 2000, {"icp_iterations": 10}, {}),
    ("icp_iterations=60", 2000, {"icp_iterations": 60}, {}),
    ("yaw_steps=4", 2000, {"yaw_steps": 4}, {}),
    ("yaw_steps=16", 2000, {"yaw_steps": 16}, {}),
    ("voxel_fraction=0.12", 2000, {"voxel_fraction": 0.12}, {}),
    ("voxel_fraction=0.05", 2000, {"voxel_fraction": 0.05}, {}),
]


def instances(split: Path, models: Path) -> list[tuple[object, object, object, object]]:
    """``(gt instance, depth m, K, box)`` of every visible instance whose model exists."""
    info = read_models_info(models / "models_info.json")
    out = []
    for scene in scene_folders(split):
        cams = read_scene_camera(scene / "scene_camera.json")
        gt, gt_info = read_scene_gt(scene / "scene_gt.json"), read_scene_gt_info(scene / "scene_gt_info.json")
        inst = load_scene_gt_instances(scene, with_depth=True)
        k = 0
        for im_id in sorted(gt):
            depth = read_depth_png(scene / "depth" / f"{im_id:06d}.png", cams[im_id].depth_scale)
            for g, gi in zip(gt[im_id], gt_info[im_id]):
                if gi.visib_fract >= MIN_VISIB_FRACT and g.obj_id in info:
                    out.append((inst[k], depth, cams[im_id].cam_K, gi.bbox_visib))
                k += 1
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", type=Path, default=SAMPLE / "test")
    ap.add_argument("--models", type=Path, default=SAMPLE / "models_eval")
    ap.add_argument("--repeats", type=int, default=3,
                    help="rounds; each round runs every setting on every instance, settings interleaved")
    ap.add_argument("--only", nargs="+", default=None, help="labels of SETTINGS to run")
    args = ap.parse_args()
    info = read_models_info(args.models / "models_info.json")
    todo = instances(args.split, args.models)
    objs = sorted({g.obj_id for g, *_ in todo})
    models = load_models(args.models, objs)
    chosen = [s for s in SETTINGS if not args.only or s[0] in args.only]
    runs = []
    for label, points, reg, per in chosen:
        d = FrameOptions()
        options = replace(d, registration=replace(d.registration, **reg), perception=replace(d.perception, **per),
                          up_plane_iterations=2 * int(per.get("plane_iterations", d.perception.plane_iterations)))
        clouds = {o: prepare_model(model_file(args.models, o), obj_id=o, diameter=float(info[o]["diameter"]),
                                   points=points) for o in objs}
        runs.append((label, options, clouds))
    times: dict[str, list[float]] = {label: [] for label, *_ in runs}
    poses: dict[str, list[object]] = {}
    for _ in range(max(1, args.repeats)):  # interleaved: a load change on a shared machine hits every setting
        for label, options, clouds in runs:
            found = []
            for g, depth, K, box in todo:
                t0 = time.perf_counter()
                try:
                    found.append(estimate_pose(depth, K, clouds[g.obj_id], BoxHint(*box), options=options))
                except EstimateRefused:
                    found.append(None)
                times[label].append(time.perf_counter() - t0)
            poses.setdefault(label, found)  # deterministic: every round finds the same poses
    print(f"{len(todo)} instances of objects {objs} in {args.split}; {args.repeats} interleaved rounds")
    print(f"{'setting':36s} {'AR':>6s} {'VSD':>6s} {'MSSD':>6s} {'MSPD':>6s} {'mssd mm':>8s} {'refused':>7s} "
          f"{'s/inst':>7s} {'x default':>9s}")
    base = statistics.median(times[runs[0][0]])
    for label, *_ in runs:
        ests = [Estimate(g.scene_id, g.im_id, g.obj_id, p.score, p.R, p.t_mm)
                for (g, *_), p in zip(todo, poses[label]) if p is not None]
        scores = evaluate_bop19([g for g, *_ in todo], ests, models)
        mssds = [float(e.mssd.min()) for e in scores.errors if e.mssd is not None and len(e.mssd)]
        m, t = scores.metrics, statistics.median(times[label])
        refused = sum(p is None for p in poses[label])
        print(f"{label:36s} {scores.ar:6.3f} {m['vsd'].ar:6.3f} {m['mssd'].ar:6.3f} {m['mspd'].ar:6.3f} "
              f"{(statistics.mean(mssds) if mssds else float('nan')):8.1f} {refused:7d} {t:7.2f} {t / base:9.2f}")


if __name__ == "__main__":
    main()

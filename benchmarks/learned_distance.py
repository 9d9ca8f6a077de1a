"""Does coming closer help the learned estimator? Trained models scored on a test split per camera
distance: AR of the four held-out variants, the RGB-only pose's VSD / MSSD / MSPD recalls given the
true box, and its errors: the rotation's (degrees, the symmetry nearest the truth) and the distance's
(per cent of the true distance).

    python benchmarks/learned_distance.py MODELS_DIR TEST_PBR NAME=MODEL_DIR [NAME=MODEL_DIR ...]
        [--edges 0,0.25,0.3,0.35,0.4,0.45,10] [--json OUT.json]

VSD and MSSD count 3D errors against the object's size, so a constant relative distance error costs
less the nearer the camera; MSPD counts pixels, so a constant angular error costs more. An estimator
is better near than far when its errors shrink with distance faster than that: the rotation's in
degrees, the distance's in per cent. A split of ``brave6d synth`` draws camera distances uniformly
over the scene's capture rings. The figures of docs/BENCHMARKS.md ("Closer views") come from here.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

DEFAULT_EDGES = (0.0, 0.25, 0.3, 0.35, 0.4, 0.45, 10.0)


def rotation_error_deg(R_true: Any, R_est: Any, symmetries: Any) -> float:
    """The angle (degrees) between ``R_est`` and the symmetric pose of ``R_true`` nearest it."""
    import numpy as np

    cosines = [(np.trace((np.asarray(R_true) @ S).T @ np.asarray(R_est)) - 1.0) / 2.0 for S in symmetries]
    return float(np.degrees(np.arccos(np.clip(max(cosines), -1.0, 1.0))))


def by_distance(name: str, model_dir: Path, models_dir: Path, test_pbr: Path, edges: list[float]) -> dict[str, Any]:
    """One model's figures on ``test_pbr``, overall and per bin of the true camera-object distance."""
    import numpy as np

    from brave6d.evaluation.learned import LearnedEstimator
    from brave6d.evaluation.learned.data import load_training_data
    from brave6d.evaluation.learned.heldout import POSE_VARIANTS, score_heldout
    from brave6d.evaluation.learned.model_file import read_model
    from brave6d.evaluation.metrics import DepthRenderer, evaluate_bop19, load_models

    preset = read_model(model_dir).preset
    data = load_training_data(test_pbr, models_dir, int(preset["work_width"]), int(preset["heldout_every"]),
                              show_progress=False, crop_width=int(preset.get("crop_source_width", preset["work_width"])))
    held = score_heldout(LearnedEstimator.load(model_dir, models_dir=models_dir), data, models_dir,
                         show_progress=False, images=list(range(len(data.images))), keep_estimates=True)
    assert held.gts is not None and held.estimates is not None
    models = load_models(models_dir, sorted(data.objects))
    renderer = DepthRenderer()
    distance = np.array([float(np.linalg.norm(g.t)) / 1000.0 for g in held.gts])
    errors: dict[int, tuple[float, float]] = {}
    for gt_index, e in held.estimates["true_box_rgb"]:
        g = held.gts[gt_index]
        rot = rotation_error_deg(g.R, e.R, data.objects[g.obj_id].sym_R)
        errors[gt_index] = (rot, 100.0 * (float(np.linalg.norm(e.t)) - float(np.linalg.norm(g.t))) / float(np.linalg.norm(g.t)))
    bins = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        chosen = set(np.nonzero((distance >= lo) & (distance < hi))[0].tolist())
        if not chosen:
            continue
        gts = [held.gts[i] for i in sorted(chosen)]
        row: dict[str, Any] = {"from_m": lo, "to_m": hi, "targets": len(gts)}
        for variant in POSE_VARIANTS:
            scores = evaluate_bop19(gts, [e for i, e in held.estimates[variant] if i in chosen], models,
                                    renderer=renderer, keep_errors=False)
            row[variant] = float(scores.ar)
            if variant == "true_box_rgb":
                row["true_box_rgb_metrics"] = {"vsd": float(scores.ar_vsd), "mssd": float(scores.ar_mssd),
                                               "mspd": float(scores.ar_mspd)}
        errs = np.array([errors[i] for i in chosen if i in errors]).reshape(-1, 2)
        row["rotation_deg_median"] = float(np.median(errs[:, 0])) if len(errs) else None
        row["rotation_over_30deg"] = float(np.mean(errs[:, 0] > 30.0)) if len(errs) else None
        row["distance_error_pct_median"] = float(np.median(np.abs(errs[:, 1]))) if len(errs) else None
        bins.append(row)
    return {"name": name, "model": str(model_dir), "images": held.images, "instances": held.instances,
            "pose_ar": held.pose_ar, "recall": {str(k): v for k, v in held.recall.items()}, "bins": bins}


def table(result: dict[str, Any]) -> str:
    """One model's bins as a markdown table."""
    from brave6d.core.progress import format_table

    rows = [(f"{b['from_m']:.2f}-{b['to_m']:.2f}" if b["to_m"] < 10 else f">= {b['from_m']:.2f}", b["targets"],
             f"{b['true_box_rgb']:.3f}", " / ".join(f"{b['true_box_rgb_metrics'][k]:.2f}" for k in ("vsd", "mssd", "mspd")),
             f"{b['true_box_depth']:.3f}", f"{b['rotation_deg_median']:.1f}", f"{b['rotation_over_30deg']:.2f}",
             f"{b['distance_error_pct_median']:.2f}") for b in result["bins"]]
    return format_table(["distance m", "targets", "AR true box RGB", "VSD / MSSD / MSPD", "AR true box + depth",
                         "rotation error deg (median)", "share > 30 deg", "distance error % (median)"], rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models_dir", type=Path, help="BOP models folder of the split's objects")
    ap.add_argument("test_pbr", type=Path, help="a train_pbr split none of the models trained on")
    ap.add_argument("models", nargs="+", metavar="NAME=MODEL_DIR", help="trained model folders to compare")
    ap.add_argument("--edges", default=",".join(str(e) for e in DEFAULT_EDGES),
                    help="distance bins' edges in metres (comma-separated)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    edges = [float(x) for x in args.edges.split(",")]
    if len(edges) < 2 or edges != sorted(edges):
        ap.error(f"--edges: at least two increasing distances, got {args.edges}")
    results = []
    for item in args.models:
        name, sep, folder = item.partition("=")
        if not sep or not name or not (Path(folder) / "model.pt").is_file():
            ap.error(f"{item!r}: give NAME=MODEL_DIR with a model.pt in MODEL_DIR")
        result = by_distance(name, Path(folder), args.models_dir, args.test_pbr, edges)
        results.append(result)
        ar = result["pose_ar"]
        print(f"\n{name} ({result['instances']} instances): AR true box RGB {ar['true_box_rgb']:.3f}, + depth "
              f"{ar['true_box_depth']:.3f}")
        print(table(result))
        near, far = result["bins"][0], result["bins"][-1]
        print(f"nearest bin - farthest bin, true box RGB: {near['true_box_rgb'] - far['true_box_rgb']:+.3f}")
    if args.json is not None:
        args.json.write_text(json.dumps({"edges": edges, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

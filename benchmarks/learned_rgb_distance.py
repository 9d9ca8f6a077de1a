"""What the RGB-only distance from the mask's area and the crops at several zooms buy and cost: a
trained model scored on a test split three times, side by side: PnP's own distance from one crop,
the distance from the mask's area against the model's silhouette
(``LearnedEstimator.mask_area_distance``), and that with the coordinate net looking at three zooms
of each box, one PnP over all their correspondences (``LearnedEstimator.crop_zooms``).

    python benchmarks/learned_rgb_distance.py MODEL_DIR MODELS_DIR TEST_PBR --out DIR
        [--bundle BUNDLE --episodes-per-object 6]

Per setting: pose AR of the four held-out variants, the BOP metrics' recalls (VSD, MSSD, MSPD) of
the RGB-only pose given the true box, and the median milliseconds per estimate. Ceilings, from the
same RGB-only estimates given true boxes: AR with the true distance (the translation moved along its
ray), and with the true distance off by a seeded relative error of 1 % and 2 % (standard
deviation): how good a distance the RGB-only target needs. With ``--bundle`` the four learned agents
also play that bundle's seeded episodes with each setting. Writes ``DIR/rgb_distance.json``; with
DIR at ``<workdir>/learned/cost`` report section 10 tabulates it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from brave6d.evaluation.learned.inference import CROP_ZOOMS

REPORT_FILE = "rgb_distance.json"
#: setting -> (LearnedEstimator.mask_area_distance, LearnedEstimator.crop_zooms); the last: the defaults
SETTINGS: dict[str, tuple[bool, tuple[float, ...]]] = {"pnp": (False, (1.0,)), "mask-area": (True, (1.0,)),
                                                       "mask-area, 3 zooms": (True, CROP_ZOOMS)}
CEILING_ERRORS = (0.01, 0.02)


def true_box_rgb_metrics(held: Any, models_dir: Path, seed: int = 0) -> dict[str, Any]:
    """The RGB-only pose given each true box (``held``: :func:`score_heldout`'s scores, its estimates
    kept): its AR and per-metric recalls, and the ceilings (AR of the same poses moved along their
    rays to the true distance, exact and off by :data:`CEILING_ERRORS`)."""
    import numpy as np

    from brave6d.evaluation.metrics import DepthRenderer, Estimate, evaluate_bop19, load_models

    rng = np.random.default_rng(seed)
    models = load_models(models_dir, sorted({g.obj_id for g in held.gts}))
    runs: dict[str, list[Any]] = {"true distance": []} | {f"distance {e:.0%} off": [] for e in CEILING_ERRORS}
    for gt_index, e in held.estimates["true_box_rgb"]:
        t_true = e.t * (float(np.asarray(held.gts[gt_index].t).reshape(3)[2]) / float(e.t[2]))
        ids = (e.scene_id, e.im_id, e.obj_id, e.score)
        runs["true distance"].append(Estimate(*ids, e.R, t_true))
        for err in CEILING_ERRORS:
            runs[f"distance {err:.0%} off"].append(Estimate(*ids, e.R, t_true * (1.0 + err * rng.standard_normal())))
    renderer = DepthRenderer()
    metrics = held.pose_ar_metrics["true_box_rgb"]
    return {"ar": held.pose_ar["true_box_rgb"], "vsd": metrics["vsd"], "mssd": metrics["mssd"], "mspd": metrics["mspd"],
            "ceilings": {name: evaluate_bop19(held.gts, estimates, models, renderer=renderer, keep_errors=False).ar
                         for name, estimates in runs.items()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="a trained model folder (model.pt)")
    parser.add_argument("models", type=Path, help="BOP models folder (the meshes the silhouettes come from)")
    parser.add_argument("test_pbr", type=Path, help="a split never trained on (every image is scored)")
    parser.add_argument("--out", type=Path, required=True, help="folder of rgb_distance.json")
    parser.add_argument("--bundle", type=Path, default=None, help="a bundle to play the learned agents on")
    parser.add_argument("--episodes-per-object", type=int, default=6)
    args = parser.parse_args(argv)

    from brave6d.core.atomic import atomic_write_json
    from brave6d.evaluation.demo import learned_agent_scores
    from brave6d.evaluation.learned import LearnedEstimator, load_training_data, read_model, score_heldout

    preset = read_model(args.model).preset
    test = load_training_data(args.test_pbr, args.models, int(preset["work_width"]), 2,
                              crop_width=int(preset.get("crop_source_width", preset["work_width"])))
    rows = []
    default = LearnedEstimator.mask_area_distance, LearnedEstimator.crop_zooms
    try:
        for name, (on, zooms) in SETTINGS.items():
            # on the class: the agents' estimators too
            LearnedEstimator.mask_area_distance, LearnedEstimator.crop_zooms = on, zooms
            estimator = LearnedEstimator.load(args.model, models_dir=args.models)
            held = score_heldout(estimator, test, args.models, images=list(range(len(test.images))),
                                 keep_estimates=True)
            row: dict[str, Any] = {"setting": name, "pose_ar": dict(held.pose_ar),
                                   "ms_per_estimate": 1000.0 * held.seconds_per_estimate,
                                   "true_box_rgb": true_box_rgb_metrics(held, args.models)}
            if args.bundle is not None:
                row["agents"] = learned_agent_scores(args.bundle, args.model, args.out / f"episodes-{name}",
                                                     args.episodes_per_object)
            rows.append(row)
            print(json.dumps(row), flush=True)
    finally:
        LearnedEstimator.mask_area_distance, LearnedEstimator.crop_zooms = default
    path = args.out / REPORT_FILE
    atomic_write_json(path, {"model": str(args.model), "test_pbr": str(args.test_pbr), "images": len(test.images),
                             "rows": rows})
    print("| distance | AR true box RGB (VSD / MSSD / MSPD) | AR detected RGB | AR true / detected + depth | ms per estimate |")
    for r in rows:
        m, ar = r["true_box_rgb"], r["pose_ar"]
        print(f"| {r['setting']} | {ar['true_box_rgb']:.3f} ({m['vsd']:.3f} / {m['mssd']:.3f} / {m['mspd']:.3f}) | "
              f"{ar['detected_rgb']:.3f} | {ar['true_box_depth']:.3f} / {ar['detected_depth']:.3f} | "
              f"{r['ms_per_estimate']:.1f} |")
    for r in rows:
        print(f"{r['setting']} ceilings: " + ", ".join(f"{k} {v:.3f}" for k, v in r["true_box_rgb"]["ceilings"].items()))
        if "agents" in r:
            print(f"{r['setting']} agents: " + ", ".join(f"{k} {v:.3f}" for k, v in r["agents"].items()))
    print(f"written: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

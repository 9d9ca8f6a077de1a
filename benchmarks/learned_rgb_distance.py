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

REPORT_FILE = "rgb_distance.json"
#: setting -> (LearnedEstimator.mask_area_distance, LearnedEstimator.crop_zooms)
SETTINGS: dict[str, tuple[bool, tuple[float, ...]]] = {"pnp": (False, (1.0,)), "mask-area": (True, (1.0,)),
                                                       "mask-area, 3 zooms": (True, (1.0, 0.75, 1.25))}
CEILING_ERRORS = (0.01, 0.02)


def true_box_rgb_metrics(estimator: Any, test: Any, models_dir: Path, seed: int = 0) -> dict[str, Any]:
    """The RGB-only pose given each true box of ``test``: its AR and per-metric recalls, and the
    ceilings (AR with the true distance, exact and off by :data:`CEILING_ERRORS`)."""
    import numpy as np

    from brave6d.core.atomic import read_png
    from brave6d.evaluation.learned import LearnedRefused
    from brave6d.evaluation.learned.data import MIN_VISIB_FRACT
    from brave6d.evaluation.metrics import DepthRenderer, Estimate, GTInstance, evaluate_bop19, load_models

    rng = np.random.default_rng(seed)
    models = load_models(models_dir, sorted(test.objects))
    gts: list[Any] = []
    runs: dict[str, list[Any]] = {"estimate": [], "true distance": []} | {f"distance {e:.0%} off": []
                                                                          for e in CEILING_ERRORS}
    for record in test.images:
        depth_mm = read_png(record.depth_path, expect="depth").astype(np.float64)
        for k in record.instances:
            inst = test.instances[k]
            gts.append(GTInstance(record.scene_id, record.im_id, inst.obj_id, inst.R, inst.t_mm,
                                  max(inst.visib_fract, MIN_VISIB_FRACT), record.K_full, record.size_full, depth_mm))
            try:
                pose = estimator.estimate(record.rgb_crop, record.K_crop, inst.obj_id, inst.box_crop)
            except LearnedRefused:
                continue
            R, t = pose.cam_T_obj[:3, :3], pose.cam_T_obj[:3, 3] * 1000.0
            t_true = t * (float(np.asarray(inst.t_mm).reshape(3)[2]) / t[2])
            ids = (record.scene_id, record.im_id, inst.obj_id, pose.score)
            runs["estimate"].append(Estimate(*ids, R, t))
            runs["true distance"].append(Estimate(*ids, R, t_true))
            for e in CEILING_ERRORS:
                runs[f"distance {e:.0%} off"].append(Estimate(*ids, R, t_true * (1.0 + e * rng.standard_normal())))
    renderer = DepthRenderer()
    scores = {name: evaluate_bop19(gts, estimates, models, renderer=renderer, keep_errors=False)
              for name, estimates in runs.items()}
    own = scores.pop("estimate")
    return {"ar": own.ar, "vsd": own.ar_vsd, "mssd": own.ar_mssd, "mspd": own.ar_mspd,
            "ceilings": {name: s.ar for name, s in scores.items()}}


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
            held = score_heldout(estimator, test, args.models, images=list(range(len(test.images))))
            row: dict[str, Any] = {"setting": name, "pose_ar": dict(held.pose_ar),
                                   "ms_per_estimate": 1000.0 * held.seconds_per_estimate,
                                   "true_box_rgb": true_box_rgb_metrics(estimator, test, args.models)}
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

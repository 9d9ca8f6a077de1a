"""What the learned detector's input widths buy and cost: detection recall and AP at IoU 0.5 per
object, pose AR given the detected boxes (RGB only and with depth) and the median milliseconds
of detecting in one image, for each set of ``LearnedEstimator.detect_scales`` (the detector looks
at the image ``work_width x scale`` wide for each scale, at most the crops' source width, and keeps
the best of overlapping detections).

    python benchmarks/learned_detect_scale.py MODEL_DIR TRAIN_PBR MODELS_DIR [--sets "1;1.375;1,1.375"]
        [--every-image] [--json PATH]

``TRAIN_PBR``: the model's own split (its held-out images are scored), or with ``--every-image``
a split rendered with another seed (``brave6d synth ... --seed 7``: none of its images was trained
on, every one is scored, a larger test set). The scales run one after the other on the same images;
the JSON (default ``MODEL_DIR/../cost/detect_scale.json``, where the report's section 10 reads it)
keeps every row.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="trained model folder (model.pt)")
    parser.add_argument("train_pbr", type=Path)
    parser.add_argument("models", type=Path, help="BOP models folder")
    parser.add_argument("--sets", default="1;1.375;1,1.375", help="scale sets: ';' between sets, ',' inside one")
    parser.add_argument("--every-image", action="store_true", help="score every image of TRAIN_PBR (another seed's split)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    from brave6d.core.atomic import atomic_write_json
    from brave6d.evaluation.learned import LearnedEstimator, load_training_data, read_model, score_heldout

    model = read_model(args.model)
    p = model.preset
    data = load_training_data(args.train_pbr, args.models, int(p["work_width"]),
                              2 if args.every_image else int(p["heldout_every"]),
                              crop_width=int(p.get("crop_source_width", p["work_width"])))
    images = list(range(len(data.images))) if args.every_image else None
    estimator = LearnedEstimator.load(args.model, models_dir=args.models)
    rows = []
    for scales in (tuple(float(x) for x in part.split(",")) for part in args.sets.split(";")):
        estimator.detect_scales = scales
        held = score_heldout(estimator, data, args.models, images=images)
        row = {"scales": list(scales), "detect_widths": estimator.detect_widths, **held.detection_summary(),
               "detect_ms": 1000.0 * held.seconds_per_detection["image_median_s"],
               "refine_ms": 1000.0 * held.seconds_per_detection["refine_median_s"]}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = args.json or args.model.parent / "cost" / "detect_scale.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, {"model": str(args.model), "train_pbr": str(args.train_pbr),
                            "every_image": args.every_image, "rows": rows})
    print("| scales | widths | recall per object | min | AP per object | AR detected RGB / + depth | detect ms |")
    for r in rows:
        print(f"| {' + '.join(f'{x:g}' for x in r['scales'])} | {' + '.join(map(str, r['detect_widths']))} | {' / '.join(f'{v:.2f}' for v in r['recall'].values())} | "
              f"{r['recall_min']:.2f} | {' / '.join(f'{v:.2f}' for v in r['ap'].values())} | "
              f"{r['detected_ar']['detected_rgb']:.3f} / {r['detected_ar']['detected_depth']:.3f} | {r['detect_ms']:.1f} |")
    print(f"written: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

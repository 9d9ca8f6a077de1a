"""What the learned estimator's training precision and steps buy and cost: for each
``precision:detector_steps:pose_steps`` point, the ``fast`` preset with those three fields trained on
TRAIN_PBR (both networks, as ``brave6d learn train`` trains them), its seconds, and on a test split its
detection recall and AP at IoU 0.5 per object and its pose AR given the true and the detected boxes.

    python benchmarks/learned_precision.py TRAIN_PBR MODELS_DIR TEST_PBR --out DIR
        [--points "fp32:1200:1000,bf16:1200:1000,bf16:2400:2000"] [--preset fast]
        [--bundle BUNDLE --episodes-per-object 6]

``bf16`` runs the forward passes in bfloat16 (``LearnPreset.precision``): the same steps in less time
where the CPU has bfloat16 instructions, so more steps in the same time. ``TEST_PBR``: a split of the
same objects rendered with another seed (``brave6d synth ... --seed 7``); every one of its images is
scored. With ``--bundle`` the four learned agents also play that bundle's seeded episodes with each
point's model. The points train one after the other (time them on an idle box). Resumable: each
finished point is kept in ``DIR/precision.json`` and not trained again; the models stay in
``DIR/model-<precision>-<detector_steps>-<pose_steps>``. Put DIR at ``<workdir>/learned/cost`` and
report section 10 tabulates it beside the other cost benchmarks.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

REPORT_FILE = "precision.json"


def parse_points(text: str) -> list[tuple[str, int, int]]:
    """``"fp32:1200:1000,bf16:2400:2000"`` -> [("fp32", 1200, 1000), ("bf16", 2400, 2000)]."""
    from brave6d.core.errors import BraveError

    points = []
    for item in text.split(","):
        parts = item.strip().split(":")
        if len(parts) != 3 or not parts[1].isdigit() or not parts[2].isdigit():
            raise BraveError(f"--points: {item!r} is not precision:detector_steps:pose_steps (e.g. bf16:2400:2000)")
        points.append((parts[0], int(parts[1]), int(parts[2])))
    return points


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("train_pbr", type=Path, help="the split the models train on")
    parser.add_argument("models", type=Path, help="BOP models folder")
    parser.add_argument("test_pbr", type=Path, help="a split never trained on (every image is scored)")
    parser.add_argument("--out", type=Path, required=True, help="folder of the models and precision.json")
    parser.add_argument("--points", default="fp32:1200:1000,bf16:1200:1000,bf16:2400:2000",
                        help="precision:detector_steps:pose_steps,...")
    parser.add_argument("--preset", default="fast", help="the preset every point changes three fields of")
    parser.add_argument("--bundle", type=Path, default=None, help="a bundle to play the learned agents on")
    parser.add_argument("--episodes-per-object", type=int, default=6)
    args = parser.parse_args(argv)

    from brave6d.core.atomic import atomic_write_json
    from brave6d.core.errors import BraveError
    from brave6d.evaluation.demo import learned_agent_scores
    from brave6d.evaluation.learned import LearnedEstimator, get_learn_preset, load_training_data, score_heldout, \
        train_learned, training_seconds

    points = parse_points(args.points)
    base = get_learn_preset(args.preset)
    presets = {p: base.with_overrides(precision=p[0], detector_steps=p[1], pose_steps=p[2]) for p in points}
    report_path = args.out / REPORT_FILE
    done: dict[str, Any] = {}
    if report_path.is_file():
        done = {r["point"]: r for r in json.loads(report_path.read_text()).get("rows", [])}
    test = None
    rows, scored_now = [], 0
    for point in points:
        key = ":".join(map(str, point))
        if key in done:
            rows.append(done[key])
            continue
        if test is None:
            test = load_training_data(args.test_pbr, args.models, base.work_width, 2, crop_width=base.crop_source_width)
        model_dir = args.out / f"model-{point[0]}-{point[1]}-{point[2]}"
        result = train_learned(args.train_pbr, args.models, model_dir, presets[point], "cpu", show_progress=True)
        if not result.trained:
            raise BraveError(f"{model_dir}: a finished model without its row in {report_path}; move the folder "
                             "aside to train and time it again")
        assert result.model is not None
        estimator = LearnedEstimator.load(model_dir, models_dir=args.models)
        held = score_heldout(estimator, test, args.models, images=list(range(len(test.images))))
        ran = result.model.preset  # as it ran (an ``auto`` point resolved)
        row = {"point": key, "precision": ran["precision"], "detector_steps": ran["detector_steps"],
               "pose_steps": ran["pose_steps"], "train_s": training_seconds(result.seconds),
               "seconds": {k: result.seconds[k] for k in ("detector", "pose")},
               "steps_per_s": {"detector": ran["detector_steps"] / result.seconds["detector"],
                               "pose": ran["pose_steps"] / result.seconds["pose"]},
               "losses": result.losses, **held.detection_summary(), "pose_ar": dict(held.pose_ar)}
        if args.bundle is not None:
            row["agents"] = learned_agent_scores(args.bundle, model_dir, model_dir / "episodes",
                                                 args.episodes_per_object)
        rows.append(row)
        done[key] = row
        scored_now += 1
        atomic_write_json(report_path, {"train_pbr": str(args.train_pbr), "test_pbr": str(args.test_pbr),
                                        "preset": base.name, "rows": list(done.values())})
        print(json.dumps(row), flush=True)
    print("| precision | steps det + pose | train s | det / pose steps/s | recall per object | min | "
          "AR true box RGB / + depth | AR detected RGB / + depth |")
    for r in rows:
        ar = r["pose_ar"]
        print(f"| {r['precision']} | {r['detector_steps']} + {r['pose_steps']} | {r['train_s']:.0f} | "
              f"{r['steps_per_s']['detector']:.1f} / {r['steps_per_s']['pose']:.1f} | "
              f"{' / '.join(f'{v:.2f}' for v in r['recall'].values())} | {r['recall_min']:.2f} | "
              f"{ar['true_box_rgb']:.3f} / {ar['true_box_depth']:.3f} | "
              f"{ar['detected_rgb']:.3f} / {ar['detected_depth']:.3f} |")
    for r in rows:
        if "agents" in r:
            print(f"{r['point']}: " + ", ".join(f"{k} {v:.3f}" for k, v in r["agents"].items()))
    print(f"written: {report_path}" if scored_now else f"every point was already in {report_path}; nothing written")
    return 0


if __name__ == "__main__":
    sys.exit(main())

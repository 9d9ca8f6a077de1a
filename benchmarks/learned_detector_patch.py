"""What the learned detector's training patches buy and cost: for each ``patch:steps`` point, the
detector trained on square patches of that many pixels for that many steps (everything else the
``fast`` preset), its seconds of training, and on a test split its detection recall and AP at IoU 0.5
per object and the pose AR given its detected boxes.

    python benchmarks/learned_detector_patch.py TRAIN_PBR MODELS_DIR TEST_PBR --pose-from MODEL_DIR
        [--points "128:4800,96:7600,64:13400"] [--preset fast] [--out DIR]
        [--bundle BUNDLE --episodes-per-object 6]

The detector is what a patch buys: a smaller patch costs less per step, so more steps fit in the same
time. Each point trains the detector exactly as ``fast`` with those two fields would (same seed,
same generator; the coordinate net is skipped, its phase one step long), on one thread beside that
one step as the two phases share a 2-core CPU in ``brave6d learn train``; the coordinate net of
``--pose-from`` (a ``fast`` model of the same split) then refines the boxes and estimates the poses,
so the points differ only in their detector. ``TEST_PBR``: a split of the same objects rendered with
another seed (``brave6d synth ... --seed 7``); every one of its images is scored. With ``--bundle``
the four learned agents also play that bundle's seeded episodes with each point's model (what the
default is chosen by: synthetic recall alone does not say how the agents fare). Resumable: each
finished point is kept in ``OUT/detector_patch.json`` (default OUT: ``MODEL_DIR/../cost``) and not
trained again; the trained detectors stay in ``OUT/detector-<patch>-<steps>``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

POSE_FIELDS = ("work_width", "crop_source_width", "crop_px", "pose_width")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("train_pbr", type=Path, help="the split the detectors train on")
    parser.add_argument("models", type=Path, help="BOP models folder")
    parser.add_argument("test_pbr", type=Path, help="a split never trained on (every image is scored)")
    parser.add_argument("--pose-from", type=Path, required=True, help="a trained model whose coordinate net is used")
    parser.add_argument("--points", default="128:4800,96:7600,64:13400", help="patch:steps,...")
    parser.add_argument("--preset", default="fast", help="the preset the detectors and --pose-from's model share")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--bundle", type=Path, default=None, help="a bundle to play the learned agents on")
    parser.add_argument("--episodes-per-object", type=int, default=6)
    args = parser.parse_args(argv)

    from brave6d.core.atomic import atomic_write_json
    from brave6d.core.errors import BraveError
    from brave6d.evaluation.demo import learned_agent_scores
    from brave6d.evaluation.learned import LearnedEstimator, get_learn_preset, load_training_data, read_model, \
        resolve_precision, score_heldout, train_learned, write_model

    points = [tuple(int(x) for x in p.split(":")) for p in args.points.split(",")]
    pose_model = read_model(args.pose_from)
    base = resolve_precision(get_learn_preset(args.preset), "cpu")  # every point at the steps it names
    mismatch = [f for f in POSE_FIELDS if pose_model.preset.get(f) != getattr(base, f)]
    if mismatch:
        raise BraveError(f"{args.pose_from}: field(s) {', '.join(mismatch)} of its preset differ from "
                         f"{base.name!r}'s; --pose-from needs a model of that preset")
    out_dir = args.out or args.pose_from.parent / "cost"
    report_path = out_dir / "detector_patch.json"
    done: dict[str, Any] = {}
    if report_path.is_file():
        done = {f"{r['patch']}:{r['steps']}": r for r in json.loads(report_path.read_text()).get("rows", [])}
    if all(f"{patch}:{steps}" in done for patch, steps in points):
        train = test = None  # every point is in the JSON: nothing to train or score, so nothing to read
    else:
        train = load_training_data(args.train_pbr, args.models, base.work_width, base.heldout_every,
                                   crop_width=base.crop_source_width)
        test = load_training_data(args.test_pbr, args.models, base.work_width, 2, crop_width=base.crop_source_width)
    rows = []
    scored_now = 0
    for patch, steps in points:
        key = f"{patch}:{steps}"
        if key in done:
            rows.append(done[key])
            continue
        assert train is not None and test is not None
        preset = base.with_overrides(detector_patch=patch, detector_steps=steps, pose_steps=1)
        trained_dir = out_dir / f"detector-{patch}-{steps}"
        result = train_learned(args.train_pbr, args.models, trained_dir, preset, "cpu", show_progress=True, data=train)
        if not result.trained:
            raise BraveError(f"{trained_dir}: a finished detector without its row in {report_path}; move the "
                             f"folder aside to train and time it again")
        assert result.model is not None
        scored_dir = trained_dir / "with-pose"
        scored_dir.mkdir(exist_ok=True)
        pose_preset = {k: v for k, v in pose_model.preset.items() if k.startswith("pose_")}  # what trained that net
        write_model(scored_dir, dataclasses.replace(result.model, pose_state=pose_model.pose_state,
                                                    preset={**result.model.preset, **pose_preset}))
        estimator = LearnedEstimator.load(scored_dir, models_dir=args.models)
        held = score_heldout(estimator, test, args.models, images=list(range(len(test.images))))
        seconds = float(result.seconds["detector"])
        row = {"patch": patch, "steps": steps, "detector_s": seconds, "steps_per_s": steps / seconds,
               "final_loss": result.losses.get("detector"), **held.detection_summary()}
        if args.bundle is not None:
            row["agents"] = learned_agent_scores(args.bundle, scored_dir, trained_dir / "episodes",
                                                 args.episodes_per_object)
        rows.append(row)
        done[key] = row
        scored_now += 1
        atomic_write_json(report_path, {"train_pbr": str(args.train_pbr), "test_pbr": str(args.test_pbr),
                                        "pose_from": str(args.pose_from), "rows": list(done.values())})
        print(json.dumps(row), flush=True)
    print("| patch px | steps | detector s | steps/s | recall per object | min | AP per object | AR detected RGB / + depth |")
    for r in rows:
        print(f"| {r['patch']} | {r['steps']} | {r['detector_s']:.0f} | {r['steps_per_s']:.2f} | "
              f"{' / '.join(f'{v:.2f}' for v in r['recall'].values())} | {r['recall_min']:.2f} | "
              f"{' / '.join(f'{v:.2f}' for v in r['ap'].values())} | "
              f"{r['detected_ar']['detected_rgb']:.3f} / {r['detected_ar']['detected_depth']:.3f} |")
    for r in rows:
        if "agents" in r:
            print(f"{r['patch']} px x {r['steps']}: " + ", ".join(f"{k} {v:.3f}" for k, v in r["agents"].items()))
    print(f"written: {report_path}" if scored_now else f"every point was already in {report_path}; nothing written")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``brave6d learn``: train the learned estimator on a train_pbr split, score one on its held-out images, or
export its networks as ONNX.

    brave6d learn export-onnx MODEL_DIR [--out ONNX_DIR]
    brave6d learn train TRAIN_PBR --models MODELS_DIR --out MODEL_DIR [--preset fast|long|paper] [--device ...] [--resume]
        [--set FIELD=VALUE ...]
    brave6d learn heldout MODEL_DIR TRAIN_PBR --models MODELS_DIR [--detect-scales 1,1.375]
    brave6d learn bop-results MODEL_DIR SPLIT_DIR --models MODELS_DIR --out RESULTS.csv [--depth] [--score]
                              [--targets test_targets_bop19.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from brave6d.core.cli_types import float_in, int_in

if TYPE_CHECKING:
    from brave6d.evaluation.learned.presets import LearnPreset


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    train = sub.add_parser("train", help="train the detector and the coordinate net on a train_pbr split")
    train.add_argument("train_pbr", type=Path, metavar="TRAIN_PBR",
                       help="the split: a train_pbr folder, or the folder 'brave6d synth' wrote")
    train.add_argument("--models", type=Path, required=True, metavar="MODELS_DIR",
                       help="BOP models folder (models_info.json, obj_XXXXXX.ply in mm)")
    train.add_argument("--out", type=Path, required=True, metavar="MODEL_DIR", help="where model.pt and its card go")
    train.add_argument("--preset", default="fast", help="fast (2-core CPU, minutes), long (2-core CPU, half an hour: a better RGB-only pose), paper (GPU), tiny (tests)")
    train.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    train.add_argument("--seed", type=int_in(0, 2**31 - 1), default=None, help="seed (default: the preset's, 0)")
    train.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", dest="overrides",
                       help="change one field of the preset (repeatable), e.g. --set work_width=640 --set "
                            "pose_steps=2000; the card records the preset as it ran")
    train.add_argument("--resume", action="store_true", help="continue the run whose checkpoint.pt is in MODEL_DIR")
    train.add_argument("--no-heldout", action="store_true", help="skip the held-out figures of the card")
    train.add_argument("--heldout-split", type=Path, default=None, metavar="HELDOUT_PBR",
                       help="score the card's held-out figures on every image of this split (rendered apart, "
                            "e.g. brave6d synth with another seed) instead of TRAIN_PBR's held-out slice")
    export = sub.add_parser("export-onnx", help="write the detector and the coordinate net as ONNX (opset 17) for "
                                                "ONNX Runtime (the 'onnx' extra)")
    export.add_argument("model_dir", type=Path, metavar="MODEL_DIR")
    export.add_argument("--out", type=Path, default=None, metavar="ONNX_DIR", help="default: MODEL_DIR/onnx")
    heldout = sub.add_parser("heldout", help="score a trained model on the held-out images of its train_pbr "
                                                "(every image of another split)")
    heldout.add_argument("model_dir", type=Path, metavar="MODEL_DIR")
    heldout.add_argument("train_pbr", type=Path, metavar="TRAIN_PBR")
    heldout.add_argument("--models", type=Path, required=True, metavar="MODELS_DIR")
    heldout.add_argument("--detect-scales", type=_scales, default=None, metavar="S[,S...]",
                         help="the detector's input widths as multiples of the training width (default 1: one pass; "
                              "1,1.375: a second, wider pass for small objects, 3x the detection time; "
                              "docs/BENCHMARKS.md prices them)")
    results = sub.add_parser("bop-results", help="run a trained model over a BOP split (test, or a held-out "
                                                  "train_pbr) and write bop_toolkit's results CSV")
    results.add_argument("model_dir", type=Path, metavar="MODEL_DIR")
    results.add_argument("split", type=Path, metavar="SPLIT_DIR", help="a BOP split folder (000000/, ...: rgb/ PNG "
                                                                        "or JPEG, depth/ at each image's depth_scale)")
    results.add_argument("--models", type=Path, required=True, metavar="MODELS_DIR",
                         help="BOP models folder (the depth refinement fits these surfaces; --score scores with them)")
    results.add_argument("--out", type=Path, required=True, metavar="RESULTS.csv",
                         help="the CSV (scene_id,im_id,obj_id,score,R,t,time; name it METHOD_DATASET-SPLIT.csv "
                              "for bop_toolkit)")
    results.add_argument("--depth", action="store_true", help="refine each pose with the split's depth")
    results.add_argument("--max-images", type=int_in(1, 10_000_000), default=None, metavar="N",
                         help="the first N images only")
    results.add_argument("--score", action="store_true",
                         help="print the CSV's BOP19 AR against the split's ground truth (brave6d's scoring)")
    results.add_argument("--targets", type=Path, default=None, metavar="TARGETS.json",
                         help="the dataset's test_targets_bop19.json: estimate the targets it lists instead of "
                              "those of the split's ground truth (a test split whose scene_gt.json is withheld)")


def _scales(text: str) -> tuple[float, ...]:
    """``1,1.375`` -> (1.0, 1.375): positive finite numbers, or argparse's one-line error."""
    positive = float_in(0, low_open=True)
    try:
        return tuple(positive(x) for x in text.split(","))
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: every scale must be a positive finite number ({exc})") from None


def parse_overrides(preset: LearnPreset, items: list[str]) -> dict[str, int | float | str]:
    """``FIELD=VALUE`` strings as preset field changes, each value of its field's type (int, float
    or text: ``precision``)."""
    from brave6d.core.errors import BraveError

    out: dict[str, int | float | str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        current = getattr(preset, name.strip(), None) if sep else None
        if not sep or name.strip() == "name" or not isinstance(current, (int, float, str)):
            raise BraveError(f"learn train: --set {item!r}: expected FIELD=VALUE with FIELD a field of the "
                             f"preset ({', '.join(k for k, v in preset.to_json().items() if k != 'name')})")
        if isinstance(current, str):
            out[name.strip()] = value.strip()
            continue
        try:
            out[name.strip()] = int(value) if isinstance(current, int) else float(value)
        except ValueError:
            raise BraveError(f"learn train: --set {item!r}: {value!r} is not a valid "
                             f"{'integer' if isinstance(current, int) else 'number'}") from None
    return out


def run(args: argparse.Namespace) -> int:
    from brave6d.evaluation.learned.pipeline import heldout_only, learn_and_card

    if args.action == "export-onnx":
        from brave6d.evaluation.learned.onnx_export import export_onnx

        done = export_onnx(args.model_dir, args.out)
        print(f"export-onnx: {done.detector} and {done.pose} (opset {done.opset}); run them with "
              "brave6d.evaluation.learned.onnx_export.use_onnx")
        return 0
    if args.action == "bop-results":
        return _bop_results(args)
    if args.action == "train":
        from brave6d.evaluation.learned.presets import get_learn_preset

        preset = get_learn_preset(args.preset)
        if args.seed is not None:
            preset = preset.with_overrides(seed=args.seed)
        if args.overrides:
            preset = preset.with_overrides(**parse_overrides(preset, args.overrides))
        card = learn_and_card(args.train_pbr, args.models, args.out, preset, args.device, args.resume,
                              heldout=not args.no_heldout, heldout_pbr=args.heldout_split)
        print(f"learn: model in {args.out / 'model.pt'} ({card['train_seconds']:.0f} s of training on "
              f"{card['device']}); card: {args.out / 'MODEL_CARD.md'}")
    else:
        card = heldout_only(args.model_dir, args.train_pbr, args.models, args.detect_scales)
    h = card.get("heldout")
    if h:
        print(f"held-out: {h['images']} images; pose AR true box {h['pose_ar']['true_box_rgb']:.3f} "
              f"(+ depth {h['pose_ar']['true_box_depth']:.3f}), detected {h['pose_ar']['detected_rgb']:.3f} "
              f"(+ depth {h['pose_ar']['detected_depth']:.3f}); detection recall "
              + ", ".join(f"obj {k}: {v:.2f}" for k, v in h["detection_recall_iou50"].items()))
    return 0


def _bop_results(args: argparse.Namespace) -> int:
    """``learn bop-results``: the CSV, a line of what was estimated, with ``--score`` its AR."""
    from brave6d.core.errors import BraveError
    from brave6d.evaluation.estimate_bop import score_results_csv
    from brave6d.evaluation.learned.inference import LearnedEstimator
    from brave6d.evaluation.learned.split_results import estimate_split
    from brave6d.evaluation.metrics import write_bop_results

    if args.score and args.targets is not None and not any(args.split.glob("[0-9]*/scene_gt.json")):
        raise BraveError(f"{args.split}: --score needs the split's ground truth (scene_gt.json), which this split "
                         "withholds: evaluate the CSV where the ground truth is (bop_toolkit's evaluation server)")
    estimator = LearnedEstimator.load(args.model_dir, models_dir=args.models)
    run = estimate_split(estimator, args.split, with_depth=args.depth, max_images=args.max_images,
                         targets_file=args.targets)
    write_bop_results(args.out, run.estimates)
    refused = ", ".join(f"{n} {cause}" for cause, n in sorted(run.refusals.items())) or "none"
    print(f"bop-results: {len(run.estimates)} estimates of {run.targets} targets in {run.images} images "
          f"({'RGB + depth' if args.depth else 'RGB only'}), median {run.median_ms_per_image:.0f} ms per image; "
          f"not estimated: {refused}; CSV: {args.out}")
    if args.score:
        ids = run.image_ids if args.max_images is not None else None
        print(score_results_csv(args.out, args.split, args.models,
                                scenes=None if ids is None else sorted({s for s, _ in ids}),
                                images=None if ids is None else {i for _, i in ids}))
    return 0

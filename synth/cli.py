"""``brave6d synth DATASET_OR_SCENE OUT --images N``: the synthetic training split (BOP train_pbr)."""

from __future__ import annotations

import argparse
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", type=Path, metavar="DATASET_OR_SCENE", help="dataset.yaml or a scene spec (YAML)")
    parser.add_argument("out", type=Path, metavar="OUT", help="output folder (train_pbr/ is written inside; resumable)")
    parser.add_argument("--images", type=int, required=True, help="number of images")
    parser.add_argument("--seed", type=int, default=0, help="seed of the split (image i depends only on seed and i)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--width", type=int, default=None, help="image width (default: the spec's camera)")
    parser.add_argument("--height", type=int, default=None, help="image height (default: the spec's camera)")


def run(args: argparse.Namespace) -> int:
    from synth.run import SynthOptions, synthesize

    result = synthesize(args.spec, args.out, SynthOptions(images=args.images, seed=args.seed, workers=args.workers,
                                                           width=args.width, height=args.height))
    print(f"synth: {result.images} images in {result.out / 'train_pbr'} ({result.rendered} rendered, "
          f"{result.skipped} already complete); {result.images_per_s:.2f} images/s with {args.workers} worker(s), "
          f"{result.seconds:.1f} s in all")
    return 0

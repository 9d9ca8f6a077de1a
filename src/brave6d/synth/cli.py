"""``brave6d synth DATASET_OR_SCENE OUT --images N``: the synthetic training split (BOP train_pbr)."""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.core.png_check import CHECKS, DEFAULT_CHECK
from brave6d.synth.limits import BOUNDS


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", type=Path, metavar="DATASET_OR_SCENE", help="dataset.yaml or a scene spec (YAML)")
    parser.add_argument("out", type=Path, metavar="OUT", help="output folder (train_pbr/ is written inside; resumable)")
    parser.add_argument("--images", type=BOUNDS["images"].arg_type(), required=True, help="number of images")
    parser.add_argument("--seed", type=BOUNDS["seed"].arg_type(), default=0,
                        help="seed of the split (image i depends only on seed and i)")
    parser.add_argument("--workers", type=BOUNDS["workers"].arg_type(), default=1,
                        help="worker processes (default 1; one per CPU core pays, at most 4 per core and as many as "
                             "memory holds)")
    parser.add_argument("--width", type=BOUNDS["width"].arg_type(), default=None,
                        help="image width (default: the spec's camera)")
    parser.add_argument("--height", type=BOUNDS["height"].arg_type(), default=None,
                        help="image height (default: the spec's camera)")
    parser.add_argument("--resume-check", choices=CHECKS, default=DEFAULT_CHECK,
                        help="how the images a resumed run finds are checked before they count as complete "
                             "(default %(default)s): header (45 bytes: truncated or foreign files, wrong size or "
                             "kind), crc (every byte, ~3x header's time), decode (a full decode, ~20-40x); a "
                             "damaged image is rendered again. Costs on this machine: brave6d report, section 8")
    parser.add_argument("--convention", choices=("brave6d", "blenderproc"), default="brave6d",
                        help="how the files are written: brave6d (PNG rgb/, depth PNGs in mm, depth_scale 1; "
                             "default) or blenderproc (as BlenderProc's BOP-challenge scripts: JPEG rgb/ of "
                             "quality 95, depth PNGs in 0.1 mm, depth_scale 0.1)")
    parser.add_argument("--mesh-dir", type=Path, action="append", default=[], metavar="DIR",
                        help="for a dataset.yaml: also accept meshes that lie under DIR (repeatable); by default "
                             "every file it names must lie in its own folder")
    parser.add_argument("--scene-dir", type=Path, action="append", default=[], metavar="DIR",
                        help="for a dataset.yaml: also accept captured scene directories (scenes: [{dir: ...}]) "
                             "under DIR (repeatable), as 'brave6d dataset run --scene-dir'")


def run(args: argparse.Namespace) -> int:
    from brave6d.synth.run import SynthOptions, synthesize

    result = synthesize(args.spec, args.out, SynthOptions(images=args.images, seed=args.seed, workers=args.workers,
                                                           width=args.width, height=args.height,
                                                           mesh_dirs=tuple(args.mesh_dir),
                                                           scene_dirs=tuple(args.scene_dir),
                                                           resume_check=args.resume_check,
                                                           convention=args.convention))
    print(f"synth: {result.images} images in {result.out / 'train_pbr'} ({result.rendered} rendered, "
          f"{result.skipped} already complete); {result.images_per_s:.2f} images/s with {args.workers} worker(s), "
          f"{result.seconds:.1f} s in all")
    if result.repaired:
        print(f"synth: {result.repaired} image(s) written before were damaged and rendered again; "
              f"first: {result.repair_reason}")
    return 0

"""``brave6d init SPEC SCENE_DIR``: create a self-contained scene directory from a spec."""

from __future__ import annotations

import argparse
import filecmp
import os
from pathlib import Path

from brave6d.core.atomic import move_aside
from brave6d.core.errors import BraveError
from brave6d.core.layout import init_scene_dir


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", type=Path, help="scene spec YAML file")
    parser.add_argument("scene_dir", type=Path, help="scene directory to create")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing scene.yaml (the old one is kept as scene.yaml.old-<time>; "
                             "captured data is kept)")


def run(args: argparse.Namespace) -> int:
    target = Path(args.scene_dir) / "scene.yaml"
    if target.exists() and not args.force:
        raise BraveError(f"{target} exists; pass --force to replace it (captured data is kept)")
    aside = move_aside(target) if target.exists() else None
    try:
        scene = init_scene_dir(args.scene_dir, args.spec)
    except BaseException:
        if aside is not None:
            os.replace(aside, target)  # a spec that fails leaves the scene as it was
        raise
    if aside is not None and filecmp.cmp(aside, target, shallow=False):
        aside.unlink()  # nothing changed: no copy to keep
    elif aside is not None:
        print(f"kept the previous spec as {aside}")
    print(f"created {scene.root} from {args.spec}")
    return 0

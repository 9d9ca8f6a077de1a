"""``brave6d init SPEC SCENE_DIR``: create a self-contained scene directory from a spec."""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.errors import BraveError
from brave6d.layout import init_scene_dir


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", type=Path, help="scene spec YAML file")
    parser.add_argument("scene_dir", type=Path, help="scene directory to create")
    parser.add_argument("--force", action="store_true", help="overwrite an existing scene.yaml")


def run(args: argparse.Namespace) -> int:
    target = Path(args.scene_dir) / "scene.yaml"
    if target.exists() and not args.force:
        raise BraveError(f"{target} exists; pass --force to replace it (captured data is kept)")
    scene = init_scene_dir(args.scene_dir, args.spec)
    print(f"created {scene.root} from {args.spec}")
    return 0

"""``brave6d spec FILE``: validate a scene spec and print what it describes."""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.core.progress import format_table
from brave6d.core.spec import load_scene_spec


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", type=Path, help="scene spec YAML file")


def run(args: argparse.Namespace) -> int:
    spec = load_scene_spec(args.spec)
    cam = spec.camera.pinhole()
    print(f"{args.spec}: scene '{spec.name}' ({spec.category.value}) is valid")
    print(f"  capture: target {list(spec.capture.target)}, distances {spec.capture.distances_m} m, "
          f"{spec.capture.views_per_distance} views each")
    print(f"  camera: {cam.width}x{cam.height}, fx={cam.fx:.1f}, hfov={cam.hfov_deg:.1f} deg; robot: {spec.robot.model}")
    rows = [(o.name, o.category.value, str(o.mesh), o.scale) for o in spec.objects]
    if rows:
        print(format_table(["object", "category", "mesh", "scale"], rows))
    effects = spec.simulation.effects.enabled() if spec.simulation else []
    print(f"  simulation effects: {', '.join(effects) if effects else 'none'}")
    return 0

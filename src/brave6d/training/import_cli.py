"""``brave6d import SOURCE SCENE_DIR``: a capture made elsewhere -> a scene directory.

SOURCE is a COLMAP model (its folder, or a project folder with ``sparse/0`` and ``images``) or a
nerfstudio / instant-ngp ``transforms.json`` (the file or its folder). Registered in
``brave6d/cli.py`` as ``Command("import", "brave6d.training.import_cli", ...)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.core.cli_types import float_in, int_in


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", type=Path, help="a COLMAP model folder (or a folder with sparse/0 and images/), "
                        "or a transforms.json (or its folder)")
    parser.add_argument("scene_dir", type=Path, help="the scene directory to create")
    parser.add_argument("--format", choices=["auto", "colmap", "transforms"], default="auto",
                        help="the source's format (default: %(default)s: transforms.json when there is one)")
    parser.add_argument("--images", type=Path, default=None,
                        help="COLMAP: the images folder (default: SOURCE/images, or images/ beside sparse/)")
    scale = parser.add_mutually_exclusive_group()
    scale.add_argument("--scale", type=float_in(0.0, None, low_open=True), default=None, metavar="FACTOR",
                       help="metres per source unit (1 when the source's poses are in metres). Neither this nor "
                            "--scale-from-distance: 1, the source's units kept as metres (training does not depend "
                            "on the scale; the server's camera radius, the agents' steps and annotated objects do)")
    scale.add_argument("--scale-from-distance", nargs=3, default=None, metavar=("FRAME_A", "FRAME_B", "METRES"),
                       help="the real distance in metres between the camera centres of two frames (named as in "
                            "the source: COLMAP image name or transforms.json file_path; or by their file name)")
    parser.add_argument("--up", default=None, metavar="x,y,z|auto",
                        help="the world's up direction in the source's coordinates, or 'auto' (the default): "
                             "perpendicular to the cameras' image rows (photos taken upright; cameras rolled "
                             "different ways are refused)")
    parser.add_argument("--downscale", type=int_in(1, 64), default=1,
                        help="resample the images by this whole factor at import (default: %(default)s)")
    parser.add_argument("--name", default=None, help="the scene's name (default: the scene folder's name)")
    parser.add_argument("--min-visible-share", type=float_in(0.0, 1.0), default=None, metavar="SHARE",
                        help="pose check: the least share of the sparse points each camera must see "
                             "(default: 0.02)")
    parser.add_argument("--skip-pose-check", action="store_true",
                        help="import even when cameras do not see the scene (not recommended)")
    parser.add_argument("--force", action="store_true",
                        help="if SCENE_DIR exists and is not empty, move it aside (SCENE_DIR.old-<time>) instead "
                             "of refusing")


def run(args: argparse.Namespace) -> int:
    from brave6d.core.errors import DataError
    from brave6d.training.importing.importer import ImportOptions, import_capture
    from brave6d.training.importing.world import ScaleChoice, parse_up
    from brave6d.training.pose_check import MIN_VISIBLE_SHARE

    scale = None
    if args.scale is not None:
        scale = ScaleChoice(factor=args.scale)
    elif args.scale_from_distance is not None:
        a, b, metres = args.scale_from_distance
        try:
            scale = ScaleChoice(distance=(a, b, float(metres)))
        except ValueError:
            raise DataError(f"--scale-from-distance: METRES must be a number, got {metres!r}") from None
    options = ImportOptions(scale=scale, up=None if args.up is None else parse_up(args.up), format=args.format,
                            images=args.images, downscale=args.downscale, name=args.name,
                            min_visible_share=MIN_VISIBLE_SHARE if args.min_visible_share is None else args.min_visible_share,
                            pose_check=not args.skip_pose_check, force=args.force)
    result = import_capture(args.source, args.scene_dir, options)
    print(summary(result))
    return 0


def summary(result) -> str:  # type: ignore[no-untyped-def]
    """What the import did, for the terminal: frames, camera, world (scale, up), the pose check."""
    rec = result.record
    cam = result.camera
    lines = [f"imported {result.frames} frames from a {rec['source']['format']} capture into {result.scene.root}",
             f"camera: {cam.width}x{cam.height}, fx {cam.fx:.2f} fy {cam.fy:.2f} cx {cam.cx:.2f} cy {cam.cy:.2f} "
             f"(OpenCV pixel centres){', distortion ' + str([round(d, 5) for d in cam.dist]) if cam.dist else ''}; "
             f"images {rec['camera']['images']}",
             f"scale: {result.world.scale:.6g} m per source unit, from {result.world.scale_from}",
             f"up: {result.world.up_from}; the source's up {[round(float(v), 4) for v in result.world.up_source]} is now +z",
             f"origin: {result.world.centre_from}"]
    if "images_downscaled" in rec["source"]:
        lines.append(rec["source"]["images_downscaled"])
    rotations = rec.get("rotations", {})
    if rotations.get("largest_correction"):
        lines.append(f"rotations: the largest projection onto a rotation moved an entry by "
                     f"{rotations['largest_correction']:.2g} ({rotations.get('largest_correction_frame')}; "
                     f"tolerance {rotations['tolerance']:g})")
    if result.missing:
        shown = ", ".join(result.missing[:10]) + (f" and {len(result.missing) - 10} more" if len(result.missing) > 10 else "")
        lines.append(f"{len(result.missing)} frames listed without an image file, left out: {shown}")
    if rec["exif_orientation_applied"]:
        lines.append(f"EXIF orientation applied to {len(rec['exif_orientation_applied'])} photos")
    lines.append(result.pose_check.summary() if result.pose_check is not None else f"pose check: {rec['pose_check']}")
    if result.moved_aside is not None:
        lines.append(f"the previous {result.scene.root} was moved aside to {result.moved_aside}")
    lines.append(f"record: {result.scene.import_record_path}\nnext: brave6d train {result.scene.root} --preset fast")
    return "\n".join(lines)

"""``brave6d export SCENE_DIR``: write the scene's render-server bundle (``<scene>/bundle``).

``--out`` is replaced only when it is absent, empty or a bundle; anything else is refused unless
``--force``, which moves it aside to ``<out>.old-<time>`` (nothing is deleted). The scene
directory, its stage folders (capture, calibration, sparse, splat, annotation) and their
ancestors are never a valid ``--out``.

The bundle carries the scene's reference geometry (``reference.ply``: a TSDF mesh of the captured
depth at the calibrated poses, what scores are measured against); ``--reference-voxel`` trades
its accuracy for build time (docs/BENCHMARKS.md), ``--no-reference`` leaves it out.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene_dir", type=Path, help="scene directory (trained splat + imported annotation)")
    parser.add_argument("--out", type=Path, default=None, help="bundle folder (default: SCENE_DIR/bundle)")
    parser.add_argument("--camera-radius", type=float, default=None,
                        help="radius (m) of the camera's collision sphere (default 0.02)")
    parser.add_argument("--width", type=int, default=None, help="default render width (default: the camera's)")
    parser.add_argument("--height", type=int, default=None, help="default render height (default: the camera's)")
    parser.add_argument("--no-holdout-images", action="store_true",
                        help="leave the held-out images out (needed when the capture cannot be undistorted)")
    parser.add_argument("--no-reference", action="store_true",
                        help="leave the reference geometry out (scores then use the splat's depth)")
    parser.add_argument("--reference-voxel", type=float, default=None, metavar="M",
                        help="TSDF voxel size (m) of the reference geometry (default 0.002; truncation 4 voxels)")
    parser.add_argument("--force", action="store_true",
                        help="if --out holds something that is not a bundle, move it aside to OUT.old-<time> "
                             "(never deleted) instead of refusing")


def run(args: argparse.Namespace) -> int:
    from brave6d.serve.bundle import export_bundle
    from brave6d.serve.geometry import DEFAULT_CAMERA_RADIUS
    from brave6d.serve.reference import ReferenceSettings

    result = export_bundle(args.scene_dir, args.out, include_holdout_images=not args.no_holdout_images,
                           camera_radius=DEFAULT_CAMERA_RADIUS if args.camera_radius is None else args.camera_radius,
                           width=args.width, height=args.height, force=args.force,
                           reference=not args.no_reference,
                           reference_settings=None if args.reference_voxel is None else
                           ReferenceSettings(voxel_m=args.reference_voxel, trunc_m=4.0 * args.reference_voxel))
    if result.moved_aside is not None:
        print(f"moved what was at {result.root} aside to {result.moved_aside}")
    print(f"bundle: {result.root}  ({result.gaussians} Gaussians, {result.objects} object instances, "
          f"{result.holdout_views} holdout views, models from {result.models_from}, {result.bytes / 1e6:.1f} MB)")
    if result.reference_triangles is not None:
        print(f"reference geometry: {result.reference_triangles} triangles (what scores are measured against)")
    else:
        print("no reference geometry: scores of this bundle use the splat's depth")
    print(f"serve it with: brave6d serve {result.root}")
    return 0

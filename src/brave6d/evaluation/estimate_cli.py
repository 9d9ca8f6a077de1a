"""``brave6d estimate``: the baseline's static estimator on any RGB-D frame, or over a BOP split.

``brave6d estimate frame --depth D.png --depth-scale 1 --K fx,fy,cx,cy --model obj.ply --box x,y,w,h``
prints the pose as JSON (``cam_T_obj`` in m, BOP's ``R`` and ``t_mm``, score, where "up" came from);
``--pixel u,v`` instead of ``--box``; ``--scene-camera scene_camera.json --im-id N`` instead of ``--K``
and ``--depth-scale`` (BOP's ``cam_K`` converted to the OpenCV convention by ``annotation``'s reader).
A refusal is one line naming its cause and exit status 2, as every user error of the CLI.

``brave6d estimate bop --split DATA/test --models DATA/models --out results.csv [--score]`` estimates
every visible ground-truth box of the split and writes the BOP results CSV (``--score``: BOP19 AR of
that CSV, read back by ``read_bop_results``, against the split's ground truth).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from brave6d.core.cli_types import float_in, int_in
from brave6d.core.errors import DataError


def _numbers(count: tuple[int, ...], what: str) -> Any:
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.replace(" ", "").split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what}: comma-separated numbers expected, got {text!r}") from None
        if len(values) not in count or not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f"{what}: {' or '.join(map(str, count))} finite numbers expected, "
                                             f"got {text!r}")
        return values

    return parse


def _add_options(p: argparse.ArgumentParser) -> None:
    from brave6d.evaluation.agents.frame import FrameOptions

    d = FrameOptions()
    r = d.registration
    p.add_argument("--model-points", type=int_in(50, 200_000), default=2000,
                   help="surface points sampled on the model (default 2000)")
    p.add_argument("--ransac-iterations", type=int_in(0, 10_000_000), default=r.ransac_iterations,
                   help=f"FPFH + RANSAC iterations per seed (default {r.ransac_iterations})")
    p.add_argument("--ransac-seeds", type=int_in(0, 64), default=len(r.ransac_seeds),
                   help=f"RANSAC runs with different seeds (default {len(r.ransac_seeds)}; 0: resting hypotheses only)")
    p.add_argument("--icp-iterations", type=int_in(1, 1000), default=r.icp_iterations,
                   help=f"ICP iterations per round, two rounds per hypothesis (default {r.icp_iterations})")
    p.add_argument("--yaw-steps", type=int_in(1, 72), default=r.yaw_steps,
                   help=f"yaws of the 'resting on the table' hypotheses (default {r.yaw_steps})")
    p.add_argument("--voxel-fraction", type=float_in(0.005, 0.5), default=r.voxel_fraction,
                   help=f"registration voxel as a fraction of the model diameter (default {r.voxel_fraction})")
    p.add_argument("--plane-voxel", type=float_in(0.0, 0.1), default=d.perception.plane_voxel_m,
                   help="thin the cloud to this voxel (m) before the table plane fits (default: their inlier "
                        "distance, 3 and 5 mm; 0.01 is about twice as fast, see benchmarks/estimate_frame.py)")
    p.add_argument("--plane-iterations", type=int_in(10, 100_000), default=d.perception.plane_iterations,
                   help=f"RANSAC iterations of each table plane fit (default {d.perception.plane_iterations}; "
                        "the fit that finds 'up' runs twice as many)")
    p.add_argument("--min-score", type=float_in(-10.0, 1.0), default=d.min_score,
                   help=f"refuse a best fit scoring less (default {d.min_score})")


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    frame = sub.add_parser("frame", help="estimate one object's pose in one RGB-D frame; print it as JSON",
                           description="Estimate cam_T_obj of one object in one frame with the baseline's static "
                           "estimator (depth only: table plane, cluster at the hint, FPFH + RANSAC and resting "
                           "hypotheses, ICP). 'up' is the table plane's normal unless --up is given. A refusal names "
                           "its cause (no depth at the hint, no plane, nothing of the model's size, no fit...).")
    frame.add_argument("--depth", type=Path, required=True, help="16-bit depth PNG (0 = no depth)")
    frame.add_argument("--depth-scale", type=float_in(0.0, None, low_open=True), default=None,
                       help="mm per depth unit (BOP's depth_scale: 1 = mm, 0.1 = tenths of a mm; default 1, or the "
                            "image's depth_scale of --scene-camera)")
    frame.add_argument("--rgb", type=Path, default=None,
                       help="RGB image of the same frame: with a model that has vertex colours it tells a "
                            "near-symmetric object from its flip (default: depth alone)")
    frame.add_argument("--K", type=_numbers((4, 9), "--K"), default=None, dest="K",
                       help="fx,fy,cx,cy or 9 values row-major, OpenCV convention (pixel centres at integers)")
    frame.add_argument("--scene-camera", type=Path, default=None,
                       help="a BOP scene_camera.json to take cam_K and depth_scale from (with --im-id)")
    frame.add_argument("--im-id", type=int_in(0, None), default=None, help="the image's id in --scene-camera")
    frame.add_argument("--model", type=Path, required=True, help="the object's mesh (PLY)")
    frame.add_argument("--units", choices=("mm", "m"), default="mm", help="the model's units (default mm, BOP's)")
    frame.add_argument("--diameter", type=float_in(0.0, None, low_open=True), default=None,
                       help="the model's diameter in --units (default: its largest vertex distance)")
    hint = frame.add_mutually_exclusive_group(required=True)
    hint.add_argument("--pixel", type=_numbers((2,), "--pixel"), default=None, help="u,v: a pixel on the object")
    hint.add_argument("--box", type=_numbers((4,), "--box"), default=None, help="x,y,w,h: a box around the object")
    frame.add_argument("--up", type=_numbers((3,), "--up"), default=None,
                       help="world up in the camera frame (world_T_cam[2,:3]); default: the table plane's normal")
    frame.add_argument("--out", type=Path, default=None, help="also write the JSON to this file")
    _add_options(frame)

    bop = sub.add_parser("bop", help="estimate every visible ground-truth box of a BOP split; write the results CSV",
                         description="Run the frame estimator on every instance of scene_gt.json with visib_fract "
                         ">= 0.1 of every image of a BOP split, hinted by its scene_gt_info.json box (an oracle "
                         "detector), and write the BOP results CSV (scene_id,im_id,obj_id,score,R,t,time) that "
                         "bop_toolkit reads. Refusals are counted by cause and leave no line.")
    bop.add_argument("--split", type=Path, required=True, help="BOP split folder (e.g. DATA/test) of scene folders")
    bop.add_argument("--models", type=Path, required=True, help="models folder (models_info.json, obj_*.ply in mm)")
    bop.add_argument("--out", type=Path, required=True, help="results CSV to write (METHOD_DATASET-SPLIT.csv for BOP)")
    bop.add_argument("--scenes", type=int_in(0, None), nargs="+", default=None, help="only these scene ids")
    bop.add_argument("--images", type=int_in(0, None), nargs="+", default=None, help="only these image ids")
    bop.add_argument("--objects", type=int_in(1, None), nargs="+", default=None, help="only these object ids")
    bop.add_argument("--hint-box", choices=("bbox_visib", "bbox_obj"), default="bbox_visib",
                     help="which scene_gt_info.json box hints each instance (default bbox_visib)")
    bop.add_argument("--score", action="store_true",
                     help="print BOP19 AR (VSD, MSSD, MSPD) of the written CSV against the split's ground truth")
    _add_options(bop)


def frame_options(args: argparse.Namespace) -> Any:
    """The :class:`~brave6d.evaluation.agents.FrameOptions` of the command line's settings."""
    from dataclasses import replace

    from brave6d.evaluation.agents.frame import FrameOptions

    d = FrameOptions()
    reg = replace(d.registration, ransac_iterations=args.ransac_iterations,
                  ransac_seeds=tuple(range(args.ransac_seeds)), icp_iterations=args.icp_iterations,
                  yaw_steps=args.yaw_steps, voxel_fraction=args.voxel_fraction)
    per = replace(d.perception, plane_voxel_m=args.plane_voxel, plane_iterations=args.plane_iterations)
    return replace(d, registration=reg, perception=per, up_plane_iterations=2 * args.plane_iterations,
                   min_score=args.min_score)


def _camera(args: argparse.Namespace) -> tuple[Any, float]:
    import numpy as np

    if args.scene_camera is not None:
        from brave6d.annotation import read_scene_camera

        if args.K is not None:
            raise DataError("give either --K or --scene-camera, not both")
        if args.im_id is None:
            raise DataError("--scene-camera needs --im-id")
        cams = read_scene_camera(args.scene_camera)
        if args.im_id not in cams:
            raise DataError(f"{args.scene_camera}: no entry for image {args.im_id}")
        cam = cams[args.im_id]
        return cam.cam_K, args.depth_scale if args.depth_scale is not None else cam.depth_scale
    if args.K is None:
        raise DataError("give the camera: --K fx,fy,cx,cy (or 9 values), or --scene-camera FILE --im-id N")
    k = args.K
    K = np.array([[k[0], 0.0, k[2]], [0.0, k[1], k[3]], [0.0, 0.0, 1.0]]) if len(k) == 4 else np.reshape(k, (3, 3))
    return K, args.depth_scale if args.depth_scale is not None else 1.0


def _run_frame(args: argparse.Namespace) -> int:
    from brave6d.core.atomic import atomic_write_text, read_png
    from brave6d.evaluation.agents.frame import BoxHint, PixelHint, estimate_pose, prepare_model, read_depth_png

    K, depth_scale = _camera(args)
    depth = read_depth_png(args.depth, depth_scale)
    rgb = read_png(args.rgb, "rgb") if args.rgb is not None else None
    options = frame_options(args)
    model = prepare_model(args.model, args.units, diameter=args.diameter, points=args.model_points,
                          seed=options.perception.seed)
    hint = PixelHint(*args.pixel) if args.pixel is not None else BoxHint(*args.box)
    pose = estimate_pose(depth, K, model, hint, up=args.up, rgb=rgb, options=options)
    text = "{\n" + ",\n".join(f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in pose.to_json().items()) + "\n}\n"
    if args.out is not None:
        atomic_write_text(args.out, text)
    sys.stdout.write(text)
    return 0


def _run_bop(args: argparse.Namespace) -> int:
    from brave6d.evaluation.estimate_bop import estimate_bop_split, score_results_csv
    from brave6d.evaluation.metrics import write_bop_results

    run = estimate_bop_split(args.split, args.models, scene_ids=args.scenes, im_ids=args.images, obj_ids=args.objects,
                             hint_box=args.hint_box, options=frame_options(args), model_points=args.model_points,
                             progress=lambda line: print(line, file=sys.stderr))
    written = write_bop_results(args.out, run.estimates)
    refused = ", ".join(f"{c} {n}" for c, n in sorted(run.refused_by_cause.items())) or "none"
    print(f"{run.images} images, {run.instances} instances: {len(run.estimates)} estimates, refused: {refused}"
          + (f", {run.skipped_no_model} without a model" if run.skipped_no_model else "") + f"; wrote {written}")
    if args.score:
        print(score_results_csv(written, args.split, args.models, args.scenes, args.images, args.objects))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.action == "frame":
        return _run_frame(args)
    if args.action == "bop":
        return _run_bop(args)
    raise AssertionError(f"unknown action {args.action!r}")

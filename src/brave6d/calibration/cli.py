"""``brave6d calibrate plan|capture|intrinsics|handeye|all SCENE_DIR``: board capture and calibration.

Registered in ``brave6d/cli.py`` as ``Command("calibrate", "brave6d.calibration.cli", ...)``.
``all`` = plan + capture + intrinsics + hand-eye + report; each action can also run alone
(``handeye`` then uses the intrinsics already in ``calibration/intrinsics.json``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.core.errors import BraveError
from brave6d.core.run_context import RunContext, Rig

ACTIONS = ("plan", "capture", "intrinsics", "handeye", "all")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=ACTIONS, metavar="ACTION",
                        help="plan: plan the board views the robot can reach (calibration/board_capture/plan.json); "
                             "capture: capture them (plans first when there is no plan); intrinsics, handeye: "
                             "calibrate from the board frames; all: every step and the report")
    parser.add_argument("scene_dir", type=Path, help="scene directory (made by 'brave6d init')")
    parser.add_argument("--robot", default="sim", help="'sim' or 'ur:HOST' (a UR arm reachable over RTDE)")
    parser.add_argument("--camera", default="sim", help="'sim' or 'oak' (a Luxonis OAK over USB)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted board capture (or reuse a "
                        "complete one) and recalibrate")
    parser.add_argument("--force", action="store_true", help="move an existing board capture aside, plan and "
                        "capture again")
    parser.add_argument("--factory-intrinsics", action="store_true",
                        help="keep the camera's own intrinsics (capture camera.json); only measure their error")
    parser.add_argument("--distortion", default="auto", metavar="MODEL",
                        help="lens distortion model: auto (k1 k2 k3, with p1 p2 only when the data show them; "
                             "default), radial, 0, 4, 5, 8, 12 or 14 (OpenCV coefficient counts)")
    parser.add_argument("--views", type=int, default=None,
                        help="board views to plan (default: 30)")


def _check_args(args: argparse.Namespace) -> None:
    from brave6d.calibration.intrinsics import DISTORTION_MODELS

    if args.resume and args.force:
        raise BraveError("--resume and --force exclude each other: resume keeps the board capture, "
                         "force moves it aside")
    if args.distortion != "auto" and args.distortion not in DISTORTION_MODELS:
        raise BraveError(f"--distortion {args.distortion}: unknown model; choose from auto, "
                         f"{', '.join(DISTORTION_MODELS)}")
    if args.views is not None and args.views < 3:
        raise BraveError(f"--views {args.views}: hand-eye calibration needs at least 3 views (30 recommended)")


def run(args: argparse.Namespace) -> int:
    from brave6d.calibration.board import export_board
    from brave6d.calibration.board_capture import DEFAULT_VIEWS, capture_board, plan_only
    from brave6d.calibration.pipeline import calibrate_scene, summary_lines

    ctx = RunContext.for_scene(args.scene_dir, rig=Rig(args.robot, args.camera))  # as the pipeline's calibrate stage
    _check_args(args)
    scene, spec, rig = ctx.scene, ctx.spec, ctx.rig
    layout = scene.board_capture
    views = args.views or DEFAULT_VIEWS
    if args.action in ("plan", "all"):
        printable = export_board(spec.board, scene.board_pdf_path)
        print(f"printable board at true scale (print at 100 %): {printable}")
    if args.action == "plan":
        plan = plan_only(layout, spec, rig.robot, rig.camera, views)
        print(f"planned {len(plan.views)} board views at {plan.distance_m:.2f} m "
              f"({len(plan.dropped)} candidates left out); wrote {layout.plan_path}")
        return 0
    if args.action in ("capture", "all"):
        cap = capture_board(layout, spec, rig.robot, rig.camera, views, resume=args.resume, force=args.force)
        print(f"board capture: {cap.written} frames captured now, {cap.total} in all "
              f"({cap.robot_seconds:.1f} s robot time) in {layout.root}")
    if args.action in ("intrinsics", "handeye", "all"):
        result = calibrate_scene(scene, spec, intrinsics=args.action != "handeye",
                                 handeye=args.action != "intrinsics", factory_intrinsics=args.factory_intrinsics,
                                 distortion=args.distortion)
        print("\n".join(summary_lines(result)))
    return 0

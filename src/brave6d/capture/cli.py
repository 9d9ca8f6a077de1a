"""``brave6d capture plan|run SCENE_DIR``: plan the views, then capture them with a robot/camera pair."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from brave6d.core.calibration_io import read_handeye
from brave6d.core.layout import SceneDir
from brave6d.core.run_context import RunContext, Rig

log = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    plan = sub.add_parser("plan", help="plan the capture views (writes capture/plan.json and plan.png)")
    plan.add_argument("scene_dir", type=Path, help="scene directory (made by 'brave6d init')")
    run = sub.add_parser("run", help="capture the planned views (plans first when there is no plan)")
    run.add_argument("scene_dir", type=Path, help="scene directory (made by 'brave6d init')")
    run.add_argument("--robot", default="sim", help="'sim' or 'ur:HOST' (a UR arm reachable over RTDE)")
    run.add_argument("--camera", default="sim", help="'sim' or 'oak' (a Luxonis OAK over USB)")
    run.add_argument("--resume", action="store_true", help="continue an interrupted capture")
    run.add_argument("--force", action="store_true", help="move an existing capture aside and start again")
    run.add_argument("--supersample", type=int, default=None,
                     help="simulated camera: rays per pixel side (default: 1, with 3x3 on silhouette edges)")


def mounting_for_planning(scene: SceneDir) -> tuple[np.ndarray | None, str]:
    """The calibrated tcp_T_cam when calibration ran, else None (the planner uses the spec's guess)."""
    if scene.handeye_path.exists():
        return read_handeye(scene), f"calibrated ({scene.handeye_path})"
    return None, "robot.tcp_T_camera_guess from the spec"


def make_plan(scene: SceneDir, save: bool = True):  # noqa: ANN201 - returns brave6d.capture.planning.Plan
    """Plan the scene's capture; with ``save``, write plan.json and the plot. Returns the plan."""
    from brave6d.capture.planning import plan_views

    spec = scene.load_spec()
    tcp_T_cam, source = mounting_for_planning(scene)
    plan = plan_views(spec, tcp_T_cam)
    plan.meta["tcp_T_cam_source"] = source
    if save:
        save_plan_files(scene, plan)
    log.info("planned %d views (%d dropped) with the %s mounting", len(plan.views), len(plan.dropped), source)
    return plan


def save_plan_files(scene: SceneDir, plan) -> None:  # noqa: ANN001 - brave6d.capture.planning.Plan
    """Write ``capture/plan.json`` and ``capture/plan.png``."""
    from brave6d.capture.planning import BoxSet, plot_plan, save_plan

    spec = scene.load_spec()
    save_plan(plan, scene.capture.plan_path)
    plot_plan(plan, scene.capture.plan_plot_path, BoxSet.from_specs(spec.collision_boxes), spec.workspace)


def captured_frame_count(scene: SceneDir) -> int:
    """How many frames ``capture/frames.jsonl`` holds (0 when there is none)."""
    return len(scene.capture.frames()) if scene.capture.frames_path.exists() else 0


def plan_for_capture(scene: SceneDir):  # noqa: ANN201 - returns brave6d.capture.planning.Plan
    """The plan to capture (or resume) with: the stored one while frames exist, else a new one (saved)."""
    from brave6d.capture.planning import load_plan

    if captured_frame_count(scene) and scene.capture.plan_path.exists():
        return load_plan(scene.capture.plan_path)
    return make_plan(scene)


def refuse_replanning_under_frames(scene: SceneDir) -> None:
    """A capture's plan stays while frames exist: frames are named by their index in the plan, so a
    new plan would mix two plans in one capture and could write over captured images."""
    from brave6d.capture.runner import CaptureExistsError

    if count := captured_frame_count(scene):
        raise CaptureExistsError(
            f"{scene.capture.frames_path}: a capture with {count} frames exists, so its plan stays as it is; "
            "capture again with 'brave6d capture run --force' (moves the old capture aside and plans anew)")


def run(args: argparse.Namespace) -> int:
    if args.action == "plan":
        scene = RunContext.for_scene(args.scene_dir).scene
        refuse_replanning_under_frames(scene)
        plan = make_plan(scene)
        print(f"planned {len(plan.views)} views, dropped {len(plan.dropped)}; "
              f"estimated {plan.estimated_time_s:.0f} s (naive ring order: {plan.naive_travel_time_s:.0f} s travel)")
        print(f"wrote {scene.capture.plan_path} and {scene.capture.plan_plot_path}")
        return 0
    from brave6d.capture.backends import open_rig
    from brave6d.capture.planning import load_plan
    from brave6d.capture.runner import CaptureOptions, run_capture

    ctx = RunContext.for_scene(args.scene_dir, rig=Rig(args.robot, args.camera))  # as the pipeline's capture stage
    scene, spec = ctx.scene, ctx.spec
    # --force plans anew; while old frames are there their plan stays with them (it goes aside with them)
    replan = args.force or not scene.capture.plan_path.exists()
    plan = make_plan(scene, save=not captured_frame_count(scene)) if replan else load_plan(scene.capture.plan_path)
    options = CaptureOptions(settle_time_s=spec.capture.settle_time_s, save_depth=spec.capture.depth,
                             resume=args.resume, force=args.force)
    try:
        with open_rig(spec, ctx.rig.robot, ctx.rig.camera, supersample=args.supersample) as rig:
            summary = run_capture(scene.capture, plan.views, rig.robot, rig.camera, options)
    finally:
        if replan and not scene.capture.plan_path.exists():
            save_plan_files(scene, plan)
    print(f"captured {summary.written} frames ({summary.resumed_from} kept from before, {summary.total} in all) "
          f"in {summary.wall_seconds:.1f} s wall, {summary.robot_seconds:.1f} s robot time")
    return 0

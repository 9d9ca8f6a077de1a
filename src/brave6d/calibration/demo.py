"""The pipeline's calibration stage: ``brave6d.calibration.demo:stage_calibrate`` (see ``brave6d.pipeline``).

Runs ``brave6d calibrate all`` on the scene with the run's rig (``RunContext.rig``; in the demo the
simulated UR5e + camera, with the spec's sensor noise, lens distortion and robot pose error on),
before the scene capture, whose plan then uses the calibrated mounting. ``brave6d dataset run``
never runs it for a captured scene: a real rig is calibrated at the robot (``brave6d calibrate all
SCENE_DIR --robot ur:HOST --camera oak``), where a person places the board and watches the arm. Work already done is reused: a complete board capture of
the wanted size is not captured again, and results newer than its frames are not recomputed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from brave6d.core.progress import StageResult
from brave6d.calibration.board_capture import DEFAULT_VIEWS, BoardPlan, capture_board
from brave6d.calibration.pipeline import CalibrationRun, calibrate_scene, load_results, refined_error, results_up_to_date

if TYPE_CHECKING:
    from brave6d.core.run_context import RunContext

#: Board views of the miniature run (``--quick``): enough for a well-conditioned solve.
QUICK_VIEWS = 12


def _existing_plan(ctx: RunContext) -> BoardPlan | None:
    path = ctx.scene.board_capture.plan_path
    return BoardPlan.load(path) if path.is_file() else None


def stage_calibrate(ctx: RunContext) -> StageResult:
    """Capture the board (resuming), calibrate intrinsics and hand-eye; figures for the summary table."""
    scene = ctx.scene
    spec = scene.load_spec()
    wanted = QUICK_VIEWS if ctx.quick else DEFAULT_VIEWS
    plan = _existing_plan(ctx)
    other_size = plan is not None and plan.requested != wanted
    complete = plan is not None and len(scene.board_capture.frames()) >= len(plan.views)
    if not other_size and complete and results_up_to_date(scene):
        return _result(load_results(scene, spec), "reused")
    capture_board(scene.board_capture, spec, ctx.rig.robot, ctx.rig.camera, wanted, resume=not other_size,
                  force=other_size)
    return _result(calibrate_scene(scene, spec), "ok")


def _result(run: CalibrationRun, status: str) -> StageResult:
    figures: dict[str, Any] = {"board views": run.frames}
    if run.intrinsics is not None:
        figures["intrinsics RMS px"] = round(run.intrinsics.rms_px, 3)
    if run.handeye is not None:
        figures["hand-eye views"] = run.handeye.residuals.n_views
        figures["hand-eye RMS px"] = round(run.handeye.residuals.reprojection_rms_px, 3)
    if run.truth_errors:
        mm, deg = refined_error(run)
        figures["error vs truth mm"] = round(mm, 3)
        figures["error vs truth deg"] = round(deg, 4)
    return StageResult("calibrate", status=status, figures=figures)

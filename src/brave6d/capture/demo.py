"""The pipeline's capture stage: plan the scene's views and capture them with the run's rig.

The rig is ``RunContext.rig``: the simulated UR5e + camera in ``brave6d demo`` and for a dataset's
simulated scenes. ``brave6d dataset run`` never runs this stage for a captured scene (its jobs run
unattended, far from any robot): a real rig's capture is ``brave6d capture run --robot ur:HOST
--camera oak`` at the robot, with a person watching the arm.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from brave6d.core.progress import StageResult
from brave6d.capture.backends import open_rig
from brave6d.capture.cli import plan_for_capture
from brave6d.capture.runner import CaptureOptions, run_capture

if TYPE_CHECKING:
    from brave6d.core.run_context import RunContext


def stage_capture(ctx: RunContext) -> StageResult:
    """Plan (with the calibrated mounting when calibration ran) and capture; resumes a partial run."""
    scene = ctx.scene
    spec = scene.load_spec()
    plan = plan_for_capture(scene)
    options = CaptureOptions(settle_time_s=spec.capture.settle_time_s, save_depth=spec.capture.depth, resume=True)
    with open_rig(spec, ctx.rig.robot, ctx.rig.camera) as rig:
        summary = run_capture(scene.capture, plan.views, rig.robot, rig.camera, options)
    per_ring = plan.views_per_ring()
    return StageResult("capture", figures={
        "frames": summary.total,
        "per ring": "/".join(str(per_ring.get(i, 0)) for i in range(len(spec.capture.distances_m))),
        "dropped": len(plan.dropped),
        "robot time s": round(summary.robot_seconds, 1),
        "travel vs naive": f"{plan.travel_time_s:.0f}/{plan.naive_travel_time_s:.0f} s",
    })

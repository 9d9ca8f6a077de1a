"""The demo's export and serve stages.

``stage_export``: write the scene's bundle (and its BOP ground truth when it has none). ``stage_serve``: start the server on a free loopback
port in a background thread, run one short episode with a scripted agent through the Python
client, stop the server. The scripted agent demonstrates the API, it is not a baseline: it
steers with the target's ground-truth pose (turn to centre the target, fly towards it until
``stop_distance``), and it tries one teleport into the table to show a refusal (the pose and
the adjustment count must not change). Reading the truth, it needs a server in training mode
(:mod:`brave6d.serve.modes`), which this stage starts; it closes its episode without a submission.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from brave6d.core.errors import BraveError, DataError

if TYPE_CHECKING:
    from brave6d.core.run_context import RunContext
    from brave6d.core.progress import StageResult
    from brave6d.serve.client import BraveClient

log = logging.getLogger(__name__)


@dataclass
class EpisodeReport:
    episode_id: str
    steps: int
    adjustments: int
    refusals: int
    collisions: int
    start_distance_m: float
    final_distance_m: float
    final_visib_fract: float | None
    render_ms_median: float
    refusal_kept_pose: bool
    summary: dict[str, Any]


def run_scripted_episode(client: BraveClient, target: int | str | None = None, width: int = 320, height: int = 240,
                         seed: int = 0, max_steps: int = 12, stop_distance: float = 0.22,
                         speed: float = 0.08, duration: float = 0.5) -> EpisodeReport:
    """One episode: approach the target (see the module docstring); returns what happened."""
    step = client.reset(target=target, width=width, height=height, seed=seed)
    render_ms = [step.timings_ms.get("render", 0.0)]
    tgt = step.observation.target()
    if tgt is None:
        raise BraveError(f"the server returned no target object ({step.mode} mode): the scripted agent steers "
                         "with the ground truth, which only a server in training mode sends")
    start_distance = float(np.linalg.norm(tgt.cam_T_obj[:3, 3]))

    # one refused teleport: 5 cm below the table top
    before = step.observation.world_T_cam.copy()
    below = before.copy()
    below[2, 3] = -0.05
    refused = client.set_pose(below)
    kept = (not refused.accepted) and np.array_equal(refused.observation.world_T_cam, before) \
        and refused.adjustments == step.adjustments
    steps = 1
    for _ in range(max_steps):
        tgt = step.observation.target()
        assert tgt is not None
        p = tgt.cam_T_obj[:3, 3]
        dist = float(np.linalg.norm(p))
        if dist <= stop_distance:
            break
        # turn towards the target: bearing angles in the camera frame (x right, y down, z forward)
        yaw = float(np.arctan2(p[0], p[2]))
        pitch = float(np.arctan2(-p[1], p[2]))
        angular = np.array([pitch, yaw, 0.0]) / duration * 0.8
        linear = np.array([0.0, 0.0, min(speed, (dist - stop_distance) / duration)])
        step = client.move(linear, angular, duration)
        steps += 1
        if step.accepted:
            render_ms.append(step.timings_ms.get("render", 0.0))
        else:  # blocked: back off a little and go on
            step = client.move([0.0, -0.02, -0.02], [0.0, 0.0, 0.0], duration)
            steps += 1
    tgt = step.observation.target()
    assert tgt is not None
    summary = client.close()
    return EpisodeReport(step.episode_id, steps, int(summary["adjustments"]), int(summary["refusals"]),
                         int(summary["collisions"]), start_distance, float(np.linalg.norm(tgt.cam_T_obj[:3, 3])),
                         tgt.visib_fract, float(np.median(render_ms)), bool(kept), summary)


def stage_export(ctx: RunContext) -> StageResult:
    """Pipeline stage: write ``<scene>/bundle``, after the BOP ground truth when the scene has none
    yet (a captured scene imported with ``brave6d annotate import-3ddat`` alone; the pipeline's
    annotate stage writes it), so that the bundle's models and a release's test split are BOP's."""
    from brave6d.annotation import BopLayout, export_bop
    from brave6d.core.progress import StageResult
    from brave6d.serve.bundle import export_bundle

    try:
        bop_written = not BopLayout.of_scene(ctx.scene).scene_gt_path.is_file()
    except DataError:  # no BOP export at all
        bop_written = True
    if bop_written:
        export_bop(ctx.scene.root)
    result = export_bundle(ctx.scene.root)
    figures: dict[str, Any] = {"gaussians": result.gaussians, "objects": result.objects,
                               "holdout views": result.holdout_views, "MB": result.bytes / 1e6,
                               "models": result.models_from}
    if bop_written:
        figures["BOP ground truth"] = "written"
    return StageResult("export", figures=figures)


def stage_serve(ctx: RunContext) -> StageResult:
    """Demo stage: serve the bundle on loopback and run one scripted agent episode against it."""
    from brave6d.core.progress import StageResult
    from brave6d.serve.app import create_app
    from brave6d.serve.bundle import load_bundle
    from brave6d.serve.client import BraveClient
    from brave6d.serve.runner import ServerThread

    bundle = load_bundle(ctx.scene.bundle_dir)
    app = create_app(bundle, device=ctx.device, log_dir=ctx.workdir / "episodes", mode="training")
    size = (320, 240)
    with ServerThread(app) as server, BraveClient(server.url) as client:
        report = run_scripted_episode(client, target=0, width=size[0], height=size[1], seed=0,
                                      max_steps=6 if ctx.quick else 12)
    if not report.refusal_kept_pose:
        raise BraveError("serve demo: a refused move changed the pose or the adjustment count")
    return StageResult("serve", figures={
        "device": app.state.scene.device, "mode": "training", "steps": report.steps, "adjustments": report.adjustments,
        "refusals": report.refusals, "distance m": f"{report.start_distance_m:.3f}->{report.final_distance_m:.3f}",
        "visib": report.final_visib_fract if report.final_visib_fract is not None else "n/a",
        f"render ms @{size[0]}x{size[1]}": report.render_ms_median,
    })

"""The pipeline's stages, in order: each one a ``"module:function"`` imported only when it runs.

Each stage package owns its stage function (``stage(ctx: RunContext) -> StageResult``); this
registry only names them, so importing the pipeline loads no stage (docs/ARCHITECTURE.md).
:func:`run_stages` runs a selection with one :class:`~brave6d.core.run_context.RunContext`,
printing a line per stage; ``brave6d demo`` and each scene job of ``brave6d dataset run`` use it.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from brave6d.core.errors import BraveError
from brave6d.core.progress import StageResult, Stopwatch, format_table
from brave6d.core.run_context import RunContext


@dataclass(frozen=True)
class Stage:
    """One stage: its name, where its function lives (``"module:function"``) and what it does."""

    name: str
    target: str
    description: str

    def resolve(self) -> Callable[[RunContext], StageResult]:
        """The stage function (its module is imported now, not before)."""
        module_name, func_name = self.target.split(":")
        return getattr(importlib.import_module(module_name), func_name)


def stage_scene(ctx: RunContext) -> StageResult:
    """The scene directory exists (made from its spec, meshes copied): report what it holds."""
    spec = ctx.spec
    effects = spec.simulation.effects.enabled() if spec.simulation else []
    return StageResult("scene", figures={
        "objects": len(spec.objects),
        "static meshes": len(spec.static_meshes),
        "collision boxes": len(spec.collision_boxes),
        "effects": "+".join(effects) or "none",
    })


#: Pipeline order.
STAGES: tuple[Stage, ...] = (
    Stage("scene", "brave6d.pipeline.stages:stage_scene", "validate the demo spec and create the scene directory"),
    Stage("calibrate", "brave6d.calibration.demo:stage_calibrate",
          "capture the ChArUco board, calibrate intrinsics and hand-eye (simulated rig)"),
    Stage("capture", "brave6d.capture.demo:stage_capture", "plan the views and capture them (simulated UR5e + camera)"),
    Stage("annotate", "brave6d.annotation.demo:stage_annotation",
          "write the 3D-DAT folder, import it, export BOP ground truth"),
    Stage("train", "brave6d.training.demo:stage_train", "train the 3DGS scene on the CPU and evaluate the holdout"),
    Stage("export", "brave6d.serve.demo:stage_export", "write the scene bundle"),
    Stage("serve", "brave6d.serve.demo:stage_serve", "serve the bundle on loopback and run one scripted episode"),
    Stage("learn", "brave6d.evaluation.learned.demo:stage_learn",
          "render a synthetic train_pbr and train the learned baseline (detector + pose network) on it"),
    Stage("evaluate", "brave6d.evaluation.demo:stage_evaluate",
          "run the baselines (weight-free and learned) on every object and score them"),
    Stage("report", "brave6d.evaluation.report.build:stage_report", "write the accuracy-vs-time report"),
)


def stage_named(name: str) -> Stage:
    """The stage called ``name`` (a :class:`KeyError` naming the known ones otherwise)."""
    for stage in STAGES:
        if stage.name == name:
            return stage
    raise KeyError(f"no pipeline stage {name!r} (stages: {', '.join(s.name for s in STAGES)})")


def run_stages(ctx: RunContext, only: Sequence[str] | None = None) -> list[StageResult]:
    """Run the stages (``only``: these, in pipeline order) with ``ctx``, one line each; stops at the
    first failure (its result is recorded, failed, and the error raised)."""
    selected = [s for s in STAGES if not only or s.name in only]
    for number, stage in enumerate(selected, start=1):
        prefix = f"[{number}/{len(selected)}] {stage.name:<12}"
        print(f"{prefix} {stage.description} ...", file=sys.stderr, flush=True)
        with Stopwatch() as watch:
            try:
                result = stage.resolve()(ctx)
            except BraveError as exc:
                ctx.results.append(StageResult(stage.name, watch.seconds, "failed", {"error": str(exc)}))
                raise
        result.name, result.seconds = stage.name, watch.seconds
        ctx.results.append(result)
        print(f"{prefix} done in {watch.seconds:.1f} s  {result.figures_text()}", file=sys.stderr, flush=True)
    return ctx.results


def summary_table(results: Sequence[StageResult]) -> str:
    """The final table: stage, status, seconds, key figures."""
    rows = [(r.name, r.status, f"{r.seconds:.1f}", r.figures_text()) for r in results]
    total = sum(r.seconds for r in results)
    rows.append(("total", "", f"{total:.1f}", ""))
    return format_table(["stage", "status", "seconds", "figures"], rows)

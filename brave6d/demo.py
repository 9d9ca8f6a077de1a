"""``brave6d demo``: run every pipeline stage, in order, on the embedded demo scene.

Each stage is a function ``stage(ctx) -> StageResult`` living in its own package and named
here as ``"module:function"``, so this module imports no stage until it runs (docs/ARCHITECTURE.md,
layering). The demo prints one line per stage and a summary table at the end.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from brave6d.errors import BraveError
from brave6d.layout import SceneDir, init_scene_dir, write_spec
from brave6d.progress import StageResult, Stopwatch, format_table
from brave6d.spec import SceneSpec

log = logging.getLogger(__name__)

#: The embedded demo scene shipped in the repository's ``data/`` folder.
DEMO_SPEC = Path(__file__).resolve().parent.parent / "data" / "demo" / "scene.yaml"


@dataclass
class DemoContext:
    """What the stages of one demo run share."""

    workdir: Path
    scene: SceneDir
    spec: SceneSpec
    quick: bool = False
    device: str = "auto"
    results: list[StageResult] = field(default_factory=list)
    #: object name -> BOP obj_id fixed by a dataset's library (None: the scene numbers its own)
    obj_ids: dict[str, int] | None = None
    #: continue a training from its checkpoints (``brave6d dataset run`` after a preemption)
    resume: bool = False


@dataclass(frozen=True)
class DemoStage:
    name: str
    target: str  # "module:function", imported only when the stage runs
    description: str

    def resolve(self) -> Callable[[DemoContext], StageResult]:
        module_name, func_name = self.target.split(":")
        return getattr(importlib.import_module(module_name), func_name)


def stage_scene(ctx: DemoContext) -> StageResult:
    """Create the scene directory from the embedded spec (validates it, copies the meshes)."""
    spec = ctx.spec
    effects = spec.simulation.effects.enabled() if spec.simulation else []
    return StageResult("scene", figures={
        "objects": len(spec.objects),
        "static meshes": len(spec.static_meshes),
        "collision boxes": len(spec.collision_boxes),
        "effects": "+".join(effects) or "none",
    })


#: Pipeline order. Each stage package appends its line when it exists.
STAGES: tuple[DemoStage, ...] = (
    DemoStage("scene", "brave6d.demo:stage_scene", "validate the demo spec and create the scene directory"),
    DemoStage("calibrate", "calibration.demo:stage_calibrate",
              "capture the ChArUco board, calibrate intrinsics and hand-eye (simulated rig)"),
    DemoStage("capture", "capture.demo:stage_capture", "plan the views and capture them (simulated UR5e + camera)"),
    DemoStage("annotate", "annotation.demo:stage_annotation", "write the 3D-DAT folder, import it, export BOP ground truth"),
    DemoStage("train", "training.demo:stage_train", "train the 3DGS scene on the CPU and evaluate the holdout"),
    DemoStage("export", "serve.demo:stage_export", "write the scene bundle"),
    DemoStage("serve", "serve.demo:stage_serve", "serve the bundle on loopback and run one scripted episode"),
    DemoStage("evaluate", "evaluation.demo:stage_evaluate", "run the active and static baselines on every object and score them"),
    DemoStage("report", "evaluation.report.build:stage_report", "write the accuracy-vs-time report"),
)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workdir", type=Path, default=Path("runs/demo"),
                        help="where the demo scene directory is written (default: runs/demo)")
    parser.add_argument("--spec", type=Path, default=DEMO_SPEC, help="scene spec (default: the embedded demo)")
    parser.add_argument("--quick", action="store_true",
                        help="miniature run: few views, few training steps, small images (what CI runs)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                        help="rasterizer device for training and rendering")
    parser.add_argument("--only", nargs="*", metavar="STAGE", choices=[s.name for s in STAGES],
                        help="run only these stages (earlier outputs must exist)")


def run(args: argparse.Namespace) -> int:
    ctx = prepare(args.workdir, args.spec, quick=args.quick, device=args.device)
    run_stages(ctx, only=args.only)
    print()
    print(summary_table(ctx.results))
    print(f"\nscene directory: {ctx.scene.root}")
    return 0


#: What ``--quick`` changes in the spec: few views on two rings (CI's miniature end-to-end run).
QUICK_CAPTURE = {"distances_m": [0.3, 0.45], "views_per_distance": 10}


def prepare(workdir: Path, spec_file: Path = DEMO_SPEC, quick: bool = False, device: str = "auto") -> DemoContext:
    """Create (or reuse) the demo scene directory under ``workdir`` (a miniature variant if ``quick``)."""
    scene = init_scene_dir(Path(workdir) / "scene", spec_file)
    spec = scene.load_spec()
    if quick:
        capture = spec.capture.model_copy(update=QUICK_CAPTURE)
        spec = spec.model_copy(update={"capture": capture, "name": f"{spec.name}_quick"})
        write_spec(scene, spec)
        spec = scene.load_spec()
    return DemoContext(workdir=Path(workdir), scene=scene, spec=spec, quick=quick, device=device)


def run_stages(ctx: DemoContext, only: list[str] | None = None) -> list[StageResult]:
    """Run the stages in order, printing one line each; stops at the first failure."""
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


def summary_table(results: list[StageResult]) -> str:
    """The final table: stage, status, seconds, key figures."""
    rows = [(r.name, r.status, f"{r.seconds:.1f}", r.figures_text()) for r in results]
    total = sum(r.seconds for r in results)
    rows.append(("total", "", f"{total:.1f}", ""))
    return format_table(["stage", "status", "seconds", "figures"], rows)

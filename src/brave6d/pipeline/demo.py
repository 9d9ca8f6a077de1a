"""``brave6d demo``: the pipeline on the embedded demo scene (simulated robot and camera).

One configuration of :mod:`brave6d.pipeline`: it makes (or reuses) the scene directory from the
spec in the repository's ``data/demo/``, runs :data:`~brave6d.pipeline.stages.STAGES` in order with
one :class:`~brave6d.core.run_context.RunContext` (the simulated rig, the training stage's default
preset), and prints a summary table at the end.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.core.layout import init_scene_dir, write_spec
from brave6d.core.run_context import DEVICES, QUICK_CAPTURE, RunContext
from brave6d.pipeline.stages import STAGES, run_stages, summary_table

#: The embedded demo scene shipped in the repository's ``data/`` folder.
DEMO_SPEC = Path(__file__).resolve().parents[3] / "data" / "demo" / "scene.yaml"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workdir", type=Path, default=Path("runs/demo"),
                        help="where the demo scene directory is written (default: runs/demo)")
    parser.add_argument("--spec", type=Path, default=DEMO_SPEC, help="scene spec (default: the embedded demo)")
    parser.add_argument("--quick", action="store_true",
                        help="miniature run: few views, few training steps, small images (what CI runs)")
    parser.add_argument("--device", choices=DEVICES, default="auto",
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


def prepare(workdir: Path, spec_file: Path = DEMO_SPEC, quick: bool = False, device: str = "auto") -> RunContext:
    """Create (or reuse) the demo scene directory under ``workdir`` (a miniature variant if
    ``quick``); the run's context: the simulated rig and the training stage's default preset."""
    scene = init_scene_dir(Path(workdir) / "scene", spec_file)
    if quick:
        spec = scene.load_spec()
        capture = spec.capture.model_copy(update=QUICK_CAPTURE)
        write_spec(scene, spec.model_copy(update={"capture": capture, "name": f"{spec.name}_quick"}))
    return RunContext.for_scene(scene.root, workdir=workdir, quick=quick, device=device)

"""``brave6d report [--workdir DIR | --scene SCENE_DIR --out DIR]``: the accuracy-vs-time report of a demo
work directory (``WORKDIR/scene`` into ``WORKDIR/report``) or of any scene directory into ``--out``.

Registered in ``brave6d/cli.py`` as ``Command("report", "brave6d.evaluation.report.cli", ...)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from brave6d.core.errors import BraveError

if TYPE_CHECKING:
    from brave6d.evaluation.report.build import ReportTarget


def configure(parser: argparse.ArgumentParser) -> None:
    from brave6d.evaluation.report.sections import names

    sections = names()
    parser.add_argument("--workdir", type=Path, default=Path("runs/demo"),
                        help="the demo's work directory, holding scene/; the report goes to WORKDIR/report "
                             "(default: runs/demo)")
    parser.add_argument("--scene", type=Path, default=None, metavar="SCENE_DIR",
                        help="report on this scene directory instead (any scene, e.g. a dataset's "
                             "scenes/<name>); needs --out")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="with --scene: the folder of report.md, its PNGs and measurements/")
    parser.add_argument("--mode", choices=["auto", "quick", "full"], default="auto",
                        help="sweep sizes: quick (CI's miniature, < 2 min) or full (several minutes); auto: quick "
                             "when the scene was made by 'brave6d demo --quick' (default: %(default)s)")
    parser.add_argument("--refresh", action="store_true", help="measure again instead of reusing cached measurements")
    parser.add_argument("--only", nargs="+", choices=sections, metavar="SECTION",
                        help=f"measure only these ({', '.join(sections)}); the others come from the cache")
    parser.add_argument("--no-measure", action="store_true",
                        help="only write the page from the cached measurements in <workdir>/report/measurements")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                        help="where to train and render: every section with a device setting "
                             "(default: %(default)s)")
    parser.add_argument("--benchmark-json", type=Path, default=None,
                        help="output of benchmarks/training.py --json, for the training section "
                             "(default: scene/splat/benchmark_training.json)")
    parser.add_argument("--schedules-json", type=Path, default=None,
                        help="output of benchmarks/time_to_quality.py --json, for the training section's "
                             "schedule comparison (default: scene/splat/time_to_quality.json)")


def run(args: argparse.Namespace) -> int:
    from brave6d.core.runtime import quiet_openmp

    quiet_openmp()  # before torch / numba load: spinning OpenMP threads distort the timings
    from brave6d.evaluation.report.build import ReportSettings, build_report

    target = report_target(args.workdir, args.scene, args.out)
    if not target.scene.is_dir() and not args.no_measure:
        hint = (f"run 'brave6d demo --workdir {args.workdir}' first" if args.scene is None
                else "give a scene directory made by 'brave6d init' or 'brave6d dataset run'")
        raise BraveError(f"{target.scene}: no scene directory ({hint})")
    quick = args.mode == "quick" or (args.mode == "auto" and _made_quick(target.scene))
    settings = ReportSettings.for_mode(quick, args.device, args.benchmark_json, args.schedules_json)
    result = build_report(target, settings, refresh=args.refresh, only=tuple(args.only or ()),
                          measure=not args.no_measure)
    for name, status in result.statuses.items():
        took = f" ({result.seconds[name]:.1f} s)" if name in result.seconds else ""
        print(f"{name:<10} {status}{took}")
    print(f"\nreport: {result.markdown}")
    return 0


def report_target(workdir: Path, scene: Path | None, out: Path | None) -> ReportTarget:
    """``--scene``/``--out`` (both or neither) or the demo layout of ``--workdir``."""
    from brave6d.evaluation.report.build import ReportTarget

    if scene is None and out is None:
        return ReportTarget.of_workdir(workdir)
    if scene is None or out is None:
        raise BraveError("brave6d report: --scene and --out go together (give both, or --workdir alone)")
    return ReportTarget.of_scene(scene, out)


def _made_quick(scene_dir: Path) -> bool:
    """True when the scene's spec is the demo's quick variant (its name ends in ``_quick``)."""
    from brave6d.core.layout import SceneDir

    try:
        return SceneDir(scene_dir).load_spec().name.endswith("_quick")
    except BraveError:
        return False

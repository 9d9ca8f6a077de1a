"""``brave6d report [--workdir DIR]``: the accuracy-vs-time report of a demo work directory.

Registered in ``brave6d/cli.py`` as ``Command("report", "evaluation.report.cli", ...)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.errors import BraveError


def configure(parser: argparse.ArgumentParser) -> None:
    from evaluation.report.sections import names

    sections = names()
    parser.add_argument("--workdir", type=Path, default=Path("runs/demo"),
                        help="the demo's work directory, holding scene/ (default: runs/demo)")
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


def run(args: argparse.Namespace) -> int:
    from brave6d.runtime import quiet_openmp

    quiet_openmp()  # before torch / numba load: spinning OpenMP threads distort the timings
    from evaluation.report.build import ReportSettings, build_report

    scene_dir = args.workdir / "scene"
    if not scene_dir.is_dir() and not args.no_measure:
        raise BraveError(f"{scene_dir}: no scene directory (run 'brave6d demo --workdir {args.workdir}' first)")
    quick = args.mode == "quick" or (args.mode == "auto" and _made_quick(scene_dir))
    settings = ReportSettings.for_mode(quick, args.device, args.benchmark_json)
    result = build_report(args.workdir, settings, refresh=args.refresh, only=tuple(args.only or ()),
                          measure=not args.no_measure)
    for name, status in result.statuses.items():
        took = f" ({result.seconds[name]:.1f} s)" if name in result.seconds else ""
        print(f"{name:<10} {status}{took}")
    print(f"\nreport: {result.markdown}")
    return 0


def _made_quick(scene_dir: Path) -> bool:
    """True when the scene's spec is the demo's quick variant (its name ends in ``_quick``)."""
    from brave6d.layout import SceneDir

    try:
        return SceneDir(scene_dir).load_spec().name.endswith("_quick")
    except BraveError:
        return False

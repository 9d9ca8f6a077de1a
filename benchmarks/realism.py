"""The report's realism section (section 7) with a larger sweep: the static estimator's AR on captured
frames and on the splat's renders of the same poses, per ring, with more targets than the report's
quick default (one target moves a ring's AR by about 1 / targets).

    python benchmarks/realism.py runs/demo [--holdout-per-level 8] [--train-per-level 4] [--device cpu]

WORKDIR holds ``scene/`` (a captured, annotated scene with its bundle). Prints one line per ring: views,
targets, AR on the captured frames, AR on the splat, the gap with the standard error of its per-target
differences, and the renders' PSNR. ``--holdout-per-level 1000 --train-per-level 1000`` takes every view.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from brave6d.core.layout import SceneDir
from brave6d.evaluation.report.measurements import MeasurementStore
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.sections.realism import RealismSweep, gap_rows, measure_realism


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdir", type=Path, help="a directory holding scene/ (e.g. runs/demo)")
    parser.add_argument("--holdout-per-level", type=int, default=8)
    parser.add_argument("--train-per-level", type=int, default=4)
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    args = parser.parse_args()
    sweep = RealismSweep(holdout_per_level=args.holdout_per_level, train_per_level=args.train_per_level,
                         device=args.device)
    with tempfile.TemporaryDirectory() as cache:
        inputs = MeasureInputs(args.workdir, SceneDir(args.workdir / "scene"), MeasurementStore(cache, refresh=True))
        measured = measure_realism(inputs, sweep)
    print("| cm | views | targets | AR captured | AR splat | gap ± SE | PSNR dB |")
    print("|---|---|---|---|---|---|---|")
    for r in gap_rows(measured.points):
        print(f"| {100 * r['distance_m']:.0f} | {r['views']} | {r['targets']} | {r['ar_real']:.3f} | "
              f"{r['ar_splat']:.3f} | {r['gap']:.3f} ± {r['gap_se']:.3f} | {r['psnr']:.2f} |")


if __name__ == "__main__":
    main()

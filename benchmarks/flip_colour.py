"""What colour buys the static estimator, and what it costs: the realism sweep (captured frames vs the
splat's renders of the same poses) once per colour weight, per ring: AR on each side, the gap with
its standard error, and the median time of one estimate.

    python benchmarks/flip_colour.py runs/demo [--weights 0,0.1] [--holdout-per-level 8]
                                     [--train-per-level 22] [--device cpu]

Weight 0 is depth alone: a near-symmetric object and its 180 degree flip explain the depth alike
and the winner follows noise (on the splat, its training noise). The agents' default weight is
``brave6d.evaluation.agents.registration.COLOR_WEIGHT``. The weights run one after the other on the
same views; the splat is rendered once per weight.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from brave6d.core.layout import SceneDir
from brave6d.evaluation.report.measurements import MeasurementStore
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.sections.realism import RealismSweep, gap_rows, measure_realism, targets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdir", type=Path, help="a directory holding scene/ (e.g. runs/demo)")
    parser.add_argument("--weights", default="0,0.1", help="comma-separated colour weights (0: depth alone)")
    parser.add_argument("--holdout-per-level", type=int, default=8)
    parser.add_argument("--train-per-level", type=int, default=22)
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    args = parser.parse_args()
    weights = [float(w) for w in args.weights.split(",") if w.strip()]
    if not weights or any(not w >= 0 for w in weights):
        parser.error(f"--weights must be non-negative numbers, got {args.weights!r}")
    print("| weight | cm | targets | AR captured | AR splat | gap ± SE | estimate s (median, captured / splat) |")
    print("|---|---|---|---|---|---|---|")
    for weight in weights:
        sweep = RealismSweep(holdout_per_level=args.holdout_per_level, train_per_level=args.train_per_level,
                             device=args.device, color_weight=weight)
        with tempfile.TemporaryDirectory() as cache:
            inputs = MeasureInputs(args.workdir, SceneDir(args.workdir / "scene"),
                                   MeasurementStore(cache, refresh=True))
            measured = measure_realism(inputs, sweep)
        objects = targets(measured.points)
        for r in gap_rows(measured.points):
            ring = [o for o in objects if abs(o["distance_m"] - r["distance_m"]) < 1e-9]
            real_s = statistics.median(o["real_estimate_s"] for o in ring) if ring else float("nan")
            splat_s = statistics.median(o["splat_estimate_s"] for o in ring) if ring else float("nan")
            print(f"| {weight:g} | {100 * r['distance_m']:.0f} | {r['targets']} | {r['ar_real']:.3f} | "
                  f"{r['ar_splat']:.3f} | {r['gap']:.3f} ± {r['gap_se']:.3f} | {real_s:.2f} / {splat_s:.2f} |",
                  flush=True)


if __name__ == "__main__":
    main()

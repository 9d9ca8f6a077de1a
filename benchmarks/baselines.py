"""The registered agents (active against static baseline): BOP AR over several seed sets of one bundle.

One seed set is what the demo's evaluation stage runs (every registered agent from the same
seeded random starts, ``EPISODES_PER_OBJECT`` per object, seeds ``offset + gt_id + 1000 r``);
with one set the AR of four objects swings by several hundredths between seeds, so this script
runs several sets side by side and prints each set's AR for every agent, the active baseline's
margin over the static one, and the pooled figures. The episode logs of each set go to
``<out>/set_<offset>/``.

    python benchmarks/baselines.py [--bundle DIR] [--offsets 0 50000 90000 130000] [--json out.json]
        [--learned-model MODEL_DIR]   # also the four learned agents (brave6d learn train), and their margin
        [--detector MODULE:FACTORY] [--pose-estimator MODULE:FACTORY]  # the learned agents on your own
                                      # estimators (brave6d.evaluation.estimators; docs/GUIDE.md)

Default bundle: ``runs/demo/scene/bundle`` (what ``bash scripts/demo.sh`` writes).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch / numba load (see brave6d.core.runtime)

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(ROOT / "src"))

from brave6d.evaluation.agents import ACTIVE_AGENT, LEARNED_ACTIVE_AGENT, LEARNED_STATIC_AGENT, STATIC_AGENT, \
    AgentSetup, runnable_agents
from brave6d.evaluation.demo import EPISODES_PER_OBJECT, run_baselines

DEFAULT_BUNDLE = ROOT / "runs" / "demo" / "scene" / "bundle"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", type=Path, default=DEFAULT_BUNDLE, help="scene bundle (default: the demo's)")
    ap.add_argument("--offsets", type=int, nargs="+", default=[0, 50000, 90000, 130000],
                    help="seed offsets, one seed set each (0 is the demo's)")
    ap.add_argument("--episodes", type=int, default=EPISODES_PER_OBJECT, help="episodes per object and set")
    ap.add_argument("--out", type=Path, default=None, help="where the episode logs go (default: a temp folder)")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    ap.add_argument("--learned-model", type=Path, default=None,
                    help="a trained model folder: the learned agents play too (default: the weight-free ones only)")
    ap.add_argument("--detector", default=None, metavar="MODULE:FACTORY",
                    help="the learned agents' detector: a factory of your own (brave6d.evaluation.estimators.Detector), "
                         "'learned' (default: the trained model's) or 'learned-onnx' (its ONNX export on ONNX Runtime)")
    ap.add_argument("--pose-estimator", default=None, metavar="MODULE:FACTORY",
                    help="the learned agents' pose estimator: a factory of your own, 'learned', 'learned-onnx' or "
                         "'registration' "
                         "(weight-free, the -depth agents only)")
    args = ap.parse_args(argv)
    if not (args.bundle / "manifest.json").is_file():
        ap.error(f"{args.bundle}: no bundle (run `bash scripts/demo.sh` first, or pass --bundle)")
    out_root = args.out or Path(tempfile.mkdtemp(prefix="brave6d_baselines_"))
    setup = AgentSetup(learned_model=args.learned_model, detector=args.detector, pose_estimator=args.pose_estimator)
    names = runnable_agents(setup)
    rows = []
    print(f"{'seed offset':>11} | " + " | ".join(f"{name:>15}" for name in names) +
          f" | {'active - static':>15} | {'adjustments':>11} | {'seconds':>7}", flush=True)
    for offset in args.offsets:
        t0 = time.perf_counter()
        run = run_baselines(args.bundle, out_root / f"set_{offset}", device="cpu", seed=offset,
                            episodes_per_object=args.episodes, setup=setup)
        agents = {a.agent: a for a in run.board.agents}
        static, active = agents[STATIC_AGENT], agents[ACTIVE_AGENT]
        row = {"offset": offset, "episodes": static.episodes, "ar": {name: agents[name].ar for name in names},
               "static_ar": static.ar, "active_ar": active.ar, "active_adjustments": active.mean_adjustments,
               "seconds": time.perf_counter() - t0}
        rows.append(row)
        print(f"{offset:>11} | " + " | ".join(f"{row['ar'][name]:15.3f}" for name in names) +
              f" | {active.ar - static.ar:+15.3f} | {active.mean_adjustments:11.2f} | {row['seconds']:7.0f}",
              flush=True)
    n = sum(r["episodes"] for r in rows)
    pooled = {k: sum(r[k] * r["episodes"] for r in rows) / n for k in ("static_ar", "active_ar")}
    pooled_ar = {name: sum(r["ar"][name] * r["episodes"] for r in rows) / n for name in names}
    wins = sum(r["active_ar"] > r["static_ar"] for r in rows)
    if LEARNED_ACTIVE_AGENT in names:
        for suffix in ("", "-depth"):
            a, st = pooled_ar[LEARNED_ACTIVE_AGENT + suffix], pooled_ar[LEARNED_STATIC_AGENT + suffix]
            print(f"learned{suffix}: active - static {a - st:+.3f} (pooled), higher in "
                  f"{sum(r['ar'][LEARNED_ACTIVE_AGENT + suffix] > r['ar'][LEARNED_STATIC_AGENT + suffix] for r in rows)}"
                  f" of {len(rows)} sets")
    print(f"pooled over {n} episodes per agent: " + ", ".join(f"{name} {ar:.3f}" for name, ar in pooled_ar.items()) +
          f" (active - static {pooled['active_ar'] - pooled['static_ar']:+.3f}); active higher in {wins} of "
          f"{len(rows)} sets")
    print(f"episode logs: {out_root}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        result = {"bundle": str(args.bundle), "sets": rows, "pooled": pooled, "pooled_ar": pooled_ar}
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

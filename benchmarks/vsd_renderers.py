"""VSD's two depth renderers priced on BOP results CSVs: Open3D ray casting against the rasteriser
that follows bop_toolkit's OpenGL rules (``DepthRenderer(method="raycast" | "gl")``).

Run: ``.venv/bin/python benchmarks/vsd_renderers.py --split SPLIT --models MODELS A.csv [B.csv ...]
[--rounds 2]``. For each CSV, brave6d's BOP19 scoring (``evaluate_bop19``) with VSD alone and with
all three metrics, each renderer in turn (rounds interleaved; the fastest run reported), and one
render per estimate alone. Prints the time per estimate-GT pair, per scoring and per render, and the
AR each renderer gives (the rasteriser's equals bop_toolkit's: docs/BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from brave6d.evaluation.estimate_bop import scene_folders
from brave6d.evaluation.metrics import (DepthRenderer, EvalConfig, evaluate_bop19, load_models,
                                        load_scene_gt_instances, read_bop_results)

METHODS = ("raycast", "gl")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("csv", type=Path, nargs="+", help="BOP results CSVs of the split")
    ap.add_argument("--split", type=Path, required=True, help="the BOP split folder (its scene folders)")
    ap.add_argument("--models", type=Path, required=True, help="the BOP models folder (mm)")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    gts = [g for s in scene_folders(args.split) for g in load_scene_gt_instances(s)]
    models = load_models(args.models, sorted({g.obj_id for g in gts}))

    def renderer(method: str) -> DepthRenderer:
        r = DepthRenderer(method=method)
        for obj_id, m in models.items():
            r.add_object(obj_id, m.points, m.faces)
        return r

    first = {g.scene_id * 1_000_000 + g.im_id: g for g in reversed(gts)}
    for path in args.csv:
        ests = read_bop_results(path)
        for m in METHODS:  # warm up: numba's cached code, Open3D's import
            evaluate_bop19(gts[:3], ests[:3], models, renderer=renderer(m))
        runs: dict[tuple[str, str], list[float]] = {}
        figures: dict[str, tuple[float, float, int]] = {}
        for _ in range(args.rounds):
            for m in METHODS:
                for what, cfg in (("vsd", EvalConfig(metrics=("vsd",))), ("all", None)):
                    t0 = time.perf_counter()
                    s = evaluate_bop19(gts, ests, models, config=cfg, renderer=renderer(m))
                    runs.setdefault((m, what), []).append(time.perf_counter() - t0)
                    if what == "vsd":
                        pairs = sum(len(e.gt_ids) for e in s.errors if e.vsd is not None)
                        figures[m] = (figures.get(m, (0.0, 0.0, 0))[0], float(s.ar_vsd), pairs)
                    else:
                        figures[m] = (float(s.ar), figures[m][1], figures[m][2])
        poses = [(e.obj_id, e.R, e.t, first[e.scene_id * 1_000_000 + e.im_id]) for e in ests
                 if e.scene_id * 1_000_000 + e.im_id in first]
        render_ms: dict[str, list[float]] = {}
        rens = {m: renderer(m) for m in METHODS}
        for _ in range(args.rounds):
            for m in METHODS:
                t0 = time.perf_counter()
                for obj_id, R, t, g in poses:
                    rens[m].render(obj_id, R, t, g.K, g.image_size[0], g.image_size[1])
                render_ms.setdefault(m, []).append(1000 * (time.perf_counter() - t0) / max(len(poses), 1))
        print(f"{path.name}: {len(ests)} estimates, {figures[METHODS[0]][2]} estimate-GT pairs with VSD")
        for m in METHODS:
            ar, ar_vsd, pairs = figures[m]
            vsd_s, all_s = min(runs[(m, "vsd")]), min(runs[(m, "all")])
            print(f"  {m:8s} VSD alone {vsd_s:.2f} s ({1000 * vsd_s / max(pairs, 1):.2f} ms per pair), all metrics "
                  f"{all_s:.2f} s, one render {min(render_ms[m]):.2f} ms; AR {ar:.9f}, AR_VSD {ar_vsd:.9f}")


if __name__ == "__main__":
    main()

"""Fidelity where agents look (issue #34): the splat against the truth at 10-50 cm, for one or two
splats side by side, with what each one cost to train.

For a simulated scene (``scene.yaml`` with a ``simulation:`` part) the splat and the simulator's truth
without camera effects are rendered at the same seeded viewpoints per object (looking at its centre,
collision-checked, at each ``--distances``, ``--views`` per object and distance, the bundle's
camera); for a captured scene the splat is compared with the held-out frames of each ring and
their sensor depth. Per distance it reports the medians of: target pixels, PSNR/SSIM of the image
and of the target's box, the depth error on the target's pixels (median mm, shares within 5 and
15 mm, share without splat depth), and the static estimator's AR on truth and on splat and their
gap (:mod:`brave6d.evaluation.report.fidelity`, the report's fidelity section).

Two ways to get the splats:

* ``--bundle [NAME=]PATH`` (once or twice): measure existing bundles, no training;
* ``--a NAME=PRESET[,field=value...] --b NAME=PRESET[,...]``: train both on the scene, interleaved
  in chunks of ``--chunk`` steps as ``time_to_quality.py`` does (its code), each one's training wall
  time recorded, then measure both trained splats (the scene's bundle gives objects, camera and
  collision world). Any :class:`brave6d.training.Preset` field can be set by name.

Writes a JSON (default ``<scene>/splat/fidelity.json``) and a PNG beside it (metric against
distance, one line per configuration), prints one table per configuration (metrics as rows,
distances as columns) and one line per configuration with its training time:

    python benchmarks/fidelity.py runs/demo/scene --bundle runs/demo/scene/bundle
    python benchmarks/fidelity.py runs/demo/scene --a fast=fast --b depth=fast,depth_lambda=0.1
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # time_to_quality beside this file (also when imported by a test)
    sys.path.insert(0, str(HERE))
if str(HERE.parent / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(HERE.parent / "src"))

import time_to_quality as ttq  # noqa: E402 - after the path set-up

from brave6d.core.errors import BraveError, DataError  # noqa: E402
from brave6d.evaluation.report.fidelity import DISTANCES_M, FidelitySweep  # noqa: E402


#: The default number of viewpoints per distance, over all objects (the issue's table: 12).
VIEWS_PER_DISTANCE = 12


def bundle_arg(text: str) -> tuple[str, Path]:
    """``[NAME=]PATH`` -> (name, path); the name defaults to the bundle folder's parent and name."""
    name, sep, path = text.partition("=")
    if not sep:
        p = Path(text)
        return f"{p.parent.name}/{p.name}" if p.parent.name else p.name, p
    return name, Path(path)


def distances_arg(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"--distances: comma-separated metres, got {text!r}") from None
    if not values or any(not (math.isfinite(v) and 0.0 < v < 10.0) for v in values):
        raise argparse.ArgumentTypeError(f"--distances: positive distances under 10 m, got {text!r}")
    return values


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def scene_bundle(scene: Any) -> Any:
    """The scene's bundle (objects, camera, collision world), with a clear error when it has none."""
    from brave6d.serve import MANIFEST, load_bundle

    if not (scene.bundle_dir / MANIFEST).is_file():
        raise DataError(f"{scene.bundle_dir}: no bundle (run 'brave6d export {scene.root}' first); the fidelity "
                        "benchmark takes the objects, camera and collision world from it")
    return load_bundle(scene.bundle_dir)


def recorded_training(path: Path, bundle: Any) -> dict[str, Any]:
    """A bundle's training time and holdout PSNR from the training's ``splat/metrics.json`` of the
    scene directory holding it, when that file is the one the bundle records (same SHA-256); else None."""
    import hashlib

    from brave6d.core.atomic import read_json
    from brave6d.core.layout import SceneDir
    from brave6d.evaluation.report.fidelity import recorded_downscale

    metrics = SceneDir(Path(path).resolve().parent).metrics_path
    recorded = (bundle.manifest.get("source") or {}).get("metrics_sha256")
    if not recorded or not metrics.is_file() or hashlib.sha256(metrics.read_bytes()).hexdigest() != recorded:
        return {"train_s": None, "holdout_psnr": None}
    data = read_json(metrics)
    return {"train_s": data.get("train_time_s"), "train_cpu_s": data.get("train_cpu_s"),
            "holdout_psnr": (data.get("holdout") or {}).get("psnr"), "steps": data.get("steps"),
            "downscale": recorded_downscale(data)}


def configurations(args: argparse.Namespace, scene: Any, device: Any) -> list[dict[str, Any]]:
    """One entry per configuration: its name, what it is, its training figures and its renderer
    (None: the bundle's own splat) with the bundle it is measured with."""
    from brave6d.serve import MANIFEST, SplatRenderer, load_bundle

    if args.bundle:
        out = []
        for name, path in args.bundle:
            if not (path / MANIFEST).is_file():
                raise DataError(f"{path}: not a bundle (no {MANIFEST}; run 'brave6d export' first)")
            bundle = load_bundle(path)
            out.append({"name": name, "source": {"bundle": str(path)}, "bundle": bundle, "renderer": None,
                        "gaussians": bundle.manifest.get("gaussians"), **recorded_training(path, bundle)})
        return out
    bundle = scene_bundle(scene)
    runs = []
    try:
        for config in (args.a, args.b):  # one after the other: both write the scene's sparse/0 (initial points)
            runs.append(ttq.local_run(config, scene, args.every, device, args.init))
        for r in runs:  # the second one's warm-up ran after the first's: count from here
            r.jit_baseline = ttq.jit_signatures()
        ttq.interleave(runs, args.chunk)
        a, b = runs
        summaries = [a.summary(b.points[-1]["psnr"]), b.summary(a.points[-1]["psnr"])]
    finally:
        for r in runs:
            r.close()
    return [{"name": r.name, "source": {"preset": s["preset"]}, "bundle": bundle,
             "renderer": SplatRenderer.from_splat(r.trainer.model.to_splat(), str(device), source=f"trained {r.name}"),
             "train_s": s["train_s"], "train_cpu_s": s["train_cpu_s"], "holdout_psnr": s["final_psnr"],
             "gaussians": s["gaussians"], "steps": s["steps"], "downscale": s["preset"]["downscale"]}
            for r, s in zip(runs, summaries)]


def measure(configs: list[dict[str, Any]], scene: Any, sweep: FidelitySweep) -> None:
    """Every configuration's views, one progress bar (with ETA) over all of them; fills ``points``."""
    from brave6d.core.progress import progress_bar
    from brave6d.evaluation.report.fidelity import FidelityProbe

    probes = [FidelityProbe(scene, c["bundle"], sweep, c["renderer"], c.get("downscale")) for c in configs]
    bar = progress_bar(total=sum(len(p.items()) for p in probes), desc="fidelity", unit="view")
    try:
        for c, probe in zip(configs, probes):
            c["mode"], c["settings"] = probe.mode, probe.settings()
            c["points"] = []
            for view_id, item in probe.items():
                c["points"].append({"id": view_id, **probe.measure(item)})
                bar.update(1)
    finally:
        bar.close()


def cell(value: Any, digits: int = 0, unit: str = "") -> str:
    from brave6d.evaluation.report.common import fmt

    text = fmt(value, digits)
    return text if text == "n/a" else text + unit


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene_dir", type=Path, help="a scene directory with a bundle (e.g. runs/demo/scene)")
    parser.add_argument("--bundle", type=bundle_arg, action="append", default=[], metavar="[NAME=]PATH",
                        help="measure this bundle's splat without training (at most twice)")
    parser.add_argument("--a", default=None, help="configuration A to train, NAME=PRESET[,field=value...]")
    parser.add_argument("--b", default=None, help="configuration B to train, e.g. depth=fast,depth_lambda=0.1")
    parser.add_argument("--distances", type=distances_arg, default=DISTANCES_M,
                        help="simulated scenes: camera distances to the object's centre in metres "
                             f"(default {','.join(f'{d:g}' for d in DISTANCES_M)})")
    parser.add_argument("--views", type=positive_int, default=None,
                        help=f"simulated scenes: viewpoints per object and distance (default: about {VIEWS_PER_DISTANCE} "
                             "per distance over all objects, 3 on the demo's 4)")
    parser.add_argument("--holdout-per-level", type=positive_int, default=FidelitySweep.holdout_per_level,
                        help="captured scenes: held-out frames per capture ring (default "
                             f"{FidelitySweep.holdout_per_level})")
    parser.add_argument("--seed", type=int, default=0, help="viewpoints' seed (default 0)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--chunk", type=positive_int, default=50, help="training steps per turn (default 50)")
    parser.add_argument("--every", type=positive_int, default=500, help="holdout evaluation every K training steps")
    parser.add_argument("--init", choices=["auto", "colmap", "depth", "random"], default="auto")
    parser.add_argument("--json", type=Path, default=None, help="output JSON (default: <scene>/splat/fidelity.json)")
    args = parser.parse_args(argv)
    if args.bundle and (args.a or args.b):
        parser.error("either --bundle (measure existing splats) or --a/--b (train two configurations), not both")
    if len(args.bundle) > 2:
        parser.error("--bundle: at most two")
    if not args.bundle and not (args.a and args.b):
        parser.error("give --bundle PATH (once or twice), or both --a and --b to train")

    from brave6d.core.runtime import prepare_process

    prepare_process()
    try:
        return run(args)
    except BraveError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def run(args: argparse.Namespace) -> int:
    from brave6d.core.atomic import atomic_write_json
    from brave6d.core.layout import SceneDir
    from brave6d.core.progress import format_table
    from brave6d.evaluation.report.fidelity import fidelity_rows, fidelity_table, plot_fidelity
    from brave6d.evaluation.report.measurements import describe_machine, machine_info
    from brave6d.evaluation.report.sections.fidelity import CEILING_NOTE
    from brave6d.training import resolve_device
    from brave6d.training.holdout_eval import json_safe

    scene = SceneDir(args.scene_dir)
    if not scene.spec_path.is_file():
        raise DataError(f"{scene.spec_path}: no scene.yaml (is {scene.root} a scene directory?)")
    device = resolve_device(args.device)
    configs = configurations(args, scene, device)
    objects = max(1, len(configs[0]["bundle"].objects))
    sweep = FidelitySweep(distances_m=args.distances, views=args.views or math.ceil(VIEWS_PER_DISTANCE / objects),
                          holdout_per_level=args.holdout_per_level, seed=args.seed, device=str(device))
    measure(configs, scene, sweep)
    machine = machine_info(str(device))
    out: dict[str, Any] = {"scene": str(scene.root), "device": str(device), "machine": machine,
                           "sweep": {"distances_m": list(sweep.distances_m), "views": sweep.views,
                                     "holdout_per_level": sweep.holdout_per_level, "seed": sweep.seed},
                           "configurations": []}
    levers = []
    for c in configs:
        rows = fidelity_rows(c["points"])
        headers, lines = fidelity_table(rows)
        trained = (f"trained {cell(c['train_s'], 0, ' s')}, holdout {cell(c['holdout_psnr'], 2, ' dB')}"
                   if c["train_s"] is not None else "training time not recorded")
        print(f"\n{c['name']} ({c['mode']}, {trained}, {cell(c['gaussians'])} Gaussians)")
        print(format_table(headers, lines))
        levers.append([c["name"], cell(c["train_s"]), cell(c["holdout_psnr"], 2), cell(c["gaussians"]),
                       *(cell(min((r[k] for r in rows if math.isfinite(r[k])), default=math.nan), d)
                         for k, d in (("box_psnr", 1), ("box_psnr_ceiling", 1), ("within_5mm", 2), ("within_15mm", 2))),
                       cell(max((r["depth_median_mm"] for r in rows if math.isfinite(r["depth_median_mm"])),
                                default=math.nan), 1),
                       cell(max((abs(r["ar_gap"]) for r in rows if math.isfinite(r["ar_gap"])), default=math.nan), 2)])
        out["configurations"].append({k: v for k, v in c.items() if k not in ("bundle", "renderer")} | {"rows": rows})
    print(f"\n{CEILING_NOTE}")
    print("\nwhat each configuration costs and buys (worst distance):")
    print(format_table(["config", "train s", "holdout dB", "Gaussians", "box PSNR min", "box ceiling min", "within 5 mm min",
                        "within 15 mm min", "depth median max mm", "|AR gap| max"], levers))
    path = args.json or scene.splat_dir / "fidelity.json"
    atomic_write_json(path, json_safe(out))
    png, _ = plot_fidelity(path.with_suffix(".png"), [(c["name"], r["rows"]) for c, r in
                                                       zip(configs, out["configurations"])],
                           f"{scene.root.name}: splat against truth where agents look", describe_machine(machine),
                           f"{configs[0]['mode']} scene, {sweep.views} views per object and distance, seed {sweep.seed}")
    print(f"{path}\n{png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

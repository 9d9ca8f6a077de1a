"""Synthetic training split speed: images per second of ``brave6d synth`` on the demo dataset's
objects, at 640x480 and 320x240, with 1 and 2 worker processes (medians of several runs).

Each run renders ``--images`` images into a fresh folder (seed = run number, so runs differ) and
counts wall time from the first image to the last written file (worker start-up included: that is
what a user waits for). Prints one line per setting and the 2-worker speed-up.

    python benchmarks/synth.py [--spec data/demo/dataset.yaml] [--images 12] [--repeats 3]

``--check-images N`` measures instead what a resumed run spends checking the images already written
(:mod:`brave6d.core.png_check`): it renders N images at 640x480 once, then times each check over all of
them (one thread, files in the page cache; median of ``--repeats`` passes) and prints ms per image.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# this file is named like the package it measures: drop its own folder from the path, put the repo first
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
if str(ROOT / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(ROOT / "src"))

from brave6d.core.progress import format_table
from brave6d.synth import SynthOptions, synthesize
from brave6d.synth.limits import usable_cpus
from brave6d.core.png_check import CHECKS
from brave6d.synth.writer import image_problem

SIZES = ((640, 480), (320, 240))
WORKERS = (1, 2)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", type=Path, default=ROOT / "data" / "demo" / "dataset.yaml")
    ap.add_argument("--images", type=int, default=12, help="images per run")
    ap.add_argument("--repeats", type=int, default=3, help="runs per setting (the median is reported)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    ap.add_argument("--check-images", type=int, default=0, metavar="N",
                    help="time the resume checks over N images at 640x480 instead (module docstring)")
    args = ap.parse_args(argv)
    if args.check_images:
        return check_times(args.spec, args.check_images, args.repeats, args.json)
    rows, figures = [], {}
    for width, height in SIZES:
        for workers in WORKERS:
            rates = []
            for r in range(args.repeats):
                with tempfile.TemporaryDirectory(prefix="brave6d-bench-synth-") as tmp:
                    result = synthesize(args.spec, Path(tmp) / "out", SynthOptions(
                        images=args.images, seed=r, workers=workers, width=width, height=height))
                    rates.append(result.images_per_s)
            key = f"{width}x{height}_w{workers}"
            figures[key] = {"median_images_per_s": statistics.median(rates), "runs": rates}
            rows.append([f"{width}x{height}", workers, f"{statistics.median(rates):.2f}",
                         " ".join(f"{x:.2f}" for x in rates)])
    print(format_table(["size", "workers", "median images/s", "runs"], rows))
    for width, height in SIZES:
        one = figures[f"{width}x{height}_w1"]["median_images_per_s"]
        two = figures[f"{width}x{height}_w2"]["median_images_per_s"]
        print(f"{width}x{height}: 2 workers / 1 worker = {two / one:.2f}x")
    print(f"({args.images} images per run, {args.repeats} runs, {os.cpu_count()} CPU cores)")
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


def check_times(spec: Path, images: int, repeats: int, json_path: Path | None) -> int:
    """Render ``images`` images at 640x480, then time each resume check over them (module docstring)."""
    size = (640, 480)
    figures: dict[str, object] = {}
    with tempfile.TemporaryDirectory(prefix="brave6d-bench-synth-check-") as tmp:
        out = Path(tmp) / "out"
        synthesize(spec, out, SynthOptions(images=images, workers=min(2, usable_cpus()), width=size[0],
                                           height=size[1]))
        pngs = list((out / "train_pbr").rglob("*.png"))
        figures["split"] = {"images": images, "pngs": len(pngs), "mib": sum(p.stat().st_size for p in pngs) / 2 ** 20}
        rows = []
        for check in CHECKS:
            passes = []
            for _ in range(repeats + 1):  # the first pass warms the page cache and the imports
                start = time.perf_counter()
                problems = [p for i in range(images) if (p := image_problem(out, i, size, check)) is not None]
                passes.append((time.perf_counter() - start) / images * 1000.0)
                assert not problems, problems[0]
            ms = statistics.median(passes[1:])
            figures[check] = {"median_ms_per_image": ms, "passes_ms_per_image": passes[1:]}
            rows.append([check, f"{ms:.3f}", " ".join(f"{x:.3f}" for x in passes[1:])])
    print(format_table(["check", "median ms/image", "passes"], rows))
    split = figures["split"]
    print(f"({images} images of {size[0]}x{size[1]}, {split['pngs']} PNGs, {split['mib']:.1f} MiB; "  # type: ignore[index]
          f"one thread, warm page cache, {repeats} timed passes)")
    if json_path is not None:
        json_path.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

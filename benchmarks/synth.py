"""Synthetic training split speed: images per second of ``brave6d synth`` on the demo dataset's
objects, at 640x480 and 320x240, with 1 and 2 worker processes (medians of several runs).

Each run renders ``--images`` images into a fresh folder (seed = run number, so runs differ) and
counts wall time from the first image to the last written file (worker start-up included: that is
what a user waits for). Prints one line per setting and the 2-worker speed-up.

    python benchmarks/synth.py [--spec data/demo/dataset.yaml] [--images 12] [--repeats 3]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# this file is named like the package it measures: drop its own folder from the path, put the repo first
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from brave6d.progress import format_table
from synth import SynthOptions, synthesize

SIZES = ((640, 480), (320, 240))
WORKERS = (1, 2)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", type=Path, default=ROOT / "data" / "demo" / "dataset.yaml")
    ap.add_argument("--images", type=int, default=12, help="images per run")
    ap.add_argument("--repeats", type=int, default=3, help="runs per setting (the median is reported)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args(argv)
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


if __name__ == "__main__":
    sys.exit(main())

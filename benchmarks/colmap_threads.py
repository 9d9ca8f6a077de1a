"""COLMAP matching and triangulation with one thread against several: time and repeatability.

Extracts the scene's training images' features once, then, per stage asked for, repeats that stage
``--repeats`` times per configuration, interleaved (1 thread, N threads, 1, N, ...), and prints the
median seconds and how many different results each configuration produced:

- ``match``: matches and verifies the nearest-camera pairs into a fresh copy of the features'
  database; the result is a hash of the matches and verified geometries
  (``ColmapOptions.match_threads`` defaults to 1);
- ``triangulate``: triangulates one matched database with the poses fixed; the result is a hash
  of the points, their tracks and colours (the bundle adjustment is the multi-threaded part;
  ``ColmapOptions.triangulation_threads`` defaults to 1).

``--threads`` is N (-1: every core). More threads than cores make thread timing vary more, so rare
differences show sooner.

    python benchmarks/colmap_threads.py SCENE_DIR [--stage both] [--repeats 3] [--threads -1] [--json PATH]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sqlite3
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))


def model_digest(rec) -> str:  # type: ignore[no-untyped-def]
    """Hash of the triangulated points (position, colour, error, track) in id order."""
    h = hashlib.sha256()
    points = rec.points3D
    for pid in sorted(rec.point3D_ids()):
        p = points[pid]
        h.update(repr((p.xyz.tolist(), p.color.tolist(), p.error,
                       sorted((e.image_id, e.point2D_idx) for e in p.track.elements))).encode())
    return h.hexdigest()[:16]


def matches_digest(db_path: Path) -> str:
    """Hash of a database's matches and verified two-view geometries, in pair order."""
    h = hashlib.sha256()
    with sqlite3.connect(db_path) as db:
        for table in ("matches", "two_view_geometries"):
            for row in db.execute(f"SELECT * FROM {table} ORDER BY pair_id"):
                h.update(repr(row).encode())
    return h.hexdigest()[:16]


def _compare(stage: str, configs: dict[str, int], repeats: int, run_once) -> dict[str, Any]:  # type: ignore[no-untyped-def]
    """Run ``run_once(threads, repeat)`` -> digest interleaved; median seconds and distinct digests."""
    seconds: dict[str, list[float]] = {name: [] for name in configs}
    digests: dict[str, dict[str, int]] = {name: {} for name in configs}
    for r in range(repeats):
        for name, threads in configs.items():
            t0 = time.perf_counter()
            digest = run_once(threads, r)
            seconds[name].append(time.perf_counter() - t0)
            digests[name][digest] = digests[name].get(digest, 0) + 1
            print(f"{stage} repeat {r + 1} {name}: {seconds[name][-1]:.2f} s, {digest}", flush=True)
    result = {name: {"median_s": statistics.median(seconds[name]), "seconds": seconds[name],
                     "different_results": len(digests[name]), "results": digests[name]} for name in configs}
    for name in configs:
        print(f"{stage}, {name}: median {result[name]['median_s']:.2f} s over {repeats}, "
              f"{result[name]['different_results']} different result(s) {digests[name]}", flush=True)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene_dir", type=Path)
    parser.add_argument("--stage", choices=("match", "triangulate", "both"), default="both")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=-1, help="the several-threads configuration (-1: every core)")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args(argv)

    import pycolmap

    from brave6d.core.layout import SceneDir
    from brave6d.training import load_scene
    from brave6d.training.colmap_init import ColmapOptions, extract_features, match_pairs, triangulate_database

    pycolmap.logging.minloglevel = 2  # COLMAP's per-image log lines would bury the table
    data = load_scene(SceneDir(args.scene_dir), 2)
    if data.undistorted_root is None:
        raise SystemExit(f"{args.scene_dir}: no undistorted image files to match")
    camera = data.full_camera or data.camera
    images = [(Path(v.rgb_path).name, v.base_T_cam) for v in data.train]
    image_dir = data.undistorted_root / "rgb"
    several = "every core" if args.threads == -1 else f"{args.threads} threads"
    configs = {"1 thread": 1, several: args.threads}
    result: dict[str, Any] = {"images": len(images), "threads": args.threads, "repeats": args.repeats}
    with tempfile.TemporaryDirectory(prefix="colmap-threads-") as tmp:
        work = Path(tmp)
        features = work / "features.db"
        t0 = time.perf_counter()
        extract_features(features, image_dir, camera, [n for n, _ in images])
        result["extract_s"] = time.perf_counter() - t0
        matched = work / "matched.db"
        shutil.copy(features, matched)
        result["pairs"] = match_pairs(matched, images, work / "pairs.txt")

        def match_once(threads: int, r: int) -> str:
            db = work / f"match-{r}-{threads}.db"
            shutil.copy(features, db)
            match_pairs(db, images, work / "pairs.txt", ColmapOptions(match_threads=threads))
            digest = matches_digest(db)
            db.unlink()
            return digest

        def triangulate_once(threads: int, r: int) -> str:
            out = work / f"tri-{r}-{threads}"
            rec = triangulate_database(matched, image_dir, images, out, ColmapOptions(triangulation_threads=threads))
            shutil.rmtree(out, ignore_errors=True)
            return f"{model_digest(rec)} ({rec.num_points3D()} points)"

        if args.stage in ("match", "both"):
            result["match"] = _compare("match", configs, args.repeats, match_once)
        if args.stage in ("triangulate", "both"):
            result["triangulate"] = _compare("triangulate", configs, args.repeats, triangulate_once)
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

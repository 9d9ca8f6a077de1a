"""COLMAP triangulation (fixed poses) with one thread against all threads: time and repeatability.

Extracts, matches and triangulates the scene's training images once (``triangulate``), then triangulates the
same database ``--repeats`` times per configuration, interleaved (1 thread, all threads, 1, all, ...),
and prints the median seconds and how many different point sets each configuration produced (a
hash of the points, their tracks and colours). The bundle adjustment inside the triangulation is
the only multi-threaded part; ``ColmapOptions.triangulation_threads`` defaults to 1.

    python benchmarks/colmap_threads.py SCENE_DIR [--repeats 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene_dir", type=Path)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args(argv)

    from brave6d.core.layout import SceneDir
    from brave6d.training import load_scene
    from brave6d.training.colmap_init import ColmapOptions, triangulate, triangulate_database

    data = load_scene(SceneDir(args.scene_dir), 2)
    if data.undistorted_root is None:
        raise SystemExit(f"{args.scene_dir}: no undistorted image files to triangulate")
    camera = data.full_camera or data.camera
    images = [(Path(v.rgb_path).name, v.base_T_cam) for v in data.train]
    image_dir = data.undistorted_root / "rgb"
    configs = {"1 thread": 1, "all threads": -1}
    seconds: dict[str, list[float]] = {name: [] for name in configs}
    digests: dict[str, set[str]] = {name: set() for name in configs}
    with tempfile.TemporaryDirectory(prefix="colmap-threads-") as work:
        _, timings = triangulate(image_dir, camera, images, Path(work), ColmapOptions())
        db_path, n_pairs = Path(work) / "database.db", timings["pairs"]
        for r in range(args.repeats):
            for name, threads in configs.items():
                t0 = time.perf_counter()
                rec = triangulate_database(db_path, image_dir, images, Path(work) / f"tri-{r}-{threads}",
                                           ColmapOptions(triangulation_threads=threads))
                seconds[name].append(time.perf_counter() - t0)
                digests[name].add(model_digest(rec))
                print(f"repeat {r + 1} {name}: {seconds[name][-1]:.1f} s, {rec.num_points3D()} points, "
                      f"{model_digest(rec)}", flush=True)
    result = {name: {"median_s": statistics.median(seconds[name]), "seconds": seconds[name],
                     "different_results": len(digests[name])} for name in configs}
    result["images"] = len(images)
    result["pairs"] = n_pairs
    for name in configs:
        print(f"{name}: median {result[name]['median_s']:.1f} s over {args.repeats}, "
              f"{result[name]['different_results']} different result(s)")
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

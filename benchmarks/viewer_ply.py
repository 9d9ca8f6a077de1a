"""Viewer PLY benchmark (issue 45): how other 3DGS viewers draw a bundle's splat against the server.

Renders a bundle's splat at 10 / 20 / 30 / 50 cm from its start target (3 views per distance, 45 deg
elevation) as served, then as a standard viewer draws today's ``splat.ply`` (``filter_3d`` ignored,
classic rasterizer) and the viewer PLY (the 3D filter baked in; classic and antialiased rasterizer),
and prints each one's PSNR against the served render (:mod:`brave6d.serve.viewer_check`).

    python benchmarks/viewer_ply.py /tmp/demo45/scene/bundle           # ~3 min on 2 cores
    python benchmarks/viewer_ply.py BUNDLE --size 320 200 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see benchmarks/rasterizer.py

from brave6d.serve import load_bundle  # noqa: E402
from brave6d.serve.viewer_check import VIEWER_WAYS, compare_viewer_renders, orbit_poses, per_distance  # noqa: E402
from brave6d.training import read_ply  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle", type=Path, help="a bundle folder (brave6d export)")
    ap.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="render size (default: the bundle's)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args(argv)
    bundle = load_bundle(args.bundle)
    camera = bundle.camera if args.size is None else bundle.camera.scaled(*args.size)
    target = tuple(float(x) for x in bundle.start.get("target", (0.0, 0.0, 0.0)))
    splat = read_ply(bundle.splat_path)
    t0 = time.perf_counter()
    scores = compare_viewer_renders(splat, camera, orbit_poses(target), bundle.render.antialiasing, args.device)
    print(f"{bundle.name}: {splat.num_gaussians} Gaussians, {camera.width}x{camera.height}, served as "
          f"{bundle.render.antialiasing}; PSNR (dB) against the served render, {time.perf_counter() - t0:.0f} s")
    print(f"{'distance':>9} " + " ".join(f"{name:>18}" for name in VIEWER_WAYS))
    table = per_distance(scores)
    for d, row in table.items():
        views = {name: [s.psnr_db[name] for s in scores if s.distance_m == d] for name in VIEWER_WAYS}
        print(f"{d * 100:7.0f}cm " + " ".join(f"{row[n]:6.1f} (min {min(views[n]):5.1f})" for n in VIEWER_WAYS))
    if args.json:
        args.json.write_text(json.dumps({"bundle": bundle.name, "width": camera.width, "height": camera.height,
                                         "served": bundle.render.antialiasing,
                                         "views": [{"distance_m": s.distance_m, "psnr_db": s.psnr_db} for s in scores],
                                         "mean_psnr_db": {str(d): r for d, r in table.items()}}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

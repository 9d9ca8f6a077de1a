"""Benchmark the render server: median render latency at 320x240 and 640x480.

Uses the demo bundle (``runs/demo/scene/bundle``) when present, else a synthetic bundle built in
a temporary folder with a realistic number of Gaussians (``--gaussians``, default 150k, the CPU
training preset's cap; SH degree 2 like that preset; 30 % of them semi-transparent blobs above
the table so that pixels see many overlapping Gaussians, as in a trained scene). For each image size it renders ``--views``
seeded views on capture-like rings around the first object and reports the median and p90 of

* ``render``: the rasterizer call alone (what the acceptance criterion names);
* ``observe``: render + ground truth + visible fractions (Open3D ray casting);
* ``request``: one HTTP ``set_pose`` round trip on loopback (FastAPI + uvicorn), PNG RGB and
  float32 depth encoded, i.e. what a client waits for.

    python benchmarks/serve.py [--bundle DIR] [--device auto|cpu|cuda] [--views N] [--json out.json] [--quick]

Like ``brave6d serve``, it sets ``OMP_WAIT_POLICY=PASSIVE`` unless the environment sets it
(``OMP_WAIT_POLICY=ACTIVE python benchmarks/serve.py`` measures the spinning default).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))
# as `brave6d serve` does (brave6d.serve.cli.quiet_openmp): OpenMP threads sleep while they wait
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from brave6d.core.transforms import look_at

DEMO_BUNDLE = REPO / "runs" / "demo" / "scene" / "bundle"
TARGETS = {"320x240": 150.0, "640x480": 600.0}  # CPU acceptance (median render ms)


def ring_views(bundle: Any, scene: Any, n: int, seed: int = 0) -> list[np.ndarray]:
    """Free views at capture distances/elevations around the first object (seeded)."""
    rng = np.random.default_rng(seed)
    centre = scene.centres_world[0] if scene.centres_world else np.asarray(bundle.start.get("target", (0, 0, 0)))
    dists = bundle.start.get("distances_m") or [0.2, 0.3, 0.4, 0.5]
    out: list[np.ndarray] = []
    while len(out) < n:
        d = float(rng.choice(dists))
        el = math.radians(rng.uniform(30, 80))
        az = rng.uniform(-math.pi, math.pi)
        eye = centre + d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        T = look_at(eye, centre)
        if bundle.world.check(T) is None:
            out.append(T)
    return out


def stats(values: list[float]) -> dict[str, float]:
    v = sorted(values)
    return {"median": statistics.median(v), "p90": float(np.percentile(v, 90)), "min": v[0], "max": v[-1],
            "n": len(v)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bundle", type=Path, default=None, help="bundle folder (default: the demo's, else synthetic)")
    parser.add_argument("--gaussians", type=int, default=150_000, help="synthetic bundle size (default 150000)")
    parser.add_argument("--volume-fraction", type=float, default=0.3,
                        help="synthetic bundle: share of semi-transparent blobs above the table (default 0.3)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--views", type=int, default=15, help="views per image size (default 15)")
    parser.add_argument("--sizes", nargs="*", default=["320x240", "640x480"])
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--quick", action="store_true", help="5 views, 30k Gaussians (smoke run)")
    parser.add_argument("--no-http", action="store_true", help="skip the HTTP round-trip measurement")
    args = parser.parse_args(argv)
    if args.quick:
        args.views, args.gaussians = 5, 30_000

    import torch

    from brave6d.serve.bundle import load_bundle
    from brave6d.serve.episodes import SceneServer

    tmp = None
    if args.bundle is not None:
        bundle_dir, source = args.bundle, "given"
    elif (DEMO_BUNDLE / "manifest.json").is_file():
        bundle_dir, source = DEMO_BUNDLE, "demo"
    else:
        from brave6d.serve.toy_scene import make_synthetic_bundle

        tmp = tempfile.TemporaryDirectory(prefix="brave6d_bench_")
        print(f"no demo bundle at {DEMO_BUNDLE}: building a synthetic one with {args.gaussians} Gaussians ...",
              flush=True)
        bundle_dir = make_synthetic_bundle(Path(tmp.name) / "scene", n_gaussians=args.gaussians, sh_degree=2,
                                           width=640, height=480, volume_fraction=args.volume_fraction)
        source = f"synthetic ({args.gaussians} Gaussians requested, {args.volume_fraction:.0%} in fuzzy blobs)"
    t0 = time.perf_counter()
    bundle = load_bundle(bundle_dir)
    scene = SceneServer(bundle, args.device)
    load_s = time.perf_counter() - t0
    results: dict[str, Any] = {
        "bundle": str(bundle_dir), "source": source, "gaussians": scene.renderer.num_gaussians,
        "sh_degree": scene.renderer.sh_degree, "device": scene.device, "load_s": load_s,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "machine": {"python": platform.python_version(), "torch": torch.__version__,
                    "cpu_threads": torch.get_num_threads(),
                    "gpu": torch.cuda.get_device_name(0) if scene.device == "cuda" else None},
        "sizes": {},
    }
    views = ring_views(bundle, scene, args.views)
    for size in args.sizes:
        w, h = (int(x) for x in size.lower().split("x"))
        camera = bundle.camera.scaled(w, h)
        for T in views[:2]:  # warm-up (compiled kernels, caches)
            scene.observe(T, camera, 0)
        render, observe, drawn = [], [], []
        for T in views:
            obs = scene.observe(T, camera, 0)
            render.append(obs.timings_ms["render"])
            observe.append(obs.timings_ms["observe"])
        for T in views:
            drawn.append(scene.renderer.render(T, camera).gaussians_drawn)
        results["sizes"][size] = {"render_ms": stats(render), "observe_ms": stats(observe),
                                  "gaussians_drawn_median": float(np.median(drawn))}
    if not args.no_http:
        from brave6d.serve.app import create_app
        from brave6d.serve.client import BraveClient
        from brave6d.serve.runner import ServerThread

        app = create_app(bundle, scene=scene, warm_up=False)
        with ServerThread(app) as server, BraveClient(server.url) as client:
            for size in args.sizes:
                w, h = (int(x) for x in size.lower().split("x"))
                client.reset(width=w, height=h, start=views[0])
                client.set_pose(views[1])
                times, server_total = [], []
                for T in views:
                    t = time.perf_counter()
                    step = client.set_pose(T)
                    times.append((time.perf_counter() - t) * 1000.0)
                    server_total.append(step.timings_ms["total"])
                client.close()
                results["sizes"][size]["request_ms"] = stats(times)
                results["sizes"][size]["server_total_ms"] = stats(server_total)

    print(f"\nbundle: {results['source']}, {results['gaussians']} Gaussians (SH degree {results['sh_degree']}), "
          f"device {results['device']}, {results['machine']['cpu_threads']} CPU threads, "
          f"OMP_WAIT_POLICY={results['omp_wait_policy']}")
    print(f"{'size':>9} | {'render ms (median / p90)':>25} | {'observe ms':>11} | {'request ms':>11} | target")
    ok = True
    for size, r in results["sizes"].items():
        target = TARGETS.get(size) if results["device"] == "cpu" else None
        med = r["render_ms"]["median"]
        verdict = "" if target is None else (f"< {target:g} ms: " + ("PASS" if med < target else "FAIL"))
        ok &= target is None or med < target
        req = r.get("request_ms", {}).get("median", float("nan"))
        print(f"{size:>9} | {med:>12.1f} / {r['render_ms']['p90']:>10.1f} | {r['observe_ms']['median']:>11.1f} | "
              f"{req:>11.1f} | {verdict}")
    results["pass"] = ok
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2))
        print(f"results written to {args.json}")
    if tmp is not None:
        tmp.cleanup()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

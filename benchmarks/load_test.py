"""Load test of the render server on loopback: N concurrent clients x M requests each.

Each client runs its own episode (reset, then alternating ``set_pose`` to seeded free views and
small camera-frame ``move``s, full observations: PNG RGB + float32 depth; every 10th request a
``set_pose`` into a collision box, which must be *refused*, not fail), then closes it.
An error is a failed request (HTTP 4xx/5xx, a broken connection, a timeout) or a wrong answer
(a refused move that changed the pose or the adjustment count, or episodes mixed up between
clients); refusals are expected answers. Reports latency percentiles (p50/p90/p99/max),
throughput and errors; the exit status is 1 when there were errors.

Targets a running server (``--url``) or starts one in-process on a free loopback port
(``--bundle``, default: the demo bundle when present, else a synthetic one). The run is
bounded by ``--max-seconds``.

    python benchmarks/load_test.py [--clients 8] [--requests 50] [--size 320x240] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import threading
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


def _views(info: dict[str, Any], rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Seeded free views around the first object, from the bundle description (GET /bundle)."""
    from brave6d.serve.geometry import CollisionWorld, OrientedBox, Workspace

    coll = info["collision"]
    world = CollisionWorld(tuple(OrientedBox.from_json(b) for b in coll["boxes"]), Workspace.from_json(coll["workspace"]),
                           coll["camera_radius"])
    centre = np.asarray(info["objects"][0]["world_T_obj"])[:3, 3] if info["objects"] else np.asarray(
        info["start"].get("target", (0, 0, 0)))
    dists = info["start"].get("distances_m") or [0.2, 0.3, 0.4, 0.5]
    out: list[np.ndarray] = []
    while len(out) < n:
        d = float(rng.uniform(min(dists), max(dists)))
        el, az = math.radians(rng.uniform(30, 80)), rng.uniform(-math.pi, math.pi)
        T = look_at(centre + d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]),
                    centre)
        if world.check(T) is None:
            out.append(T)
    return out


def _blocked_pose(info: dict[str, Any]) -> np.ndarray | None:
    """A pose inside the first collision box that lies in the workspace, if any (else below it)."""
    T = np.eye(4)
    boxes = info["collision"]["boxes"]
    if boxes:
        T[:3, 3] = np.asarray(boxes[-1]["world_T_box"])[:3, 3]
    else:
        T[:3, 3] = np.asarray(info["collision"]["workspace"]["min"]) - 0.1
    return T


def run_load_test(url: str, clients: int = 8, requests: int = 50, width: int = 320, height: int = 240,
                  seed: int = 0, max_seconds: float = 600.0, timeout: float = 120.0) -> dict[str, Any]:
    """Run the load test against ``url``; returns latencies (ms), throughput and errors."""
    from brave6d.serve.client import BraveClient

    with BraveClient(url, timeout=timeout) as probe:
        info = probe.bundle()
    blocked = _blocked_pose(info)
    deadline = time.monotonic() + max_seconds
    latencies: list[list[float]] = [[] for _ in range(clients)]
    errors: list[str] = []
    episodes: list[str | None] = [None] * clients
    lock = threading.Lock()
    barrier = threading.Barrier(clients)

    def worker(k: int) -> None:
        rng = np.random.default_rng(seed + k)
        views = _views(info, rng, 8)
        try:
            barrier.wait(timeout=60)
        except threading.BrokenBarrierError:
            pass
        with BraveClient(url, timeout=timeout) as client:
            try:
                t = time.perf_counter()
                step = client.reset(width=width, height=height, start=views[0])
                latencies[k].append((time.perf_counter() - t) * 1000.0)
                episodes[k] = step.episode_id
                adjustments = 0
                for i in range(1, requests):
                    if time.monotonic() > deadline:
                        with lock:
                            errors.append(f"client {k}: stopped at request {i}: --max-seconds reached")
                        break
                    t = time.perf_counter()
                    if i % 10 == 5:
                        pose_before = step.observation.world_T_cam
                        step = client.set_pose(blocked)
                        latencies[k].append((time.perf_counter() - t) * 1000.0)
                        if step.accepted or step.adjustments != adjustments or not np.array_equal(
                                step.observation.world_T_cam, pose_before):
                            with lock:
                                errors.append(f"client {k}: request {i}: a blocked pose was not refused cleanly")
                        continue
                    if i % 2:
                        step = client.set_pose(views[i % len(views)])
                    else:
                        step = client.move(linear=(0.0, 0.0, 0.02), angular=(0.0, 0.1, 0.0), duration=0.5)
                    latencies[k].append((time.perf_counter() - t) * 1000.0)
                    if step.episode_id != episodes[k]:
                        with lock:
                            errors.append(f"client {k}: got episode {step.episode_id}, expected {episodes[k]}")
                    if step.accepted:
                        adjustments += 1
                    if step.adjustments != adjustments:
                        with lock:
                            errors.append(f"client {k}: adjustments {step.adjustments}, expected {adjustments}")
                    if step.observation.rgb is None or step.observation.rgb.shape != (height, width, 3):
                        with lock:
                            errors.append(f"client {k}: request {i}: bad image")
                client.close()
            except Exception as exc:  # noqa: BLE001 - every failure counts (ServerError, OSError, ...)
                with lock:
                    errors.append(f"client {k}: {type(exc).__name__}: {exc}")

    t0 = time.perf_counter()
    threads = [threading.Thread(target=worker, args=(k,), name=f"load-{k}") for k in range(clients)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t0
    flat = np.asarray([x for lat in latencies for x in lat])
    pct = (lambda q: float(np.percentile(flat, q))) if len(flat) else (lambda q: float("nan"))
    if len({e for e in episodes if e}) != sum(1 for e in episodes if e):
        errors.append("two clients shared an episode")
    return {"url": url, "clients": clients, "requests_per_client": requests, "size": f"{width}x{height}",
            "requests": len(flat), "errors": len(errors), "error_messages": errors[:20],
            "wall_s": wall, "throughput_rps": len(flat) / wall if wall > 0 else 0.0,
            "latency_ms": {"p50": pct(50), "p90": pct(90), "p99": pct(99), "max": float(flat.max()) if len(flat) else
                           float("nan"), "mean": float(flat.mean()) if len(flat) else float("nan")}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default=None, help="a running server (default: start one in-process)")
    parser.add_argument("--bundle", type=Path, default=None, help="bundle to serve (default: demo, else synthetic)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--requests", type=int, default=50)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--max-seconds", type=float, default=600.0)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if not (1 <= args.clients <= 64 and 1 <= args.requests <= 1000):
        parser.error("--clients must be in 1..64 and --requests in 1..1000 (loopback load test)")
    w, h = (int(x) for x in args.size.lower().split("x"))
    tmp = None
    server = None
    url = args.url
    if url is None:
        from brave6d.serve.app import ServerLimits, create_app
        from brave6d.serve.runner import ServerThread

        bundle_dir = args.bundle
        if bundle_dir is None and (DEMO_BUNDLE / "manifest.json").is_file():
            bundle_dir = DEMO_BUNDLE
        if bundle_dir is None:
            from brave6d.serve.toy_scene import make_synthetic_bundle

            tmp = tempfile.TemporaryDirectory(prefix="brave6d_load_")
            bundle_dir = make_synthetic_bundle(Path(tmp.name) / "scene", n_gaussians=150_000, sh_degree=2,
                                               volume_fraction=0.3)
        limits = ServerLimits(request_timeout_s=min(3600.0, max(60.0, args.max_seconds)),  # the bound of ServerLimits
                              max_episodes=max(32, 2 * args.clients))
        app = create_app(bundle_dir, device=args.device, limits=limits,
                         log_dir=Path(tmp.name) / "episodes" if tmp else None)
        server = ServerThread(app).start()
        url = server.url
    try:
        result = run_load_test(url, args.clients, args.requests, w, h, max_seconds=args.max_seconds)
    finally:
        if server is not None:
            server.stop()
        if tmp is not None:
            tmp.cleanup()
    lat = result["latency_ms"]
    print(f"{result['clients']} clients x {result['requests_per_client']} requests at {result['size']} on {url}: "
          f"{result['requests']} requests in {result['wall_s']:.1f} s ({result['throughput_rps']:.1f} req/s), "
          f"errors {result['errors']}")
    print(f"latency ms: p50 {lat['p50']:.0f}  p90 {lat['p90']:.0f}  p99 {lat['p99']:.0f}  max {lat['max']:.0f}")
    for msg in result["error_messages"]:
        print("  error:", msg)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return 1 if result["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())

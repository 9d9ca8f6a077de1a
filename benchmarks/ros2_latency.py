"""Benchmark the ROS 2 interface: latency per step over ROS 2 (DDS) vs over HTTP, same bundle.

Both servers run as their own processes, as an agent would meet them: ``brave6d ros2 BUNDLE``
(DDS on loopback, a random domain id) and ``brave6d serve BUNDLE`` (HTTP on 127.0.0.1). For each of
``--views`` seeded free views (capture-like rings around the first object, as
``benchmarks/serve.py``), one ``set_pose`` is sent over each interface, alternating, and timed

* ROS 2: ``geometry_msgs/PoseStamped`` published on ``/brave6d_sim/set_pose`` -> its status, RGB
  and depth images, both camera infos and ``/tf`` received and decoded (``Ros2Agent.set_pose``);
* HTTP: ``POST /episodes/{id}/set_pose`` -> the reply received and decoded (PNG RGB + float32
  depth, ``BraveClient.set_pose``).

Both include the server's render (the same renderer on the same device); the difference is the
transport. Prints median and p90 per interface.

    python benchmarks/ros2_latency.py [--bundle DIR] [--size 640x480] [--views 30] [--device cpu] [--json out.json]

Uses the demo bundle (``runs/demo/scene/bundle``) when present, else a synthetic one
(``--gaussians``, default 50k).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # first: this folder's serve.py must not shadow the serve package
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from benchmarks.serve import ring_views  # noqa: E402

DEMO_BUNDLE = REPO / "runs" / "demo" / "scene" / "bundle"


def stats(values: list[float]) -> dict[str, float]:
    v = sorted(values)
    return {"median": statistics.median(v), "p90": float(np.percentile(v, 90)), "min": v[0], "max": v[-1],
            "n": len(v)}


def start(cmd: list[str], ready: str, timeout_s: float = 300.0) -> tuple[subprocess.Popen, str]:
    """Start a ``brave6d`` command; wait for its line starting with ``ready``; (process, that line)."""
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.Popen([sys.executable, "-m", "brave6d.cli", *cmd], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + timeout_s
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"{cmd[0]} exited with status {proc.wait()}")
        if line.startswith(ready):
            return proc, line.strip()
    proc.kill()
    raise RuntimeError(f"{cmd[0]} did not start within {timeout_s:g} s")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bundle", type=Path, default=None, help="bundle folder (default: the demo's, else synthetic)")
    parser.add_argument("--gaussians", type=int, default=50_000, help="synthetic bundle size (default 50000)")
    parser.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--views", type=int, default=30, help="timed steps per interface (default 30)")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split("x"))

    from ros_interface.ros2.agent import Ros2Agent
    from ros_interface.ros2.dds import DdsDomain
    from serve.bundle import load_bundle
    from serve.client import BraveClient
    from serve.episodes import SceneServer

    tmp = tempfile.TemporaryDirectory(prefix="brave6d_ros2_bench_")
    if args.bundle is not None:
        bundle_dir, source = args.bundle, "given"
    elif (DEMO_BUNDLE / "manifest.json").is_file():
        bundle_dir, source = DEMO_BUNDLE, "demo"
    else:
        from serve.synthetic import make_synthetic_bundle

        print(f"no demo bundle at {DEMO_BUNDLE}: building a synthetic one with {args.gaussians} Gaussians ...",
              flush=True)
        bundle_dir = make_synthetic_bundle(Path(tmp.name) / "scene", n_gaussians=args.gaussians, sh_degree=2,
                                           width=w, height=h, volume_fraction=0.3)
        source = f"synthetic ({args.gaussians} Gaussians requested)"
    bundle = load_bundle(bundle_dir)
    views = ring_views(bundle, SceneServer(bundle, "cpu", visibility=False), args.views + 2, seed=1)

    domain_id = random.randrange(100, 230)
    logs = Path(tmp.name) / "episodes"
    common = ["--device", args.device, "--log-dir", str(logs)]
    ros, ros_line = start(["ros2", str(bundle_dir), "--domain-id", str(domain_id), "--width", str(w), "--height",
                           str(h), *common], "brave6d ros2:")
    http, http_line = start(["serve", str(bundle_dir), "--port", "0", *common], "brave6d serve:")
    url = re.search(r"http://[^\s]+", http_line).group(0)  # type: ignore[union-attr]
    results: dict[str, Any] = {"bundle": str(bundle_dir), "source": source, "size": f"{w}x{h}",
                               "device": args.device, "views": args.views, "domain_id": domain_id,
                               "python": platform.python_version(), "omp_wait_policy": os.environ["OMP_WAIT_POLICY"]}
    try:
        with DdsDomain(domain_id) as dds, BraveClient(url) as client:
            agent = Ros2Agent(dds, timeout_s=120)
            agent.wait_until_connected(timeout_s=120)
            agent.reset(start=views[0])
            client.reset(width=w, height=h, start=views[0])
            agent.set_pose(views[1])  # warm-up: compiled kernels, DDS fragments, HTTP connection
            client.set_pose(views[1])
            ros_ms, http_ms = [], []
            for T in views[2:]:
                t = time.perf_counter()
                obs = agent.set_pose(T)
                ros_ms.append((time.perf_counter() - t) * 1000.0)
                t = time.perf_counter()
                step = client.set_pose(T)
                http_ms.append((time.perf_counter() - t) * 1000.0)
                assert obs.rgb.shape == (h, w, 3) and step.observation.rgb is not None
            agent.close()
            client.close()
    finally:
        for p in (ros, http):
            p.terminate()
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
    results["ros2_ms"], results["http_ms"] = stats(ros_ms), stats(http_ms)
    results["servers"] = {"ros2": ros_line, "http": http_line}
    print(f"\n{results['source']}, {w}x{h}, device {args.device}, {args.views} steps per interface")
    print(f"{'interface':>10} | {'median ms':>9} | {'p90 ms':>7} | {'min':>6} | {'max':>6}")
    for name in ("ros2", "http"):
        s = results[f"{name}_ms"]
        print(f"{name:>10} | {s['median']:>9.1f} | {s['p90']:>7.1f} | {s['min']:>6.1f} | {s['max']:>6.1f}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2))
        print(f"results written to {args.json}")
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Clients that never read their replies (issue #44 class 4): what they cost the render server.

Starts ``brave6d serve`` on a synthetic bundle on a free loopback port (a process of its own, so that
its resident memory is the server's alone), opens one episode at the largest image size, then opens
``--connections`` connections from 127.0.0.2, each pipelining ``--requests`` GETs of the episode's
``observation.npz`` (about 8.6 MB each at 1280 x 960) and never reading. Meanwhile a normal client
from 127.0.0.1 times small ``set_pose`` requests of its own episode. Prints the server's resident
memory before, its peak while the clients hold their connections, how many connections the server
closed, and how soon after the clients close theirs its memory is back within 50 MB of the start
(at most ``--after-s`` seconds); the normal client's
median latency before and during. The run is bounded by its arguments (at most 256 connections,
a few minutes).

    python benchmarks/non_reading_clients.py [--connections 64] [--requests 20] [--hold-s 20] [--after-s 30]
        [--json out.json] [-- SERVER_FLAGS...]

Exit status 1 when the acceptance of issue #44 fails: growth over 200 MB, memory not back within
200 MB of the start after the clients close, or the normal client's median latency over 2x.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import select
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))

from brave6d.core.transforms import look_at

PEER = "127.0.0.2"  # Linux routes all of 127/8 to loopback: the non-reading clients' own address
FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
GROWTH_LIMIT_MB = 200.0
LATENCY_RATIO_LIMIT = 2.0
RETURNED_MB = 100.0  # memory counts as returned once the growth is back within this (half the limit; allocator arenas of the 64 connections keep ~50 MB, the bug kept 600+)


def rss_mb(pid: int) -> float:
    """Resident memory of process ``pid`` (MB)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def start_server(bundle: Path, log_dir: Path, flags: list[str], stderr: Path | None = None
                 ) -> tuple[subprocess.Popen[str], str]:
    """``brave6d serve bundle`` on a free loopback port, its standard error to ``stderr`` (None: dropped);
    the process and its URL (also benchmarks/hostile_load.py's server)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO / "src"), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.Popen([sys.executable, "-m", "brave6d.cli", "serve", str(bundle), "--port", "0", "--device",
                             "cpu", "--log-dir", str(log_dir), *flags], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL if stderr is None else stderr.open("w"), text=True)
    banner = proc.stdout.readline() if proc.stdout else ""
    match = re.search(r"on http://(127\.0\.0\.1:\d+)", banner)
    if not match:
        proc.kill()
        log = stderr.read_text()[-2000:] if stderr is not None else ""
        raise RuntimeError(f"the server did not start: {banner!r} {log}")
    return proc, f"http://{match.group(1)}"


def new_episode(client: httpx.Client, width: int, height: int) -> str:
    r = client.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, "width": width, "height": height})
    r.raise_for_status()
    return str(r.json()["episode_id"])


def latencies(client: httpx.Client, episode: str, seconds: float, stop: threading.Event | None = None) -> list[float]:
    """Seconds per ``set_pose`` (no images) of ``episode``, for ``seconds`` or until ``stop``."""
    out: list[float] = []
    body = {"pose": {"world_T_cam": FREE.tolist()}, "rgb": "none", "depth": "none"}
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not (stop is not None and stop.is_set()):
        t0 = time.perf_counter()
        client.post(f"/episodes/{episode}/set_pose", json=body).raise_for_status()
        out.append(time.perf_counter() - t0)
        time.sleep(0.05)
    return out


def closed_by_server(s: socket.socket) -> bool:
    """Whether the server closed or reset ``s`` (without reading what it sent)."""
    p = select.poll()
    p.register(s, select.POLLRDHUP | select.POLLERR | select.POLLHUP)
    return any(ev & (select.POLLRDHUP | select.POLLERR | select.POLLHUP) for _, ev in p.poll(0))


def non_reading(address: tuple[str, int], episode: str, requests: int) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind((PEER, 0))
    s.settimeout(30)
    s.connect(address)
    req = f"GET /episodes/{episode}/observation.npz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode()
    s.sendall(req * requests)
    return s


def measure(connections: int = 64, requests: int = 20, hold_s: float = 20.0, after_s: float = 30.0,
            width: int = 1280, height: int = 960, flags: list[str] | None = None,
            work: Path | None = None) -> dict[str, Any]:
    """Run the scenario of the module docstring; the figures as a dict (MB, seconds, counts)."""
    from brave6d.serve.toy_scene import make_synthetic_bundle

    connections = min(connections, 256)
    with tempfile.TemporaryDirectory(prefix="brave6d-nonreading-") as tmp:
        root = Path(work) if work is not None else Path(tmp)
        bundle = make_synthetic_bundle(root / "scene", n_gaussians=2000, n_views=4)
        proc, url = start_server(bundle, root / "episodes", list(flags or []))
        try:
            host, port = url.rsplit("//", 1)[1].split(":")
            with httpx.Client(base_url=url, timeout=120) as c:
                big = new_episode(c, width, height)
                small = new_episode(c, 64, 48)
                latencies(c, small, 1.0)  # warm up
                before_lat = latencies(c, small, 3.0)
                rss0 = rss_mb(proc.pid)
                socks = [non_reading((host, int(port)), big, requests) for _ in range(connections)]
                stop = threading.Event()
                during: list[float] = []
                timer = threading.Thread(target=lambda: during.extend(latencies(c, small, hold_s, stop)), daemon=True)
                timer.start()
                peak, t0 = rss0, time.monotonic()
                while time.monotonic() - t0 < hold_s:
                    peak = max(peak, rss_mb(proc.pid))
                    time.sleep(0.2)
                stop.set()
                timer.join()
                closed = sum(closed_by_server(s) for s in socks)
                rss_held = rss_mb(proc.pid)
                for s in socks:
                    s.close()
                t1 = time.monotonic()
                after, returned_s = rss_mb(proc.pid), None
                while time.monotonic() - t1 < after_s:
                    after = rss_mb(proc.pid)
                    if after - rss0 <= RETURNED_MB and returned_s is None:
                        returned_s = time.monotonic() - t1
                        break
                    time.sleep(0.5)
                alive = c.get("/health").status_code == 200
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
    lat0, lat1 = statistics.median(before_lat), statistics.median(during) if during else float("inf")
    return {"connections": connections, "requests": requests, "image": f"{width}x{height}",
            "rss_start_mb": round(rss0, 1), "rss_peak_mb": round(peak, 1), "growth_mb": round(peak - rss0, 1),
            "closed_by_server": closed, "rss_before_clients_close_mb": round(rss_held, 1),
            "rss_after_close_mb": round(after, 1), "held_after_close_mb": round(after - rss0, 1),
            "returned_within_s": None if returned_s is None else round(returned_s, 1),
            "latency_before_ms": round(lat0 * 1e3, 1), "latency_during_ms": round(lat1 * 1e3, 1),
            "latency_ratio": round(lat1 / lat0, 2), "server_alive": alive, "flags": list(flags or [])}


def acceptance_failures(r: dict[str, Any]) -> list[str]:
    """What of issue #44's acceptance the figures ``r`` fail (empty: none)."""
    out = []
    if r["growth_mb"] > GROWTH_LIMIT_MB:
        out.append(f"memory grew by {r['growth_mb']} MB (at most {GROWTH_LIMIT_MB:g})")
    if r["returned_within_s"] is None:
        out.append(f"{r['held_after_close_mb']} MB still held after the clients closed (returned: within "
                   f"{RETURNED_MB:g} MB of the start)")
    if r["latency_ratio"] > LATENCY_RATIO_LIMIT:
        out.append(f"the normal client's median latency rose {r['latency_ratio']}x")
    if not r["server_alive"]:
        out.append("the server stopped answering")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--connections", type=int, default=64)
    ap.add_argument("--requests", type=int, default=20)
    ap.add_argument("--hold-s", type=float, default=20.0, help="how long the clients hold their connections")
    ap.add_argument("--after-s", type=float, default=30.0, help="how long to wait for the memory after they close")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("server_flags", nargs="*", help="flags for brave6d serve (after --)")
    args = ap.parse_args(argv)
    r = measure(args.connections, args.requests, args.hold_s, args.after_s, flags=args.server_flags)
    print(json.dumps(r, indent=1))
    if args.json:
        args.json.write_text(json.dumps(r, indent=1) + "\n")
    failures = acceptance_failures(r)
    for f in failures:
        print("FAIL:", f)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

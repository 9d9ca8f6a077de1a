"""Hostile load on the render server (issue #65, classes 1 and 4): what it costs the other clients.

Starts ``brave6d serve`` on a synthetic bundle on a free loopback port (a process of its own, its
standard error captured), and a normal client from 127.0.0.1 that times small free views
(``POST /render``, 64 x 48, PNG + depth) and ``GET /health`` all along. Two scenarios:

``json``: ``--json-bodies`` (20) clients from 127.0.0.2 each send one adversarial JSON body of
``--body-kib`` (1024) KiB to ``POST /render`` (the server runs with ``--max-body-bytes`` 2 MiB, so the
body reaches the JSON reader): ``unterminated`` is 70 ``[``, a ``"`` and then ``\\"`` to the end (the
reader's depth check was quadratic in it), ``numbers`` a pose whose matrix holds 1 MiB of numbers.
Reports the time each body takes to be refused (the server's cost of it: the reply comes once it is
parsed and refused) and the normal client's median latency before and while they arrive.

``abandon``: ``--abandoned`` (300) maximum-size free views (1280 x 960) sent from 127.0.0.2 on at most
``--connections`` (60) connections at a time, each connection closed (reset) ``--drop-after-s`` after
its request went, without reading the reply. Reports the normal client's render latency before,
while the abandoners send and after they leave (its 504s counted), how many abandoned requests the
per-client connection cap refused at once (429) and how many renders the server drew in that time
(the normal client's and the abandoned ones), then sends SIGINT to the server
while ``--live`` (20) connected clients wait for maximum-size renders and reports how long it took to
exit, its exit status and how many tracebacks its log holds.

    python benchmarks/hostile_load.py [--scenario json|abandon|both] [--json out.json]

Exit status 1 when issue #65's acceptance fails: a body costs 1 s or more, the normal client's
median latency rises over 2x (while the bodies arrive; after the abandoners leave), or the
shutdown logs a traceback or takes longer than 30 s.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))

from brave6d.core.transforms import look_at  # noqa: E402
from non_reading_clients import start_server  # noqa: E402 - the same server start (benchmarks/ is on the path)

PEER = "127.0.0.2"  # Linux routes all of 127/8 to loopback: the hostile clients' own address
FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
SMALL = {"pose": {"world_T_cam": FREE.tolist()}, "width": 64, "height": 48}
BIG = {"pose": {"world_T_cam": FREE.tolist()}, "width": 1280, "height": 960}
LATENCY_RATIO_LIMIT = 2.0
BODY_COST_LIMIT_S = 1.0
SHUTDOWN_LIMIT_S = 30.0


def stop_server(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class Timer:
    """The normal client: times ``POST /render`` (small) and ``GET /health`` in a loop, in phases."""

    def __init__(self, url: str) -> None:
        self.client = httpx.Client(base_url=url, timeout=120)
        self.phase = "warm-up"
        self.samples: dict[str, list[tuple[str, float, int]]] = {}
        self.stop = threading.Event()
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        for _ in range(3):  # warm up (the first renders compile kernels)
            self.client.post("/render", json=SMALL)
        self.ready.set()
        while not self.stop.is_set():
            for what, call in (("render", lambda: self.client.post("/render", json=SMALL)),
                               ("health", lambda: self.client.get("/health"))):
                phase, t0 = self.phase, time.perf_counter()  # a sample counts in the phase it started in
                try:
                    status = call().status_code
                except httpx.HTTPError:
                    status = -1
                self.samples.setdefault(phase, []).append((what, time.perf_counter() - t0, status))
            time.sleep(0.02)

    def median_ms(self, phase: str, what: str) -> float:
        values = [s for w, s, code in self.samples.get(phase, []) if w == what and code == 200]
        return round(statistics.median(values) * 1e3, 1) if values else float("inf")

    def p90_ms(self, phase: str, what: str) -> float:
        """The 90th percentile (of at least 5 samples; else the largest): a stall shows here, not in the median."""
        values = sorted(s for w, s, code in self.samples.get(phase, []) if w == what)
        if not values:
            return float("inf")
        return round(values[min(len(values) - 1, int(0.9 * len(values)))] * 1e3, 1)

    def max_ms(self, phase: str, what: str) -> float:
        values = [s for w, s, _ in self.samples.get(phase, []) if w == what]
        return round(max(values) * 1e3, 1) if values else float("inf")

    def failures(self, phase: str) -> int:
        return sum(code != 200 for _, _, code in self.samples.get(phase, []))

    def count(self, phase: str) -> int:
        return len(self.samples.get(phase, []))

    def __enter__(self) -> Timer:
        self.thread.start()
        self.ready.wait(300)
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()
        self.client.close()


def adversarial_body(kind: str, size: int) -> bytes:
    """A JSON body of ``size`` bytes built to cost the reader: see the module docstring."""
    if kind == "unterminated":
        head = b"[" * 70 + b'"'
        return head + b'\\"' * ((size - len(head)) // 2)
    if kind == "numbers":
        head, tail = b'{"pose": {"world_T_cam": [[', b"]]}}"
        numbers = b"0.123456789," * ((size - len(head) - len(tail)) // 12)
        return head + numbers + b"0" + tail
    raise ValueError(kind)


def post_raw(address: tuple[str, int], body: bytes, timeout: float = 120.0) -> tuple[int, float]:
    """POST ``body`` to /render from :data:`PEER`; (status, seconds from the last byte sent to the reply)."""
    with socket.create_connection(address, timeout=timeout, source_address=(PEER, 0)) as s:
        head = (f"POST /render HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n").encode()
        s.sendall(head + body)
        t0 = time.perf_counter()
        try:
            first = s.recv(64)
        except TimeoutError:  # no reply within the timeout: counted as such
            return -1, timeout
        elapsed = time.perf_counter() - t0
    match = re.match(rb"HTTP/1.1 (\d+)", first)
    return (int(match.group(1)) if match else -1), elapsed


def abandon(address: tuple[str, int], drop_after_s: float) -> bool:
    """Send one maximum-size free view from :data:`PEER` and reset the connection unread; whether
    the server had refused the connection at once (429: the client's connection cap)."""
    body = json.dumps(BIG).encode()
    s = socket.create_connection(address, timeout=30, source_address=(PEER, 0))
    try:
        s.sendall((f"POST /render HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                   f"Content-Length: {len(body)}\r\n\r\n").encode() + body)
    except OSError:
        pass
    time.sleep(drop_after_s)  # the server has read the request: it is queued or rendering
    s.setblocking(False)
    try:
        refused = s.recv(64).startswith(b"HTTP/1.1 429")
    except OSError:
        refused = False
    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    s.close()
    return refused


def scenario_json(url: str, bodies: int, kib: int, settle_s: float) -> dict[str, Any]:
    host, port = url.rsplit("//", 1)[1].split(":")
    address = (host, int(port))
    out: dict[str, Any] = {"bodies": bodies, "body_kib": kib}
    with Timer(url) as timer:
        time.sleep(settle_s)
        timer.phase = "before"
        time.sleep(settle_s)
        for kind in ("unterminated", "numbers"):
            body = adversarial_body(kind, kib * 1024)
            status, alone = post_raw(address, body)  # one body, nothing else arriving
            timer.phase = f"during {kind}"
            with ThreadPoolExecutor(bodies) as pool:
                results = list(pool.map(lambda _: post_raw(address, body), range(bodies)))
            time.sleep(0.5)
            timer.phase = f"after {kind}"
            time.sleep(settle_s)
            out[kind] = {"status_alone": status, "seconds_alone": round(alone, 3),
                         "statuses": sorted({s for s, _ in results}),
                         "seconds_max_concurrent": round(max(t for _, t in results), 3),
                         "render_ms_before": timer.median_ms("before", "render"),
                         "render_ms_during": timer.median_ms(f"during {kind}", "render"),
                         "render_p90_ms_before": timer.p90_ms("before", "render"),
                         "render_p90_ms_during": timer.p90_ms(f"during {kind}", "render"),
                         "render_max_ms_during": timer.max_ms(f"during {kind}", "render"),
                         "health_ms_before": timer.median_ms("before", "health"),
                         "health_ms_during": timer.median_ms(f"during {kind}", "health"),
                         "health_max_ms_during": timer.max_ms(f"during {kind}", "health"),
                         "samples_during": timer.count(f"during {kind}"),
                         "failures_during": timer.failures(f"during {kind}")}
            r = out[kind]
            r["render_ratio"] = round(r["render_ms_during"] / r["render_ms_before"], 2)
            r["render_p90_ratio"] = round(r["render_p90_ms_during"] / r["render_p90_ms_before"], 2)
    return out


def scenario_abandon(url: str, proc: subprocess.Popen[str], abandoned: int, connections: int, drop_after_s: float,
                     live: int, settle_s: float, stderr: Path) -> dict[str, Any]:
    host, port = url.rsplit("//", 1)[1].split(":")
    address = (host, int(port))
    out: dict[str, Any] = {"abandoned": abandoned, "connections": connections, "drop_after_s": drop_after_s}
    with httpx.Client(base_url=url, timeout=120) as c:
        t0 = time.perf_counter()
        c.post("/render", json=BIG).raise_for_status()
        out["big_render_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
        renders = c.get("/health").json()["renders"]
    with Timer(url) as timer:
        time.sleep(settle_s)
        timer.phase = "before"
        time.sleep(settle_s)
        timer.phase = "while sending"
        t0 = time.perf_counter()
        with ThreadPoolExecutor(connections) as pool:
            refused = sum(pool.map(lambda _: abandon(address, drop_after_s), range(abandoned)))
        out["sending_s"] = round(time.perf_counter() - t0, 1)
        out["refused_429"] = refused
        timer.phase = "after"
        time.sleep(2 * settle_s)
        with httpx.Client(base_url=url, timeout=120) as c:  # renders drawn: the normal client's and the abandoned
            out["renders_drawn"] = c.get("/health").json()["renders"] - renders
        normal = 3 + sum(1 for phase in ("warm-up", "before", "while sending", "after")  # 3: the timer's warm-up
                         for w, _, code in timer.samples.get(phase, []) if w == "render" and code == 200)
        out["abandoned_drawn"] = out["renders_drawn"] - normal  # give or take the normal client's last one
        for phase in ("before", "while sending", "after"):
            key = phase.replace(" ", "_")
            out[f"render_ms_{key}"] = timer.median_ms(phase, "render")
            out[f"render_p90_ms_{key}"] = timer.p90_ms(phase, "render")
            out[f"render_max_ms_{key}"] = timer.max_ms(phase, "render")
            out[f"failures_{key}"] = timer.failures(phase)
        out["render_ratio_after"] = round(out["render_ms_after"] / out["render_ms_before"], 2)
        out["render_p90_ratio_after"] = round(out["render_p90_ms_after"] / out["render_p90_ms_before"], 2)
    # Ctrl-C while live clients wait for maximum-size renders
    waiting = ThreadPoolExecutor(live)
    clients = [httpx.Client(base_url=url, timeout=60) for _ in range(live)]

    def wait_render(client: httpx.Client) -> int:
        try:
            return client.post("/render", json=BIG).status_code
        except httpx.HTTPError:
            return -1

    futures = [waiting.submit(wait_render, cl) for cl in clients]
    time.sleep(1.0)
    t0 = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    try:
        code = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        code = None
        proc.kill()
        proc.wait()
    out["shutdown_s"] = round(time.perf_counter() - t0, 2)
    out["exit_status"] = code
    statuses = [f.result() for f in futures]
    waiting.shutdown()
    for cl in clients:
        cl.close()
    log = stderr.read_text(errors="replace")
    out["live_statuses"] = sorted(set(statuses))
    out["tracebacks"] = log.count("Traceback")
    out["log_tail"] = log.strip().splitlines()[-3:]
    return out


def measure(scenario: str = "both", bodies: int = 20, kib: int = 1024, abandoned: int = 300, connections: int = 60,
            drop_after_s: float = 0.3, live: int = 20, settle_s: float = 4.0, n_gaussians: int = 20_000) -> dict[str, Any]:
    """Run the scenarios of the module docstring; the figures as a dict (ms, seconds, counts)."""
    from brave6d.serve.toy_scene import make_synthetic_bundle

    out: dict[str, Any] = {"gaussians": n_gaussians}
    with tempfile.TemporaryDirectory(prefix="brave6d-hostile-load-") as tmp:
        root = Path(tmp)
        bundle = make_synthetic_bundle(root / "scene", n_gaussians=n_gaussians, n_views=4)
        if scenario in ("json", "both"):
            proc, url = start_server(bundle, root / "episodes", ["--max-body-bytes", str(2 * 2**20)], root / "json.log")
            try:
                out["json"] = scenario_json(url, bodies, kib, settle_s)
            finally:
                stop_server(proc)
        if scenario in ("abandon", "both"):
            proc, url = start_server(bundle, root / "episodes", [], root / "abandon.log")
            try:
                out["abandon"] = scenario_abandon(url, proc, abandoned, connections, drop_after_s, live, settle_s,
                                                  root / "abandon.log")
            finally:
                stop_server(proc)
    return out


def acceptance_failures(r: dict[str, Any]) -> list[str]:
    """What of issue #65's acceptance the figures ``r`` fail (empty: none)."""
    out = []
    for kind, figures in r.get("json", {}).items():
        if not isinstance(figures, dict):
            continue
        if figures["seconds_alone"] >= BODY_COST_LIMIT_S:
            out.append(f"json {kind}: one body took {figures['seconds_alone']} s to refuse")
        if figures["render_ratio"] > LATENCY_RATIO_LIMIT or figures["render_p90_ratio"] > LATENCY_RATIO_LIMIT:
            out.append(f"json {kind}: the normal client's render latency rose {figures['render_ratio']}x (median), "
                       f"{figures['render_p90_ratio']}x (90th percentile)")
    a = r.get("abandon")
    if a:
        if a["render_ratio_after"] > LATENCY_RATIO_LIMIT or a["render_p90_ratio_after"] > LATENCY_RATIO_LIMIT \
                or a["failures_after"]:
            out.append(f"abandon: after the abandoners left, renders took {a['render_ratio_after']}x (median), "
                       f"{a['render_p90_ratio_after']}x (90th percentile), {a['failures_after']} failed")
        if a["tracebacks"] or a["shutdown_s"] > SHUTDOWN_LIMIT_S or a["exit_status"] is None:
            out.append(f"abandon: Ctrl-C took {a['shutdown_s']} s, exit {a['exit_status']}, "
                       f"{a['tracebacks']} tracebacks logged")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", choices=("json", "abandon", "both"), default="both")
    ap.add_argument("--json-bodies", type=int, default=20)
    ap.add_argument("--body-kib", type=int, default=1024)
    ap.add_argument("--abandoned", type=int, default=300)
    ap.add_argument("--connections", type=int, default=60)
    ap.add_argument("--drop-after-s", type=float, default=0.3)
    ap.add_argument("--live", type=int, default=20)
    ap.add_argument("--settle-s", type=float, default=4.0, help="seconds of each timing phase")
    ap.add_argument("--gaussians", type=int, default=20_000)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    r = measure(args.scenario, args.json_bodies, args.body_kib, args.abandoned, args.connections, args.drop_after_s,
                args.live, args.settle_s, args.gaussians)
    print(json.dumps(r, indent=1))
    if args.json:
        args.json.write_text(json.dumps(r, indent=1) + "\n")
    failures = acceptance_failures(r)
    for f in failures:
        print("FAIL:", f)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

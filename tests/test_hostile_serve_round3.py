"""Work that stops when its client leaves (issue #65, classes 1 and 4): a render whose client has
dropped its connection is taken off the queue or skipped once it holds the device, never drawn; at
shutdown every action in flight is withdrawn (503) and nothing is logged as an error; request
bodies over 64 KiB are parsed off the event loop.

Before: 300 maximum-size free views sent and dropped kept every other client's renders answering
504 for at least 95 s (each was drawn), and Ctrl-C then logged 168-302 tracebacks (the withdrawn
actions' futures, cancelled at shutdown, raised in their done callbacks). Here the device is held
by the test (the renderer's lock), so the queue is deterministic: no timing decides the outcome.
"""

from __future__ import annotations

import json
import logging
import socket
import struct
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from brave6d.core.transforms import look_at
from brave6d.serve import SceneServer, ServerLimits, ServerThread, create_app, load_bundle, make_synthetic_bundle

FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
PEER = "127.0.0.2"  # Linux routes all of 127/8 to loopback: the abandoning client's own address
BIG = {"pose": {"world_T_cam": FREE.tolist()}, "width": 1280, "height": 960, "rgb": "none", "depth": "none"}
SMALL = {"pose": {"world_T_cam": FREE.tolist()}, "width": 64, "height": 48}


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SceneServer:
    bundle = load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("abandon_scene"), n_gaussians=1000))
    return SceneServer(bundle, device="cpu")


@pytest.fixture()
def served(scene: SceneServer, tmp_path: Path) -> Iterator[tuple[ServerThread, SceneServer]]:
    app = create_app(scene.bundle, scene=scene, warm_up=False, log_dir=tmp_path / "episodes",
                     limits=ServerLimits(request_timeout_s=60.0))
    with ServerThread(app) as server:
        with httpx.Client(base_url=server.url, timeout=120) as c:
            assert c.post("/render", json=SMALL).status_code == 200  # kernels compiled before the counts
        yield server, scene


def _in_flight(server: ServerThread, count: int, seconds: float = 20.0) -> None:
    """Wait until ``count`` actions are in flight on the server (their requests read and queued)."""
    inflight = server.server.config.app.state.inflight
    t0 = time.monotonic()
    while inflight.running() < count:
        assert time.monotonic() - t0 < seconds, f"{inflight.running()} of {count} actions in flight"
        time.sleep(0.02)


def _send_and_drop_later(server: ServerThread) -> socket.socket:
    body = json.dumps(BIG).encode()
    s = socket.create_connection((server.host, server.port), timeout=30, source_address=(PEER, 0))
    s.sendall(b"POST /render HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
              + f"Content-Length: {len(body)}\r\n\r\n".encode() + body)
    return s


def _reset(s: socket.socket) -> None:
    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    s.close()


def test_renders_whose_clients_left_are_never_drawn(served: tuple[ServerThread, SceneServer]) -> None:
    server, scene = served
    renders = scene.renderer.renders
    with scene.renderer.lock:  # the device is busy: every render waits for it
        socks = [_send_and_drop_later(server) for _ in range(24)]  # more than the 16 workers: some queue
        _in_flight(server, 24)
        for s in socks:
            _reset(s)
        t0 = time.monotonic()
        while server.server.config.app.state.inflight.running() and time.monotonic() - t0 < 20:
            time.sleep(0.02)  # each handler sees its client gone and withdraws its action
        assert server.server.config.app.state.inflight.running() == 0
    with httpx.Client(base_url=server.url, timeout=120) as c:
        r = c.post("/render", json=SMALL)
    assert r.status_code == 200
    time.sleep(0.5)  # a withdrawn render that was waiting for the device has had its turn by now
    assert scene.renderer.renders - renders == 1, "a render whose client had left was drawn"


def test_shutdown_withdraws_what_waits_and_logs_no_error(served: tuple[ServerThread, SceneServer],
                                                         caplog: pytest.LogCaptureFixture) -> None:
    server, scene = served
    caplog.set_level(logging.WARNING)
    statuses: list[int] = []

    def wait_for_render() -> None:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            statuses.append(c.post("/render", json=BIG).status_code)

    with scene.renderer.lock, ThreadPoolExecutor(20) as pool:
        for _ in range(20):
            pool.submit(wait_for_render)
        _in_flight(server, 20)
        t0 = time.monotonic()
        stopping = threading.Thread(target=server.stop)
        stopping.start()
        stopping.join(20)
        took = time.monotonic() - t0
        assert not stopping.is_alive(), "the server still waits for the renders queued at shutdown"
    assert took < 10 and statuses == [503] * 20, (took, statuses)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert not errors, [r.getMessage() for r in errors]


def test_timed_out_actions_leave_no_traceback_at_shutdown(scene: SceneServer, tmp_path: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    """A timed-out action's future, cancelled when the pool shuts down, raised CancelledError in its
    done callback: one 'Exception in callback' traceback per such action."""
    caplog.set_level(logging.WARNING)
    app = create_app(scene.bundle, scene=scene, warm_up=False, log_dir=tmp_path / "episodes",
                     limits=ServerLimits(request_timeout_s=0.5, workers=4))
    server = ServerThread(app).start()

    def render() -> int:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            return c.post("/render", json=BIG).status_code

    with scene.renderer.lock:
        with ThreadPoolExecutor(8) as pool:  # 4 wait for the device, 4 stay queued in the pool
            assert list(pool.map(lambda _: render(), range(8))) == [504] * 8
        server.stop()
    time.sleep(0.5)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert not errors, [r.getMessage() for r in errors]


def test_large_bodies_are_parsed_off_the_event_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    import asyncio
    from concurrent.futures import ThreadPoolExecutor as Pool

    from brave6d.serve import app as app_module

    threads: list[str] = []
    real = app_module.parse_json

    def recording(*args, **kwargs):  # type: ignore[no-untyped-def]
        threads.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(app_module, "parse_json", recording)
    limits = ServerLimits(max_body_bytes=2**20)
    small, large = json.dumps({"a": 1}).encode(), json.dumps({"a": "x" * 100_000}).encode()
    with Pool(1, thread_name_prefix="brave6d-json") as parser:
        async def both() -> None:
            assert await app_module.parse_request_json(small, "body", limits, parser) == {"a": 1}
            assert len((await app_module.parse_request_json(large, "body", limits, parser))["a"]) == 100_000
        asyncio.run(both())
    assert threads[0] == "MainThread" and threads[1].startswith("brave6d-json"), threads

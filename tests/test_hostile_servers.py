"""Clients that distrust servers (issue #65, class 6): ``BraveClient`` and ``BraveEnv`` against a
hostile server on loopback. Every reply is read within the client's limits (size as sent and
decompressed, JSON depth and number length, image headers, ``.npy`` headers, a deadline for the
whole call) and a reply that breaks one is the client's own one-line :class:`ReplyError`.

Before: a raw ``ValueError`` (a 5000-digit integer), ``RecursionError`` (JSON 100,000 deep),
``MemoryError`` (an ``.npy`` header of 27.9 GiB, a gzip bomb at 2.1 GB, a chunked reply that never
ends at 3 GB), ``cv2.error`` / ``TypeError`` (PNG headers of 100000 x 100000 and 30000 x 30000),
and a reply dripping a byte every 2 s held a ``timeout=5`` call past 45 s.

The hostile server is a plain socket server speaking HTTP/1.1 (one scripted reply per request):
the real client library, the other side of the protocol faked only in what it sends.
"""

from __future__ import annotations

import base64
import gzip
import io
import json
import socket
import struct
import threading
import time
import zipfile
import zlib
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from brave6d.core.transforms import look_at
from brave6d.serve import BraveClient, BraveEnv, ClientLimits, ReplyError, ServerError

Reply = Callable[[socket.socket], None]
FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
W, H = 64, 48


class HostileServer:
    """A loopback HTTP server that answers every request with ``reply`` (a function writing raw bytes)."""

    def __init__(self) -> None:
        self.reply: Reply = lambda s: None
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.stop = threading.Event()
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._one, args=(conn,), daemon=True).start()

    def _one(self, conn: socket.socket) -> None:
        with conn:
            try:
                conn.settimeout(10)
                data = b""
                while b"\r\n\r\n" not in data:
                    data += conn.recv(65536)
                head, _, body = data.partition(b"\r\n\r\n")
                length = next((int(v) for k, _, v in (line.partition(b":") for line in head.split(b"\r\n"))
                               if k.strip().lower() == b"content-length"), 0)
                while len(body) < length:
                    body += conn.recv(65536)
                self.reply(conn)
            except OSError:
                pass


@pytest.fixture()
def hostile() -> Iterator[HostileServer]:
    server = HostileServer()
    yield server
    server.stop.set()
    server.sock.close()


def reply_bytes(body: bytes, status: int = 200, headers: str = "content-type: application/json\r\n") -> Reply:
    def send(conn: socket.socket) -> None:
        conn.sendall(f"HTTP/1.1 {status} X\r\n{headers}content-length: {len(body)}\r\nconnection: close\r\n\r\n"
                     .encode() + body)
    return send


def observation(rgb: bytes | None = None, rgb_shape: tuple[int, int] = (H, W), depth: bytes | None = None) -> dict:
    """A free view's reply, its images as given (base64)."""
    obs = {"width": W, "height": H, "K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]], "world_T_cam": FREE.tolist(),
           "rgb": None if rgb is None else {"encoding": "png", "data": base64.b64encode(rgb).decode(),
                                            "shape": [rgb_shape[0], rgb_shape[1], 3]},
           "depth": None if depth is None else {"encoding": "f32", "data": base64.b64encode(depth).decode(),
                                                "shape": [H, W]},
           "objects": []}
    return {"scene": "s", "observation": obs, "timings_ms": {}}


def png_header(width: int, height: int) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(bytes(64))) + chunk(b"IEND", b""))


def _refused(call: Callable[[], object], says: str, within_s: float = 10.0) -> str:
    t0 = time.perf_counter()
    with pytest.raises(ReplyError) as info:
        call()
    message = str(info.value)
    assert "\n" not in message and says in message, message
    assert time.perf_counter() - t0 < within_s
    return message


# ----------------------------------------------------------------------------- JSON
def test_a_5000_digit_integer_is_a_reply_error(hostile: HostileServer) -> None:
    hostile.reply = reply_bytes(b'{"status": "ok", "episodes_open": ' + b"9" * 5000 + b"}")
    with BraveClient(hostile.url) as client:
        _refused(client.health, "a number of 5000 characters")


def test_json_nested_100000_deep_is_a_reply_error(hostile: HostileServer) -> None:
    hostile.reply = reply_bytes(b"[" * 100_000 + b"]" * 100_000)
    with BraveClient(hostile.url) as client:
        _refused(client.health, "nested too deeply")
        env = BraveEnv(client=client, width=W, height=H)
        _refused(lambda: env.reset(seed=0), "nested too deeply")


def test_an_error_reply_is_one_short_line(hostile: HostileServer) -> None:
    hostile.reply = reply_bytes(json.dumps({"error": "bad\nnews " * 5000, "field": "x\ny", "status": 400}).encode(), 400)
    with BraveClient(hostile.url) as client, pytest.raises(ServerError) as info:
        client.health()
    assert "\n" not in str(info.value) and len(str(info.value)) < 400 and info.value.field == "x y"


# ----------------------------------------------------------------------------- sizes
def test_a_declared_or_endless_reply_past_the_limit_is_refused(hostile: HostileServer) -> None:
    limits = ClientLimits(max_reply_bytes=2**20)
    hostile.reply = reply_bytes(b"0" * (2**20 + 1))
    with BraveClient(hostile.url, limits=limits) as client:
        _refused(client.health, "declares 1048577 bytes")

    def endless(conn: socket.socket) -> None:  # a chunked reply that never ends
        conn.sendall(b"HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ntransfer-encoding: chunked\r\n\r\n")
        piece = b"%x\r\n%s\r\n" % (65536, b" " * 65536)
        while True:
            conn.sendall(piece)

    hostile.reply = endless
    with BraveClient(hostile.url, limits=limits) as client:
        _refused(client.health, "longer than 1048576 bytes")


def test_a_gzip_bomb_is_refused_once_it_inflates_past_the_limit(hostile: HostileServer) -> None:
    bomb = gzip.compress(b" " * (32 * 2**20), compresslevel=9)  # 32 MiB of spaces in about 32 kB
    hostile.reply = reply_bytes(bomb, headers="content-type: application/json\r\ncontent-encoding: gzip\r\n")
    with BraveClient(hostile.url, limits=ClientLimits(max_reply_bytes=2**20)) as client:
        _refused(client.health, "decompresses to more than 1048576 bytes")


def test_a_compressed_reply_within_the_limit_is_read(hostile: HostileServer) -> None:
    hostile.reply = reply_bytes(gzip.compress(b'{"status": "ok"}'),
                                headers="content-type: application/json\r\ncontent-encoding: gzip\r\n")
    with BraveClient(hostile.url) as client:
        assert client.health() == {"status": "ok"}


def test_an_npy_header_of_27_9_gib_is_refused_before_allocating(hostile: HostileServer) -> None:
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False,
                                                  "shape": (100_000, 100_000, 3)})
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("rgb.npy", header.getvalue() + bytes(64))
    hostile.reply = reply_bytes(buf.getvalue(), headers="content-type: application/octet-stream\r\n")
    with BraveClient(hostile.url) as client:
        _refused(lambda: client.observation_npz("e1"), "240000000000 bytes")


# ----------------------------------------------------------------------------- images
@pytest.mark.parametrize("size, says", [((100_000, 100_000), "declares 100000x100000 pixels"),
                                        ((30_000, 30_000), "declares 30000x30000 pixels"),
                                        ((W + 1, H), f"the image's header says {W + 1}x{H}")])
def test_an_image_header_larger_than_the_message_is_refused_before_decoding(hostile: HostileServer,
                                                                           size: tuple[int, int], says: str) -> None:
    hostile.reply = reply_bytes(json.dumps(observation(png_header(*size))).encode())
    with BraveClient(hostile.url) as client:
        _refused(lambda: client.render(FREE), says)


def test_a_message_claiming_a_huge_image_is_refused(hostile: HostileServer) -> None:
    body = observation(png_header(W, H))
    body["observation"].update(width=100_000, height=100_000)
    body["observation"]["rgb"]["shape"] = [100_000, 100_000, 3]
    hostile.reply = reply_bytes(json.dumps(body).encode())
    with BraveClient(hostile.url) as client:
        _refused(lambda: client.render(FREE), "100000x100000 pixels")


def test_depth_of_the_wrong_length_is_refused(hostile: HostileServer) -> None:
    hostile.reply = reply_bytes(json.dumps(observation(depth=bytes(4 * W * H - 4))).encode())
    with BraveClient(hostile.url) as client:
        _refused(lambda: client.render(FREE), f"{4 * W * H - 4} bytes")


def test_a_well_formed_view_still_decodes(hostile: HostileServer) -> None:
    import cv2

    rgb = np.random.default_rng(0).integers(0, 255, (H, W, 3), dtype=np.uint8)
    depth = np.full((H, W), 0.5, "<f4")
    png = cv2.imencode(".png", rgb[:, :, ::-1])[1].tobytes()
    hostile.reply = reply_bytes(json.dumps(observation(png, depth=depth.tobytes())).encode())
    with BraveClient(hostile.url) as client:
        view = client.render(FREE)
    assert np.array_equal(view.rgb, rgb) and np.array_equal(view.depth, depth)


# ----------------------------------------------------------------------------- the deadline
@pytest.mark.parametrize("where", ["body", "headers"])
def test_a_dripping_reply_cannot_outlast_the_calls_deadline(hostile: HostileServer, where: str) -> None:
    """httpx's timeout is per read: a byte every 0.5 s never trips a 2 s timeout. The client's
    deadline covers the whole call."""
    def drip(conn: socket.socket) -> None:
        head = b"HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: 1000\r\n\r\n"
        if where == "body":
            conn.sendall(head)
        for byte in ((head if where == "headers" else b"") + b" " * 1000):
            conn.sendall(bytes([byte]))
            time.sleep(0.5)

    hostile.reply = drip
    with BraveClient(hostile.url, timeout=2.0) as client:
        message = _refused(client.health, "no whole reply within the call's deadline of 2 s", within_s=4.0)
    assert "GET /health" in message

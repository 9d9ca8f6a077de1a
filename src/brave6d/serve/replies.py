"""What a client reads from a render server it does not trust: every reply held to limits.

From a client's side the server is untrusted: an agent may be pointed at anyone's server, and a
server that is not ours (or not ours any more) can send anything. So :class:`~brave6d.serve.BraveClient`
(and :class:`~brave6d.serve.BraveEnv`, which uses it) reads every reply through this module, with the
same kind of limits the server keeps on requests (:class:`ClientLimits`, defaults in docs/SECURITY.md):

- an overall deadline per call (:func:`call_deadline`): the connection's every read and write waits at
  most until the deadline, so a server that drips a byte every 2 s cannot hold a ``timeout=5`` call
  longer than 5 s (httpx's timeouts are per read);
- the reply's size as sent (its ``Content-Length``, then the bytes as they stream: a chunked reply
  that never ends is cut at the limit) and, when the server compresses it (``gzip``, ``deflate``;
  the client asks for none), its size decompressed, inflated piece by piece within the limit;
- JSON through the one JSON reader (:mod:`brave6d.core.json_input`: depth, number length, finite
  numbers, linear time);
- images: base64 sizes, each image's header (PNG's IHDR, other formats' by Pillow) against the
  message's own size and the server's largest image before anything is decoded, the decoded image
  against that size; depth as exactly ``height x width`` float32 values;
- ``observation.npz``: members listed in the zip's directory with their sizes (each and in all within
  the limit) before anything is inflated, each ``.npy`` header checked before its array is read
  (:func:`brave6d.core.npy_check.npy_from_bytes`).

A reply that breaks a limit raises :class:`ReplyError` (a :class:`~brave6d.core.errors.BraveError`):
one line naming the request and the limit, never a ``ValueError`` of CPython's integer limit, a
``RecursionError``, a ``MemoryError`` or an OpenCV error.
"""

from __future__ import annotations

import binascii
import io
import time
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError, DataError
from brave6d.core.json_input import JsonInputError, JsonLimits, parse_json
from brave6d.serve.limits import MAX_HEIGHT, MAX_WIDTH


class ReplyError(BraveError):
    """A server's reply this client refuses to read (too large, too deep, too slow, malformed)."""


@dataclass(frozen=True)
class ClientLimits:
    """What one reply may hold (docs/SECURITY.md); ``deadline_s`` bounds a whole call."""

    max_reply_bytes: int = 128 * 2**20  # a 1280 x 960 PNG + depth observation is about 12 MB as JSON
    max_depth: int = 64  # the deepest reply nests 5
    max_number_chars: int = 100
    max_pixels: int = MAX_WIDTH * MAX_HEIGHT  # the server renders no larger image
    deadline_s: float = 120.0

    def __post_init__(self) -> None:
        for name in ("max_reply_bytes", "max_depth", "max_number_chars", "max_pixels"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ClientLimits.{name} must be an integer >= 1, got {value!r}")
        if not 0 < self.deadline_s < float("inf"):
            raise ValueError(f"ClientLimits.deadline_s must be a positive number of seconds, got {self.deadline_s!r}")

    def json(self) -> JsonLimits:
        return JsonLimits(max_bytes=self.max_reply_bytes, max_depth=self.max_depth,
                          max_number_chars=self.max_number_chars)


# ----------------------------------------------------------------------------- the deadline
#: The monotonic time by which the running call must end (None: no call runs in this thread).
_DEADLINE: ContextVar[float | None] = ContextVar("brave6d_client_deadline", default=None)


@contextmanager
def call_deadline(seconds: float) -> Iterator[float]:
    """Every read and write of the connection inside the block ends by ``seconds`` from now."""
    deadline = time.monotonic() + seconds
    token = _DEADLINE.set(deadline)
    try:
        yield deadline
    finally:
        _DEADLINE.reset(token)


def _bounded(timeout: float | None) -> float | None:
    """``timeout`` cut to what is left of the call's deadline; httpcore's timeout once it has passed."""
    import httpcore

    deadline = _DEADLINE.get()
    if deadline is None:
        return timeout
    left = deadline - time.monotonic()
    if left <= 0:
        raise httpcore.ReadTimeout("the call's deadline passed")
    return left if timeout is None else min(timeout, left)


def deadline_transport() -> Any:
    """An ``httpx.HTTPTransport`` whose connections wait no longer than the running call's deadline
    (:func:`call_deadline`): httpcore's network backend, wrapped."""
    import httpcore
    import httpx

    class Stream(httpcore.NetworkStream):
        def __init__(self, stream: Any) -> None:
            self._stream = stream

        def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
            return self._stream.read(max_bytes, _bounded(timeout))

        def write(self, buffer: bytes, timeout: float | None = None) -> None:
            self._stream.write(buffer, _bounded(timeout))

        def close(self) -> None:
            self._stream.close()

        def start_tls(self, ssl_context: Any, server_hostname: str | None = None, timeout: float | None = None) -> Any:
            return Stream(self._stream.start_tls(ssl_context, server_hostname, _bounded(timeout)))

        def get_extra_info(self, info: str) -> Any:
            return self._stream.get_extra_info(info)

    class Backend(httpcore.NetworkBackend):
        def __init__(self) -> None:
            self._backend = httpcore.SyncBackend()

        def connect_tcp(self, host: str, port: int, timeout: float | None = None, local_address: str | None = None,
                        socket_options: Any = None) -> Any:
            return Stream(self._backend.connect_tcp(host, port, _bounded(timeout), local_address, socket_options))

        def connect_unix_socket(self, path: str, timeout: float | None = None, socket_options: Any = None) -> Any:
            return Stream(self._backend.connect_unix_socket(path, _bounded(timeout), socket_options))

        def sleep(self, seconds: float) -> None:
            self._backend.sleep(seconds)

    transport = httpx.HTTPTransport()
    pool = getattr(transport, "_pool", None)
    if pool is None or not hasattr(pool, "_network_backend"):  # an httpx / httpcore this was not written for
        raise RuntimeError("httpx's transport has no httpcore connection pool to hold to a deadline")
    pool._network_backend = Backend()
    return transport


# ----------------------------------------------------------------------------- bodies
def read_body(response: Any, limits: ClientLimits, what: str) -> bytes:
    """The body of the streamed ``response`` (``httpx``), within ``limits.max_reply_bytes`` as sent
    and as decompressed; ``what`` names the request in errors (``POST /render``)."""
    cap = limits.max_reply_bytes
    declared = response.headers.get("content-length", "")
    if declared.strip().isdigit() and int(declared) > cap:
        raise ReplyError(f"{what}: the server's reply declares {int(declared)} bytes (at most {cap} are read)")
    encoding = response.headers.get("content-encoding", "identity").strip().lower()
    if encoding not in ("", "identity", "gzip", "x-gzip", "deflate"):
        raise ReplyError(f"{what}: the server's reply is {encoding[:40]!r}-encoded (identity, gzip or deflate are read)")
    inflate = zlib.decompressobj(31 if "gzip" in encoding else 15) if encoding in ("gzip", "x-gzip", "deflate") else None
    chunks: list[bytes] = []
    size = raw = 0
    try:
        for piece in response.iter_raw():
            raw += len(piece)
            if raw > cap:
                raise ReplyError(f"{what}: the server's reply is longer than {cap} bytes (at most {cap} are read)")
            if inflate is None:
                out = [piece]
            else:
                out = []
                while piece and size + sum(map(len, out)) <= cap:
                    out.append(inflate.decompress(piece, cap + 1 - size - sum(map(len, out))))
                    piece = inflate.unconsumed_tail
            size += sum(map(len, out))
            if size > cap:
                raise ReplyError(f"{what}: the server's reply decompresses to more than {cap} bytes (at most "
                                 f"{cap} are read)")
            chunks.extend(out)
    except zlib.error as exc:
        raise ReplyError(f"{what}: the server's {encoding} reply does not inflate ({exc})") from None
    return b"".join(chunks)


def parse_reply(data: bytes, limits: ClientLimits, what: str) -> Any:
    """The JSON of a reply through the one JSON reader; :class:`ReplyError` naming ``what``."""
    try:
        return parse_json(data, f"{what}: the server's reply", limits.json())
    except JsonInputError as exc:
        raise ReplyError(str(exc)) from None


def one_line(text: Any, limit: int = 300) -> str:
    """``text`` as one short line (a server's error message is shown, never trusted to be short)."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


# ----------------------------------------------------------------------------- images
def _b64(data: str, what: str, field: str, limit: int) -> bytes:
    if len(data) > limit * 4 // 3 + 4:
        raise ReplyError(f"{what}: field '{field}': {len(data)} characters of base64 (at most {limit} bytes are read)")
    try:
        return binascii.a2b_base64(data, strict_mode=True)  # validated in C (b64decode's validate=True: a regex)
    except (binascii.Error, ValueError) as exc:
        raise ReplyError(f"{what}: field '{field}': not base64 ({exc})") from None


def _size(width: Any, height: Any, what: str, limits: ClientLimits) -> tuple[int, int]:
    if not (isinstance(width, int) and isinstance(height, int) and 0 < width and 0 < height
            and width * height <= limits.max_pixels):
        raise ReplyError(f"{what}: the observation is {width}x{height} pixels (at most {limits.max_pixels} are read)")
    return width, height


def decode_rgb(image: Any, width: int, height: int, what: str, limits: ClientLimits) -> NDArray[np.uint8]:
    """An observation's RGB (``png`` / ``jpeg``, base64) as (H, W, 3) uint8: its header against the
    message's size before it is decoded, the decoded image against it after."""
    import cv2

    from brave6d.core.png_check import SIGNATURE, image_header_problem, png_size

    width, height = _size(width, height, what, limits)
    if list(image.shape) != [height, width, 3] or image.encoding not in ("png", "jpeg"):
        raise ReplyError(f"{what}: field 'observation.rgb': a {image.encoding[:20]!r} image of shape "
                         f"{list(image.shape)[:4]} is not the {height}x{width} RGB the message says")
    data = _b64(image.data, what, "observation.rgb.data", limits.max_reply_bytes)
    problem = image_header_problem(data, limits.max_pixels)
    if problem is not None:
        raise ReplyError(f"{what}: field 'observation.rgb': {problem}")
    if data.startswith(SIGNATURE):
        header = png_size(data[:24])
    else:
        from PIL import Image

        with Image.open(io.BytesIO(data)) as im:  # the header only
            header = (int(im.size[0]), int(im.size[1]))
    if header != (width, height):
        raise ReplyError(f"{what}: field 'observation.rgb': the image's header says {header[0]}x{header[1]}, the "
                         f"message {width}x{height}")
    try:
        bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    except cv2.error:
        bgr = None
    if bgr is None or bgr.shape != (height, width, 3):
        raise ReplyError(f"{what}: field 'observation.rgb': does not decode to a {width}x{height} RGB image")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def decode_depth(image: Any, width: int, height: int, what: str, limits: ClientLimits) -> NDArray[np.float32]:
    """An observation's depth (``f32``: little-endian float32, base64) as (H, W) float32: exactly
    ``height x width`` values."""
    width, height = _size(width, height, what, limits)
    if list(image.shape) != [height, width] or image.encoding != "f32":
        raise ReplyError(f"{what}: field 'observation.depth': a {image.encoding[:20]!r} image of shape "
                         f"{list(image.shape)[:4]} is not the {height}x{width} float32 depth the message says")
    data = _b64(image.data, what, "observation.depth.data", 4 * width * height)
    if len(data) != 4 * width * height:
        raise ReplyError(f"{what}: field 'observation.depth.data': {len(data)} bytes, {height}x{width} float32 "
                         f"values are {4 * width * height}")
    return np.frombuffer(data, dtype="<f4").reshape(height, width).astype(np.float32)


# ----------------------------------------------------------------------------- observation.npz
#: The arrays an ``observation.npz`` holds at most (the server writes eight).
MAX_NPZ_MEMBERS = 32


def read_npz(data: bytes, what: str, limits: ClientLimits) -> dict[str, NDArray[Any]]:
    """The arrays of an ``observation.npz`` reply: its zip directory checked first (members, their
    declared sizes each and in all within the limit), each member inflated within its declared size
    and its ``.npy`` header checked before its array is read."""
    from brave6d.core.npy_check import npy_from_bytes

    cap = limits.max_reply_bytes
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            infos = zf.infolist()
            if len(infos) > MAX_NPZ_MEMBERS:
                raise ReplyError(f"{what}: {len(infos)} arrays in the .npz (at most {MAX_NPZ_MEMBERS} are read)")
            total = sum(i.file_size for i in infos)
            if total > cap:
                raise ReplyError(f"{what}: the .npz declares {total} bytes of arrays (at most {cap} are read)")
            out: dict[str, NDArray[Any]] = {}
            for info in infos:
                name = info.filename.removesuffix(".npy")
                with zf.open(info) as member:
                    raw = member.read(info.file_size + 1)
                out[name] = npy_from_bytes(raw, f"{what}: {info.filename[:80]}", cap)
            return out
    except (zipfile.BadZipFile, zlib.error, NotImplementedError, EOFError, OSError) as exc:
        raise ReplyError(f"{what}: not a readable .npz ({type(exc).__name__}: {one_line(exc, 120)})") from None
    except DataError as exc:
        raise ReplyError(str(exc)) from None

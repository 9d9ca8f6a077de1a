"""Every reader of input from elsewhere stays linear (issue #65, class 1 and the rule behind it):
doubling an adversarial input at most about doubles the time.

Each case times a reader on an adversarial input of ``n`` units and of ``4 n`` (two doublings),
the best of a few runs each, and compares the ratio, never an absolute time: linear time gives 4,
quadratic 16; the bound is 10 (about 3.2 per doubling: caches that a larger input outgrows cost up to
twice per entry), so a busy machine does not fail it and a quadratic reader cannot pass it. The sizes are small (a case takes well under a second). Before
issue #65 the JSON reader's depth check was quadratic in an unterminated string full of escaped
quotes (``[`` x 70, ``"``, ``\\"`` ...): 8 KiB 0.3 s, 16 KiB 1.2 s, 32 KiB 4.7 s.
"""

from __future__ import annotations

import gc
import gzip
import hashlib
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.aruco_dictionary import read_dictionary_file
from brave6d.core.json_input import JsonInputError, JsonLimits, json_depth, parse_json
from brave6d.core.ply_check import read_ply_vertices
from brave6d.dataset.release.formats import read_sha256sums
from brave6d.serve.replies import ClientLimits, parse_reply, read_body

#: The largest time ratio allowed for an input four times larger (linear: 4, quadratic: 16; between
#: them, room for caches: a hash table or an array that outgrows the CPU's caches costs more per entry).
MAX_RATIO_FOR_4X = 10.0


def _best_seconds(fn: Callable[[], object], repeats: int = 3) -> float:
    """The least CPU time (this process's, so other processes on a busy machine do not count) of
    ``repeats`` runs of ``fn``; a refusal is the reader's answer, its time is what counts. The cyclic
    garbage collector is off while a run is timed (and collects between runs): its full passes over
    every live container fire at points that depend on what ran before, so they made the ratio of a
    reader that builds many small containers jump from 5 to 13 between runs; the reader's own work is
    what is timed."""
    best = float("inf")
    for _ in range(repeats):
        gc.collect()
        gc.disable()
        try:
            t0 = time.process_time()
            try:
                fn()
            except Exception:  # noqa: BLE001
                pass
            best = min(best, time.process_time() - t0)
        finally:
            gc.enable()
    return best


def _units(build: Callable[[int], bytes], size: int) -> int:
    """How many units make about ``size`` bytes of the input ``build`` makes: the inputs are sized
    past the CPU's caches (a megabyte), where time per byte no longer depends on the size."""
    return max(1, size * 1000 // len(build(1000)))


def _ratio(make: Callable[[int], Callable[[], object]], n: int) -> float:
    """Time of the reader on 4n units over its time on n units (each the best of three)."""
    small, large = make(n), make(4 * n)
    _best_seconds(small, 1)  # warm up (imports, caches)
    ratio = _best_seconds(large) / max(_best_seconds(small), 1e-4)
    print(f"time ratio for 4x the input: {ratio:.2f}")
    return ratio


# ----------------------------------------------------------------------------- JSON
#: Inputs that build a Python object per few bytes are timed from 256 KiB, the others from 1 MiB (a dict
#: of many keys outgrows the caches between 256 KiB and 1 MiB: timed from 1 MiB).
OBJECT_HEAVY = ("many numbers", "many strings with brackets")  # many keys: from 1 MiB, past the caches
JSON_SHAPES: dict[str, Callable[[int], bytes]] = {
    "unterminated string of escaped quotes": lambda n: b"[" * 70 + b'"' + b'\\"' * n,
    "escaped backslashes before quotes": lambda n: b"[" * 70 + b'"' + b'\\\\\\"' * n,
    "deep brackets": lambda n: b"[" * n + b"]" * n,
    "many numbers": lambda n: b"[" + b"1.5e3," * n + b"0]",
    "many strings with brackets": lambda n: b"[" + b'"[{\\"]",' * n + b"0]",
    "many keys": lambda n: b"{" + b",".join(b'"k%d":[{}]' % i for i in range(n)) + b"}",
}


@pytest.mark.parametrize("shape", sorted(JSON_SHAPES))
def test_the_json_reader_is_linear(shape: str) -> None:
    build = JSON_SHAPES[shape]
    limits = JsonLimits(max_bytes=64 * 2**20)

    def make(n: int) -> Callable[[], object]:
        data = build(n)
        return lambda: parse_json(data, "doc.json", limits)

    assert _ratio(make, _units(build, 2**18 if shape in OBJECT_HEAVY else 2**20)) < MAX_RATIO_FOR_4X


def test_the_depth_scan_is_linear_on_its_worst_input() -> None:
    def make(n: int) -> Callable[[], object]:
        data = b"[" * 70 + b'"' + b'\\"' * n
        return lambda: json_depth(data)

    assert _ratio(make, 2**19) < MAX_RATIO_FOR_4X


# ----------------------------------------------------------------------------- ArUco dictionary files
DICTIONARY_SHAPES: dict[str, Callable[[int], bytes]] = {
    "yaml, long line of spaces": lambda n: b"nmarkers: 1" + b" " * (50 * n) + b"x\n",
    "yaml, many entries": lambda n: b"%YAML:1.0\n---\n" + b"".join(b"k%d: 1\n" % i for i in range(n)),
    "json, nested": lambda n: b'{"a":' * n + b"1" + b"}" * n,
    "xml, nested": lambda n: b"<opencv_storage>" + b"<a>" * n + b"</a>" * n + b"</opencv_storage>",
    "xml, unclosed comment": lambda n: b"<opencv_storage><!--" + b"-" * (10 * n),
    "xml, long value": lambda n: b"<opencv_storage><a>" + b"0" * (10 * n) + b"</b>",
}


@pytest.mark.parametrize("shape", sorted(DICTIONARY_SHAPES))
def test_the_dictionary_file_reader_is_linear(tmp_path: Path, shape: str) -> None:
    def make(n: int) -> Callable[[], object]:
        path = tmp_path / f"{n}.yml"
        path.write_bytes(DICTIONARY_SHAPES[shape](n))
        return lambda: read_dictionary_file(path)

    assert _ratio(make, _units(DICTIONARY_SHAPES[shape], 2**18)) < MAX_RATIO_FOR_4X  # 4x: the 1 MB file limit


# ----------------------------------------------------------------------------- PLY points
def _ply(n: int, fmt: str, faces: bool) -> bytes:
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
            + ("element face 1\nproperty list uint int vertex_indices\n" if faces else "") + "end_header\n").encode()
    if fmt == "ascii":
        body = b"0.5 1.5 2.5\n" * n
    else:
        body = np.zeros((n, 3), "<f4").tobytes()
    return head + body + (b"4000000000 1 2 3\n" if faces and fmt == "ascii" else b"\x00\x28\x6b\xee" if faces else b"")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("faces", [False, True])
def test_the_points_ply_reader_is_linear(tmp_path: Path, fmt: str, faces: bool) -> None:
    def make(n: int) -> Callable[[], object]:
        path = tmp_path / f"{n}.ply"
        path.write_bytes(_ply(n, fmt, faces))
        return lambda: read_ply_vertices(path)

    assert _ratio(make, _units(lambda n: _ply(n, fmt, faces), 2**18 if fmt == "ascii" else 2**20)) < MAX_RATIO_FOR_4X


# ----------------------------------------------------------------------------- a release's SHA256SUMS
def test_the_checksum_list_reader_is_linear(tmp_path: Path) -> None:
    def make(n: int) -> Callable[[], object]:
        path = tmp_path / f"{n}.SHA256SUMS"
        digest = hashlib.sha256(b"").hexdigest()
        path.write_text("".join(f"{digest}  dir/{'a' * 40}_{i}.png\n" for i in range(n)))
        return lambda: read_sha256sums(path)

    assert _ratio(make, 2**18 // 110) < MAX_RATIO_FOR_4X


# ----------------------------------------------------------------------------- a client reading a server's reply
class _Reply:
    """An ``httpx`` streamed response as :func:`read_body` reads it: headers and raw pieces."""

    def __init__(self, body: bytes, encoding: str = "identity") -> None:
        self.headers = {"content-encoding": encoding}
        self.body = body

    def iter_raw(self):  # type: ignore[no-untyped-def]
        view = memoryview(self.body)
        for i in range(0, len(view), 65536):
            yield bytes(view[i:i + 65536])


@pytest.mark.parametrize("encoding", ["identity", "gzip"])
def test_the_client_reads_a_reply_in_linear_time(encoding: str) -> None:
    limits = ClientLimits(max_reply_bytes=2**30)

    def make(n: int) -> Callable[[], object]:
        text = b"[" * 60 + b'"' + b'\\"' * n
        body = gzip.compress(text) if encoding == "gzip" else text
        return lambda: parse_reply(read_body(_Reply(body, encoding), limits, "GET /x"), limits, "GET /x")

    assert _ratio(make, 2**17) < MAX_RATIO_FOR_4X


def test_a_refusal_is_still_a_refusal_at_every_size() -> None:
    """The adversarial inputs above are refused, not read, at the sizes timed (a timing of a reader
    that accepted them would time something else)."""
    for n in (20_000, 80_000):
        with pytest.raises(JsonInputError, match="nested too deeply"):
            parse_json(JSON_SHAPES["unterminated string of escaped quotes"](n), "doc.json")


# ----------------------------------------------------------------------------- the depth scan counts as a parser does
def _parser_depth(text: str) -> tuple[int, bool]:
    """The deepest nesting a JSON parser reaches in ``text`` before it stops, and whether it reached
    the end (a backslash outside a string stops a parser there)."""
    depth = deepest = 0
    inside = escaped = False
    for ch in text:
        if inside:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                inside = False
        elif ch == "\\":
            return deepest, False
        elif ch == '"':
            inside = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest, True


@given(text=st.text(alphabet='[]{}"\\a,', max_size=80), piece=st.sampled_from([1, 2, 3, 7, 1 << 20]))
@settings(max_examples=400, deadline=None)
def test_the_depth_scan_counts_brackets_outside_strings_as_a_parser_does(text: str, piece: int) -> None:
    """Escapes, quotes and brackets in any order, the scan cut into pieces of any size: the depth is
    the parser's; where a parser stops early (a backslash outside a string) it is never less."""
    import brave6d.core.json_input as json_input

    deepest, whole = _parser_depth(text)
    saved = json_input._SCAN_CHUNK
    json_input._SCAN_CHUNK = piece
    try:
        scanned = json_depth(text.encode())
    finally:
        json_input._SCAN_CHUNK = saved
    assert scanned == deepest if whole else scanned >= deepest


@given(data=st.binary(max_size=400))
@settings(max_examples=200, deadline=None)
def test_any_reply_is_json_or_one_reply_error(data: bytes) -> None:
    from brave6d.serve.replies import ReplyError

    try:
        parse_reply(read_body(_Reply(data), ClientLimits(), "GET /x"), ClientLimits(), "GET /x")
    except ReplyError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("GET /x")

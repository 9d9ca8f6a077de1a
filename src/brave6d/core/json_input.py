"""The one reader of JSON that comes from elsewhere: files (a release's ``manifest.json``, a bundle's
``scene.json`` / ``manifest.json`` / ``objects.json``, BOP's ``scene_gt.json``, an imported
``transforms.json``, pose files) and messages (the server's WebSocket messages, episode-log lines).

Every document is held to :class:`JsonLimits` before and while it is parsed:

- its size in bytes (checked before it is read into memory, for a file from its length);
- how deeply arrays and objects nest (checked on the raw text, before parsing: one linear scan of
  the brackets outside strings, :func:`json_depth`; its time grows with the length of the text and
  nothing else, whatever the text holds);
- every number's literal length (CPython refuses to convert an integer of more than 4300 digits
  with a ``ValueError`` that is no ``JSONDecodeError``, and a 100,000-digit float takes long to
  convert) and, by default, that it is finite (``NaN``, ``Infinity`` and ``1e999`` are refused: they
  are not JSON, and a NaN in a pose or a size passes every ``<`` check).

A document that breaks a limit, is not UTF-8 or not valid JSON raises :class:`JsonInputError` (a
:class:`~brave6d.core.errors.DataError`) in one line that names the file or message (``where``)
and, when known, the line and column.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from brave6d.core.errors import DataError

#: Bytes of raw text the depth scan takes at a time (its memory: a few arrays of this many entries).
_SCAN_CHUNK = 1 << 20


#: A key shown as ``.key`` in a field's name (others as ``['key']``).
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class JsonInputError(DataError):
    """A JSON document that is malformed (``syntax``: a cut-off document is one) or breaks a
    :class:`JsonLimits` limit."""

    def __init__(self, message: str, syntax: bool = False) -> None:
        super().__init__(message)
        self.syntax = syntax


@dataclass(frozen=True)
class JsonLimits:
    """What one JSON document may hold (defaults in docs/SECURITY.md)."""

    max_bytes: int = 256 * 2**20  # the largest member the zip reader reads into memory
    max_depth: int = 64  # nested arrays / objects; the project's deepest file nests 6
    max_number_chars: int = 100  # characters of one number literal (a float64's repr has at most 24)
    finite: bool = True  # NaN, Infinity and literals that overflow to inf are refused

    def __post_init__(self) -> None:
        for name in ("max_bytes", "max_depth", "max_number_chars"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"JsonLimits.{name} must be an integer >= 1, got {value!r}")


DEFAULT_LIMITS = JsonLimits()


class _Refused(Exception):
    """Raised inside the parser's hooks; becomes a :class:`JsonInputError` naming the field."""


def parse_json(data: bytes | str, where: str, limits: JsonLimits = DEFAULT_LIMITS) -> Any:
    """Parse the JSON document ``data`` held to ``limits``; errors are :class:`JsonInputError`
    starting with ``where`` (the file, ``zip:member`` or ``message``) and, for a refused number,
    naming its field (``field 'camera.K[0][2]'``)."""
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else bytes(data)
    if len(raw) > limits.max_bytes:
        raise JsonInputError(f"{where}: {len(raw)} bytes of JSON (at most {limits.max_bytes} are read)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise JsonInputError(f"{where}: not UTF-8 text (byte {exc.start})") from None
    _check_depth(raw, where, limits.max_depth)
    try:
        return _loads(text, limits, _raise)
    except _Refused:
        field, why = _first_refused(_loads(text, limits, _Marked))
        named = f"field '{field}': " if field else ""
        raise JsonInputError(f"{where}: {named}{why}") from None
    except json.JSONDecodeError as exc:
        raise JsonInputError(f"{where}: not valid JSON (line {exc.lineno} column {exc.colno}: {exc.msg})",
                             syntax=True) from None
    except RecursionError:  # not reached within max_depth; kept for callers with a huge limit
        raise JsonInputError(f"{where}: JSON nested too deeply to read") from None


class _Marked:
    """A refused number in the second parse, which finds the field (see :func:`_first_refused`)."""

    def __init__(self, why: str) -> None:
        self.why = why


def _raise(why: str) -> Any:
    raise _Refused(why)


def _loads(text: str, limits: JsonLimits, refuse: Callable[[str], Any]) -> Any:
    """``json.loads`` whose numbers are held to ``limits``; a refused one is ``refuse(why)``."""
    def parse_int(literal: str) -> Any:
        if len(literal) > limits.max_number_chars:
            return refuse(_too_long(literal, limits))
        return int(literal)

    def parse_float(literal: str) -> Any:
        if len(literal) > limits.max_number_chars:
            return refuse(_too_long(literal, limits))
        value = float(literal)
        if limits.finite and not math.isfinite(value):
            return refuse(f"the number {literal} overflows a 64-bit float (only finite numbers are read)")
        return value

    def parse_constant(name: str) -> Any:
        if limits.finite:
            return refuse(f"{name} is not a JSON number (only finite numbers are read)")
        return float(name)

    return json.loads(text, parse_int=parse_int, parse_float=parse_float, parse_constant=parse_constant)


def _too_long(literal: str, limits: JsonLimits) -> str:
    return f"a number of {len(literal)} characters (at most {limits.max_number_chars} are read)"


def _key(field: str, key: str) -> str:
    """``field.key`` (``key`` alone at the top), or ``field['key']`` for a key that is no identifier."""
    if _IDENTIFIER.fullmatch(key) is None:
        return f"{field}[{key!r}]"
    return f"{field}.{key}" if field else key


def _first_refused(value: Any, field: str = "") -> tuple[str, str]:
    """(field, why) of the first :class:`_Marked` in ``value`` in document order (depth is bounded:
    :func:`_check_depth` ran first); ``("", "")`` when there is none."""
    if isinstance(value, _Marked):
        return field, value.why
    if isinstance(value, dict):
        items: Any = ((_key(field, k), v) for k, v in value.items())
    elif isinstance(value, list):
        items = ((f"{field}[{i}]", v) for i, v in enumerate(value))
    else:
        return "", ""
    for sub, v in items:
        found = _first_refused(v, sub)
        if found[1]:
            return found
    return "", ""


def read_json_file(path: Path | str, limits: JsonLimits = DEFAULT_LIMITS) -> Any:
    """Read and parse the JSON file ``path`` (:func:`parse_json`); a missing, unreadable, too large
    or malformed file, or one that is no regular file (a FIFO, a device), raises
    :class:`JsonInputError` naming it."""
    from brave6d.core.bounded_files import read_regular

    p = Path(path)
    data = read_regular(p, limits.max_bytes, what="JSON", error=JsonInputError)
    return parse_json(data, str(p), limits)


def _check_depth(raw: bytes, where: str, max_depth: int) -> None:
    """Refuse ``raw`` when its arrays / objects nest more than ``max_depth`` deep (outside strings)."""
    if raw.count(b"[") + raw.count(b"{") <= max_depth:
        return
    deepest = json_depth(raw)
    if deepest > max_depth:
        raise JsonInputError(f"{where}: JSON nested too deeply ({deepest} levels of arrays and objects, at most "
                             f"{max_depth} are read)")


def json_depth(raw: bytes) -> int:
    """How deeply the arrays and objects of the JSON text ``raw`` nest, brackets inside strings not
    counted: one pass over the text, in pieces of :data:`_SCAN_CHUNK` bytes, vectorised (no regular
    expression, which backtracks on an unterminated string: quadratic time).

    A quote ends a string unless an odd run of backslashes comes just before it. In text that is
    not JSON (a backslash outside a string) the count may differ from a parser's, but only after
    the point where the parser stops with a syntax error, so no parser nests deeper than this."""
    import numpy as np

    depth = deepest = 0
    in_string = 0  # 1 while the text between pieces is inside a string
    backslashes = 0  # the run of backslashes that ended the previous piece
    for start in range(0, len(raw), _SCAN_CHUNK):
        b = np.frombuffer(raw, dtype=np.uint8, count=min(_SCAN_CHUNK, len(raw) - start), offset=start)
        n = len(b)
        quotes = np.flatnonzero(b == ord('"'))
        last_other = None  # per byte: the last position at or before it that is no backslash
        slash = b == ord("\\")
        if backslashes or slash.any():
            last_other = np.maximum.accumulate(np.where(slash, np.int32(-1), np.arange(n, dtype=np.int32)))
            if len(quotes):
                before = np.where(quotes > 0, last_other[np.maximum(quotes - 1, 0)], -1)
                run = quotes - 1 - before + np.where(before < 0, backslashes, 0)  # backslashes just before
                quotes = quotes[(run & 1) == 0]  # the quotes that open or close a string
        brackets = np.flatnonzero((b == ord("[")) | (b == ord("]")) | (b == ord("{")) | (b == ord("}")))
        if len(brackets):
            outside = ((np.searchsorted(quotes, brackets) + in_string) & 1) == 0
            steps = brackets[outside]
            if len(steps):
                kinds = b[steps]
                levels = depth + np.cumsum(np.where((kinds == ord("[")) | (kinds == ord("{")), 1, -1))
                deepest = max(deepest, int(levels.max()))
                depth = int(levels[-1])
        in_string = (in_string + len(quotes)) & 1
        if last_other is None:
            backslashes = 0
        else:
            tail = n - 1 - int(last_other[-1])
            backslashes = tail + backslashes if tail == n else tail
    return deepest

"""The one reader of JSON that comes from elsewhere: files (a release's ``manifest.json``, a bundle's
``scene.json`` / ``manifest.json`` / ``objects.json``, BOP's ``scene_gt.json``, an imported
``transforms.json``, pose files) and messages (the server's WebSocket messages, episode-log lines).

Every document is held to :class:`JsonLimits` before and while it is parsed:

- its size in bytes (checked before it is read into memory, for a file from its length);
- how deeply arrays and objects nest (checked on the raw text, before parsing: a cheap scan of the
  brackets outside strings);
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

#: A JSON string literal (escapes included): removed before the brackets are counted.
_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)


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
    or malformed file raises :class:`JsonInputError` naming it."""
    p = Path(path)
    try:
        with open(p, "rb") as handle:
            size = handle.seek(0, 2)
            if size > limits.max_bytes:
                raise JsonInputError(f"{p}: {size} bytes of JSON (at most {limits.max_bytes} are read)")
            handle.seek(0)
            data = handle.read(limits.max_bytes + 1)
    except FileNotFoundError:
        raise JsonInputError(f"{p}: file not found") from None
    except IsADirectoryError:
        raise JsonInputError(f"{p}: a folder, not a JSON file") from None
    except OSError as exc:
        raise JsonInputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    return parse_json(data, str(p), limits)


def _check_depth(raw: bytes, where: str, max_depth: int) -> None:
    """Refuse ``raw`` when its arrays / objects nest more than ``max_depth`` deep (outside strings)."""
    if raw.count(b"[") + raw.count(b"{") <= max_depth:
        return
    import numpy as np

    bare = np.frombuffer(_STRING.sub(b'""', raw), dtype=np.uint8)
    opens = (bare == ord("[")) | (bare == ord("{"))
    at = np.flatnonzero(opens | (bare == ord("]")) | (bare == ord("}")))
    if len(at) == 0:
        return
    depth = np.cumsum(np.where(opens[at], 1, -1), dtype=np.int64)
    deepest = int(depth.max())
    if deepest > max_depth:
        raise JsonInputError(f"{where}: JSON nested too deeply ({deepest} levels of arrays and objects, at most "
                             f"{max_depth} are read)")

"""PLY headers checked before a PLY reader allocates anything (every PLY the project reads).

plyfile allocates ``count`` rows of an element as its header declares before it reads them, so a
200-byte file whose header says ``element vertex 4000000000`` asks for tens of GB
(``MemoryError``, or an array filled half-way where memory is overcommitted). :func:`check_ply_header`
reads the header only (at most :data:`MAX_PLY_HEADER_BYTES`) and refuses, in one line naming the
file, a header that is not a PLY's, an element with more than :data:`MAX_PLY_ELEMENTS` rows, or
elements whose rows cannot fit in the bytes after the header (each row takes at least its
fixed-size properties in binary, two characters per property in ASCII; a list at least its length).
"""

from __future__ import annotations

from pathlib import Path

from brave6d.core.errors import DataError

#: Rows of one element read at most (a splat of 268 million Gaussians, about 66 GB as a 3DGS PLY).
MAX_PLY_ELEMENTS = 2**28
#: Bytes of header read before ``end_header`` must have appeared.
MAX_PLY_HEADER_BYTES = 2**20

_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
          "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


def check_ply_header(path: Path | str, max_elements: int = MAX_PLY_ELEMENTS, name: str | None = None
                     ) -> dict[str, int]:
    """The element counts of the PLY file ``path`` (``{"vertex": 1200, "face": 2000}``), once its
    header is checked as the module says; :class:`DataError` naming the file (or ``name``) otherwise."""
    p = name or str(Path(path))
    try:
        with open(path, "rb") as handle:
            head = handle.read(MAX_PLY_HEADER_BYTES)
            size = handle.seek(0, 2)
    except FileNotFoundError:
        raise DataError(f"{p}: file not found") from None
    except OSError as exc:
        raise DataError(f"{p}: cannot read ({exc.strerror or exc})") from None
    end = _header_end(head)
    if not head.startswith(b"ply") or end is None:
        raise DataError(f"{p}: not a PLY file (no 'ply' ... 'end_header' header within "
                        f"{MAX_PLY_HEADER_BYTES} bytes)")
    rows: dict[str, int] = {}
    least: dict[str, int] = {}  # bytes one row takes at least
    fmt = None
    order: list[str] = []
    for number, raw in enumerate(head[:end].decode("ascii", "replace").splitlines()[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        where = f"{p}: PLY header line {number}"
        if words[0] == "format":
            fmt = words[1] if len(words) == 3 and words[1] in _FORMATS else None
            if fmt is None:
                raise DataError(f"{where}: unknown format {raw.strip()[:60]!r} (known: {', '.join(_FORMATS)})")
        elif words[0] == "element" and len(words) == 3:
            name, count = words[1], _count(words[2], where)
            if count > max_elements:
                raise DataError(f"{where}: declares {count} '{name}' elements, more than the {max_elements} read "
                                "(MAX_PLY_ELEMENTS)")
            if name in rows:
                raise DataError(f"{where}: element '{name}' declared twice")
            rows[name], least[name] = count, 0
            order.append(name)
        elif words[0] == "property" and order:
            least[order[-1]] += _property_bytes(words, where, ascii_format=fmt == "ascii")
        else:
            raise DataError(f"{where}: not a PLY header line: {raw.strip()[:60]!r}")
    if fmt is None:
        raise DataError(f"{p}: PLY header has no 'format' line")
    need = sum(rows[name] * least[name] for name in order)
    have = size - end
    if need > have:
        biggest = max(order, key=lambda name: rows[name] * least[name])
        raise DataError(f"{p}: its PLY header declares {rows[biggest]} '{biggest}' elements ({need} bytes at least "
                        f"in all), but the file holds {have} bytes after its header")
    return rows


def _header_end(head: bytes) -> int | None:
    """The offset just after the ``end_header`` line, or None."""
    for marker in (b"\nend_header\r\n", b"\nend_header\n", b"\rend_header\r"):
        at = head.find(marker)
        if at >= 0:
            return at + len(marker)
    return None


def _count(word: str, where: str) -> int:
    if not (word.isascii() and word.isdigit() and len(word) <= 20):
        raise DataError(f"{where}: an element count (a whole number >= 0) is required, got {word[:30]!r}")
    return int(word)


def _property_bytes(words: list[str], where: str, ascii_format: bool) -> int:
    """The least bytes a property takes in one row: a scalar's size, a list's length field (an
    empty list); two characters (a digit and a separator) in ASCII."""
    if words[1:2] == ["list"] and len(words) == 5 and words[2] in _SIZES and words[3] in _SIZES:
        return 2 if ascii_format else _SIZES[words[2]]
    if len(words) == 3 and words[1] in _SIZES:
        return 2 if ascii_format else _SIZES[words[1]]
    raise DataError(f"{where}: not a PLY property: {' '.join(words)[:60]!r}")

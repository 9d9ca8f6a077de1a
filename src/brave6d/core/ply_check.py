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

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from numpy.typing import NDArray

from brave6d.core.bounded_files import open_regular
from brave6d.core.errors import DataError

#: Rows of one element read at most (a splat of 268 million Gaussians, about 66 GB as a 3DGS PLY).
MAX_PLY_ELEMENTS = 2**28
#: Bytes of header read before ``end_header`` must have appeared.
MAX_PLY_HEADER_BYTES = 2**20

_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
          "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
#: PLY scalar types as NumPy's (without the byte order).
_NUMPY = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
          "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
          "double": "f8", "float64": "f8"}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


@dataclass(frozen=True)
class PlyElement:
    """One element of a PLY header: its name, rows and properties (``(name, type)``; a list property's
    type is ``("list", count type, item type)``)."""

    name: str
    count: int
    properties: tuple[tuple[str, str | tuple[str, str, str]], ...]

    @property
    def has_lists(self) -> bool:
        return any(not isinstance(kind, str) for _, kind in self.properties)


@dataclass(frozen=True)
class PlyHeader:
    """A checked PLY header: its format, elements in file order and the offset of the data."""

    format: str
    elements: tuple[PlyElement, ...]
    data_offset: int
    size: int


def check_ply_header(path: Path | str, max_elements: int = MAX_PLY_ELEMENTS, name: str | None = None
                     ) -> dict[str, int]:
    """The element counts of the PLY file ``path`` (``{"vertex": 1200, "face": 2000}``), once its
    header is checked as the module says; :class:`DataError` naming the file (or ``name``) otherwise."""
    return {e.name: e.count for e in read_ply_header(path, max_elements, name).elements}


def read_ply_header(path: Path | str, max_elements: int = MAX_PLY_ELEMENTS, name: str | None = None) -> PlyHeader:
    """The header of the PLY file ``path``, checked as the module says (:func:`check_ply_header`)."""
    p = name or str(Path(path))
    try:
        with open_regular(path, p) as handle:  # a FIFO or a device is refused, never waited on
            head = handle.read(MAX_PLY_HEADER_BYTES)
            size = handle.seek(0, 2)
    except OSError as exc:
        raise DataError(f"{p}: cannot read ({exc.strerror or exc})") from None
    end = _header_end(head)
    if not head.startswith(b"ply") or end is None:
        raise DataError(f"{p}: not a PLY file (no 'ply' ... 'end_header' header within "
                        f"{MAX_PLY_HEADER_BYTES} bytes)")
    rows: dict[str, int] = {}
    least: dict[str, int] = {}  # bytes one row takes at least
    props: dict[str, list[tuple[str, str | tuple[str, str, str]]]] = {}
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
            element, count = words[1], _count(words[2], where)
            if count > max_elements:
                raise DataError(f"{where}: declares {count} '{element}' elements, more than the {max_elements} read "
                                "(MAX_PLY_ELEMENTS)")
            if element in rows:
                raise DataError(f"{where}: element '{element}' declared twice")
            rows[element], least[element], props[element] = count, 0, []
            order.append(element)
        elif words[0] == "property" and order:
            least[order[-1]] += _property_bytes(words, where, ascii_format=fmt == "ascii")
            kind: str | tuple[str, str, str] = words[1] if len(words) == 3 else ("list", words[2], words[3])
            props[order[-1]].append((words[-1], kind))
        else:
            raise DataError(f"{where}: not a PLY header line: {raw.strip()[:60]!r}")
    if fmt is None:
        raise DataError(f"{p}: PLY header has no 'format' line")
    need = sum(rows[element] * least[element] for element in order)
    have = size - end
    if need > have:
        biggest = max(order, key=lambda element: rows[element] * least[element])
        raise DataError(f"{p}: its PLY header declares {rows[biggest]} '{biggest}' elements ({need} bytes at least "
                        f"in all), but the file holds {have} bytes after its header")
    return PlyHeader(fmt, tuple(PlyElement(e, rows[e], tuple(props[e])) for e in order), end, size)


def read_ply_vertices(path: Path | str, name: str | None = None) -> dict[str, NDArray[Any]]:
    """The columns of the ``vertex`` element of the PLY file ``path`` (a point cloud's ``x``, ``y``,
    ``z``, ``red`` ...), read in one pass of the vertex rows alone; :class:`DataError` naming the file.

    Why not plyfile: it reads an element with list properties row by row in Python (a 10 MB file
    takes minutes and a gigabyte) and allocates a list as long as its length field claims (4e9).
    Here the vertex element must come first and hold scalar properties only (a point cloud's do);
    binary rows are one array read of exactly ``count`` rows, ASCII rows one ``numpy.loadtxt`` of
    ``count`` lines; elements after the vertices (faces, whatever their lists claim) are never read.
    """
    import numpy as np

    p = name or str(Path(path))
    header = read_ply_header(path, name=p)
    if not header.elements or header.elements[0].name != "vertex":
        raise DataError(f"{p}: a point cloud PLY starts with its 'vertex' element, this one with "
                        f"{header.elements[0].name if header.elements else 'no element'!r}")
    vertex = header.elements[0]
    if vertex.has_lists:
        listed = next(n for n, kind in vertex.properties if not isinstance(kind, str))
        raise DataError(f"{p}: vertex property '{listed}' is a list; a point cloud's vertices hold numbers only")
    names = [n for n, _ in vertex.properties]
    if len(set(names)) != len(names):
        raise DataError(f"{p}: a vertex property is declared twice ({', '.join(names)})")
    try:
        with open_regular(path, p) as handle:
            handle.seek(header.data_offset)
            if header.format == "ascii":
                import io
                import warnings

                text = io.TextIOWrapper(handle, encoding="ascii", errors="strict", newline=None)
                with warnings.catch_warnings():
                    warnings.simplefilter("error")  # an empty file or too few rows is refused, not a warning
                    table = np.loadtxt(text, dtype=np.float64, max_rows=vertex.count, ndmin=2) \
                        if vertex.count else np.zeros((0, len(names)))
                if table.shape != (vertex.count, len(names)):
                    raise ValueError(f"{table.shape[0]} rows of {table.shape[1]} numbers, the header declares "
                                     f"{vertex.count} of {len(names)}")
                return {n: table[:, i] for i, n in enumerate(names)}
            order = "<" if header.format == "binary_little_endian" else ">"
            dtype = np.dtype([(n, order + _NUMPY[kind]) for n, kind in vertex.properties])  # type: ignore[index]
            rows = np.fromfile(handle, dtype=dtype, count=vertex.count)
    except (ValueError, UnicodeDecodeError, UserWarning) as exc:
        raise DataError(f"{p}: vertex rows unreadable ({type(exc).__name__}: {str(exc)[:200]})") from None
    except OSError as exc:
        raise DataError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if len(rows) != vertex.count:
        raise DataError(f"{p}: {len(rows)} vertex rows, the header declares {vertex.count}")
    return {n: rows[n] for n in names}


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

"""Triangle-mesh PLY files: the project's one reader and writer of object-model PLYs.

Every mesh PLY the project reads or writes goes through here: the BOP models
(``models/obj_XXXXXX.ply``, millimetres), the bundle's models, the model bytes the server sends
to agents, and the synthetic test meshes. Callers convert units themselves; this module keeps
the file's numbers. (The Gaussian-splat PLY of ``brave6d.training.ply`` is a different format with its
own owner.)

Reading (plyfile: ascii and binary of either byte order): ``x y z`` as float64, faces from the
``vertex_indices`` (or ``vertex_index``) list, each polygon fan-triangulated in place
(``a b c d`` -> ``a b c``, ``a c d``), ``red green blue`` uchar as vertex colours; other
properties are ignored. A file without faces is a point cloud (``faces`` of shape (0, 3)).
Writing: binary little-endian, ``x y z [nx ny nz]`` float32, ``[red green blue]`` uchar, faces as
``list uchar int``, written atomically.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.atomic import atomic_write_bytes
from brave6d.core.errors import DataError
from brave6d.core.ply_check import check_ply_header

_FACE_LISTS = ("vertex_indices", "vertex_index")
#: plyfile memory-maps a binary face element whose lists all have this length (fast on big models).
_TRIANGLE_LISTS = {"face": {name: 3 for name in _FACE_LISTS}}


@dataclass(frozen=True)
class MeshData:
    """Triangles in the file's units: ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64 (F = 0
    for a point cloud), optional ``vertex_colors`` (V, 3) uint8 sRGB; ``source`` names the file."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    vertex_colors: NDArray[np.uint8] | None = None
    source: str = "<memory>"

    def scaled(self, factor: float) -> MeshData:
        """The same mesh with its vertices multiplied by ``factor`` (a unit change)."""
        return MeshData(self.vertices * float(factor), self.faces, self.vertex_colors, self.source)


def read_ply_mesh(source: Path | str | bytes, name: str | None = None) -> MeshData:
    """Read a mesh PLY from a path or from the file's bytes; errors are :class:`DataError` naming
    ``name`` (default: the path, or ``<PLY bytes>``)."""
    if isinstance(source, bytes):
        label = name or "<PLY bytes>"
        with tempfile.NamedTemporaryFile(suffix=".ply") as handle:  # a real file, so plyfile can memory-map it
            handle.write(source)
            handle.flush()
            return read_ply_mesh(handle.name, label)
    path = Path(source)
    label = name or str(path)
    if not path.is_file():
        raise DataError(f"{label}: mesh file not found")
    try:
        check_ply_header(path, name=label)  # element counts against the file's size, before plyfile allocates
    except DataError as exc:
        raise DataError(f"{label}: cannot read the PLY mesh ({str(exc).removeprefix(label + ': ')})") from None
    try:
        ply = _read_plydata(path)
        vertex = ply["vertex"].data
        vertices = np.stack([np.asarray(vertex[axis], dtype=np.float64) for axis in "xyz"], axis=1)
        faces = _triangles(ply["face"].data if "face" in ply else None)
        colors = _vertex_colors(vertex)
    except DataError as exc:
        raise DataError(f"{label}: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - plyfile raises many types on broken files
        raise DataError(f"{label}: cannot read the PLY mesh ({type(exc).__name__}: {exc})") from None
    if len(vertices) == 0:
        raise DataError(f"{label}: the PLY mesh has no vertices")
    if not np.all(np.isfinite(vertices)):
        raise DataError(f"{label}: vertices contain NaN or inf")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise DataError(f"{label}: a face refers to a vertex outside 0..{len(vertices) - 1}")
    return MeshData(vertices, faces, colors, label)


def _read_plydata(path: Path) -> Any:
    """The parsed file: memory-mapped when every face is a triangle, else read row by row."""
    from plyfile import PlyData, PlyElementParseError

    try:
        return PlyData.read(str(path), mmap="c", known_list_len=_TRIANGLE_LISTS)
    except PlyElementParseError:  # a face that is not a triangle (or a broken file): the general reader
        return PlyData.read(str(path), mmap=False)


def _triangles(face: NDArray[Any] | None) -> NDArray[np.int64]:
    """(F, 3) triangles of a PLY face element; polygons are fan-triangulated in file order."""
    if face is None or len(face) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    names = face.dtype.names or ()
    list_name = next((n for n in _FACE_LISTS if n in names), None)
    if list_name is None:
        raise DataError(f"the face element has no {' or '.join(_FACE_LISTS)} list")
    polygons = face[list_name]
    if polygons.dtype != object:  # memory-mapped fixed-length triangles, shape (F, 3)
        return np.array(polygons, dtype=np.int64).reshape(-1, 3)
    lengths = np.fromiter((len(p) for p in polygons), dtype=np.int64, count=len(polygons))
    if np.any(lengths < 3):
        raise DataError("a face has fewer than three vertices")
    flat = np.concatenate([np.asarray(p, dtype=np.int64) for p in polygons])
    if np.all(lengths == 3):
        return flat.reshape(-1, 3)
    per_polygon = lengths - 2
    polygon = np.repeat(np.arange(len(lengths)), per_polygon)
    first = (np.cumsum(lengths) - lengths)[polygon]
    k = np.arange(int(per_polygon.sum())) - np.repeat(np.cumsum(per_polygon) - per_polygon, per_polygon) + 1
    return np.stack([flat[first], flat[first + k], flat[first + k + 1]], axis=1)


def _vertex_colors(vertex: NDArray[Any]) -> NDArray[np.uint8] | None:
    names = vertex.dtype.names or ()
    if not all(c in names and vertex.dtype[c] == np.uint8 for c in ("red", "green", "blue")):
        return None
    return np.stack([np.array(vertex[c], dtype=np.uint8) for c in ("red", "green", "blue")], axis=1)


def write_ply_mesh(path: Path | str, vertices: ArrayLike, faces: ArrayLike, normals: ArrayLike | None = None,
                   vertex_colors: ArrayLike | None = None, comment: str | None = None) -> Path:
    """Write a binary little-endian mesh PLY atomically (layout in the module docstring); returns the path."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if vertex_colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vert = np.empty(len(v), dtype=fields)
    vert["x"], vert["y"], vert["z"] = v[:, 0], v[:, 1], v[:, 2]
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64).reshape(len(v), 3)
        vert["nx"], vert["ny"], vert["nz"] = n[:, 0], n[:, 1], n[:, 2]
    if vertex_colors is not None:
        c = np.asarray(vertex_colors, dtype=np.uint8).reshape(len(v), 3)
        vert["red"], vert["green"], vert["blue"] = c[:, 0], c[:, 1], c[:, 2]
    face = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = f
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {name}\n" for name, t in fields)
    comment_line = f"comment {comment}\n" if comment is not None else ""
    header = (f"ply\nformat binary_little_endian 1.0\n{comment_line}element vertex {len(v)}\n{props}"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    return atomic_write_bytes(path, header.encode("ascii") + vert.tobytes() + face.tobytes())

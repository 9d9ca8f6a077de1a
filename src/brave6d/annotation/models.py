"""Object meshes for BOP: load (PLY through :mod:`brave6d.annotation.ply_mesh`, other formats through
trimesh), write the BOP model PLY in millimetres, models_info entries.

BOP models are triangle meshes in millimetres (``models/obj_XXXXXX.ply``) with per-vertex
normals and, when the source has them, vertex colours. ``models_info.json`` holds per object
the bounding box (``min_x.., size_x..``), the ``diameter`` (largest distance between two
vertices, computed on the convex hull: the farthest pair of a point set are hull vertices) and
the symmetries (discrete: flattened 4x4 with translation in mm; continuous: ``{axis, offset}``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import ConvexHull
from scipy.spatial.distance import cdist

from brave6d.annotation.ply_mesh import MeshData, read_ply_mesh, write_ply_mesh
from brave6d.core.errors import DataError


def load_mesh(path: Path | str, what: str = "", colors: bool = True) -> MeshData:
    """Load a mesh file as one triangle mesh (pieces concatenated); errors name ``what`` and the file.

    ``colors``: keep vertex colours (for non-PLY formats textures are sampled at the vertices);
    off for occluders.
    """
    p = Path(path)
    prefix = f"{what}: " if what else ""
    if not p.is_file():
        raise DataError(f"{prefix}mesh not found: {p}")
    if p.suffix.lower() == ".ply":
        ply = read_ply_mesh(p, f"{prefix}{p}")
        if len(ply.faces) == 0:
            raise DataError(f"{prefix}{p}: the file holds no triangles")
        return MeshData(ply.vertices, ply.faces, ply.vertex_colors if colors else None, str(p))
    try:
        mesh = trimesh.load(str(p), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many exception types on broken files
        raise DataError(f"{prefix}{p}: cannot load mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise DataError(f"{prefix}{p}: the file holds no triangles")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if not np.all(np.isfinite(vertices)):
        raise DataError(f"{prefix}{p}: vertices contain NaN or inf")
    return MeshData(vertices, faces, _vertex_colors(mesh) if colors else None, str(p))


def _vertex_colors(mesh: trimesh.Trimesh) -> NDArray[np.uint8] | None:
    visual = mesh.visual
    kind = getattr(visual, "kind", None)
    try:
        if kind == "vertex":
            colors = np.asarray(visual.vertex_colors)
        elif kind == "texture":
            colors = np.asarray(visual.to_color().vertex_colors)
        else:
            return None
    except Exception:  # a texture without UVs or image: no colours rather than failing
        return None
    if colors.ndim != 2 or colors.shape[0] != len(mesh.vertices) or colors.shape[1] < 3:
        return None
    return np.ascontiguousarray(colors[:, :3], dtype=np.uint8)


def vertex_normals(vertices: ArrayLike, faces: ArrayLike) -> NDArray[np.float64]:
    """Area-weighted unit vertex normals (zero for vertices used by no face)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    face_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normals = np.zeros_like(v)
    for k in range(3):
        np.add.at(normals, f[:, k], face_n)
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, norm, out=np.zeros_like(normals), where=norm > 0)


def diameter(points: ArrayLike, chunk: int = 2048) -> float:
    """Largest distance between two points (computed over the convex hull's vertices)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 2:
        return 0.0
    try:
        pts = pts[ConvexHull(pts).vertices]
    except Exception:  # flat or degenerate point sets (QhullError): use every point
        pass
    best = 0.0
    for start in range(0, len(pts), chunk):
        best = max(best, float(cdist(pts[start:start + chunk], pts[start:]).max()))
    return best


#: The public name of :func:`diameter` (``brave6d.annotation.model_diameter``).
model_diameter = diameter


def write_ply(path: Path | str, vertices: ArrayLike, faces: ArrayLike, vertex_colors: ArrayLike | None = None,
              comment: str = "BRAVE-6D BOP model (millimetres)") -> Path:
    """The BOP model PLY: x y z, area-weighted normals, [red green blue], triangles (atomic)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    return write_ply_mesh(path, v, f, vertex_normals(v, f), vertex_colors, comment)


def model_info_mm(vertices_mm: ArrayLike, symmetries_discrete: Sequence[ArrayLike] = (),
                  symmetries_continuous: Sequence[tuple[Sequence[float], Sequence[float]]] = ()) -> dict[str, Any]:
    """One ``models_info.json`` entry. Inputs in millimetres (discrete: 4x4, continuous: (axis, offset))."""
    v = np.asarray(vertices_mm, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    info: dict[str, Any] = {
        "diameter": diameter(v),
        "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
        "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]), "size_z": float(hi[2] - lo[2]),
    }
    if len(symmetries_discrete):
        info["symmetries_discrete"] = [[float(x) for x in np.asarray(m, dtype=np.float64).reshape(-1)]
                                       for m in symmetries_discrete]
    if len(symmetries_continuous):
        info["symmetries_continuous"] = [{"axis": [float(a) for a in axis], "offset": [float(o) for o in offset]}
                                         for axis, offset in symmetries_continuous]
    return info


def write_bop_model(ply_path: Path | str, mesh: MeshData, scale_to_m: float, discrete_m: Sequence[ArrayLike],
                    continuous_mm: Sequence[tuple[Any, Any]]) -> dict[str, Any]:
    """Write ``ply_path`` (``mesh`` scaled to metres by ``scale_to_m``, stored in mm) and return its
    ``models_info.json`` entry; ``discrete_m``: symmetry transforms (4x4 or flattened, translation in
    metres); ``continuous_mm``: ``(axis, offset in mm)`` pairs."""
    vertices_mm = np.asarray(mesh.vertices, dtype=np.float64) * float(scale_to_m) * 1000.0
    write_ply(ply_path, vertices_mm, mesh.faces, mesh.vertex_colors)
    discrete = []
    for m in discrete_m:
        m_mm = np.array(m, dtype=np.float64).reshape(4, 4)
        m_mm[:3, 3] *= 1000.0
        discrete.append(m_mm)
    return model_info_mm(vertices_mm, discrete, list(continuous_mm))


def write_bop_models(models_dir: Path | str, objects: Sequence[tuple[int, Path, float, Any]]) -> Path:
    """A BOP models folder for an object library: ``obj_XXXXXX.ply`` (mm) and ``models_info.json``.

    ``objects``: ``(obj_id, mesh file, scale to metres, symmetry)`` per object; ``symmetry`` is
    None or has the scene spec's ``discrete`` (flattened 4x4, metres) and ``continuous_axes``.
    The same objects give the same bytes (a rerun keeps the checksum of a folder that the learned
    model's inputs key includes). Each file is written atomically.
    """
    from brave6d.annotation.bop_format import dump_bop_json
    from brave6d.core.atomic import atomic_write_text

    out = Path(models_dir)
    out.mkdir(parents=True, exist_ok=True)
    info: dict[int, Any] = {}
    for obj_id, mesh_file, scale, symmetry in objects:
        info[obj_id] = write_bop_model(out / f"obj_{obj_id:06d}.ply", load_mesh(mesh_file, f"object {obj_id}"), scale,
                                       symmetry.discrete if symmetry is not None else [],
                                       [(axis, (0.0, 0.0, 0.0)) for axis in
                                        (symmetry.continuous_axes if symmetry is not None else [])])
    atomic_write_text(out / "models_info.json", dump_bop_json(info))
    return out

"""The target's model as the agent uses it: a seeded surface sample in metres with normals and,
when the model PLY has vertex colours, the colour at each point."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ModelOptions:
    """How the model is sampled."""

    points: int = 2000  # surface points drawn
    seed: int = 0


@dataclass(frozen=True)
class ModelCloud:
    """A surface sample of an object model in metres (model frame), with face normals and the
    model's colour at each point (``colors`` (N, 3) in [0, 1]; None: the model has none)."""

    obj_id: int
    points: Array
    normals: Array
    diameter_m: float
    extents: Array  # sorted (descending) extents along the principal axes
    colors: Array | None = None


def principal_extents(points: Array, lo: float = 2.0, hi: float = 98.0) -> Array:
    """Extents (sorted, descending) of a point set along its principal axes (robust percentiles)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 3:
        return np.zeros(3)
    centred = pts - pts.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    proj = centred @ vt.T
    ext = np.percentile(proj, hi, axis=0) - np.percentile(proj, lo, axis=0)
    return np.sort(np.pad(ext, (0, 3 - len(ext))))[::-1]


def sample_model(obj_id: int, vertices_mm: Array, faces: NDArray[np.int64] | None, diameter_mm: float,
                 n: int = 2000, seed: int = 0, vertex_colors: NDArray[np.uint8] | None = None) -> ModelCloud:
    """``n`` points drawn uniformly (by area, seeded) on the model's surface, mm -> m, with outward
    face normals (a mesh wound inwards, by its signed volume, is flipped); a model without faces
    is used as a point cloud with normals pointing away from its centroid. ``vertex_colors``
    (V, 3) uint8: each point's colour, interpolated over its triangle (the points do not change)."""
    v = np.asarray(vertices_mm, dtype=np.float64).reshape(-1, 3) / 1000.0
    vc = None
    if vertex_colors is not None:
        vc = np.asarray(vertex_colors, dtype=np.float64).reshape(-1, 3) / 255.0
        if len(vc) != len(v):
            raise BraveError(f"object {obj_id}: {len(vc)} vertex colours for {len(v)} vertices")
    rng = np.random.default_rng(seed)
    colors = None
    if faces is None or len(faces) == 0:
        idx = rng.choice(len(v), size=min(n, len(v)), replace=False)
        pts = v[idx]
        colors = vc[idx] if vc is not None else None
        normals = pts - pts.mean(axis=0)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    else:
        f = np.asarray(faces, dtype=np.int64)
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        cross = np.cross(b - a, c - a)
        area = 0.5 * np.linalg.norm(cross, axis=1)
        keep = area > 0
        if not np.any(keep):
            raise BraveError(f"object {obj_id}: the model has no triangle with a positive area")
        a, b, c, cross, area, f = a[keep], b[keep], c[keep], cross[keep], area[keep], f[keep]
        if float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c)))) < 0:  # inward winding: flip
            cross = -cross
        tri = rng.choice(len(area), size=n, p=area / area.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        pts = (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]
        normals = cross[tri] / np.linalg.norm(cross[tri], axis=1, keepdims=True)
        if vc is not None:
            ft = f[tri]
            colors = ((1 - s)[:, None] * vc[ft[:, 0]] + (s * (1 - r2))[:, None] * vc[ft[:, 1]]
                      + (s * r2)[:, None] * vc[ft[:, 2]])
    return ModelCloud(int(obj_id), pts, normals, float(diameter_mm) / 1000.0, principal_extents(pts), colors)


def read_model_ply(data: bytes) -> tuple[Array, NDArray[np.int64] | None, NDArray[np.uint8] | None]:
    """Vertices (mm), triangles (None for a point cloud) and vertex colours (None without) of a PLY
    file's bytes (what ``GET /bundle/models/{id}`` sends)."""
    from brave6d.annotation import read_ply_mesh

    mesh = read_ply_mesh(data, "the object model PLY")
    return mesh.vertices, (mesh.faces if len(mesh.faces) else None), mesh.vertex_colors

"""The target's model as the agent uses it: a seeded surface sample in metres with normals."""

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
    """A surface sample of an object model in metres (model frame), with face normals."""

    obj_id: int
    points: Array
    normals: Array
    diameter_m: float
    extents: Array  # sorted (descending) extents along the principal axes


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
                 n: int = 2000, seed: int = 0) -> ModelCloud:
    """``n`` points drawn uniformly (by area, seeded) on the model's surface, mm -> m, with outward
    face normals (a mesh wound inwards, by its signed volume, is flipped); a model without faces
    is used as a point cloud with normals pointing away from its centroid."""
    v = np.asarray(vertices_mm, dtype=np.float64).reshape(-1, 3) / 1000.0
    rng = np.random.default_rng(seed)
    if faces is None or len(faces) == 0:
        idx = rng.choice(len(v), size=min(n, len(v)), replace=False)
        pts = v[idx]
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
        a, b, c, cross, area = a[keep], b[keep], c[keep], cross[keep], area[keep]
        if float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c)))) < 0:  # inward winding: flip
            cross = -cross
        tri = rng.choice(len(area), size=n, p=area / area.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        pts = (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]
        normals = cross[tri] / np.linalg.norm(cross[tri], axis=1, keepdims=True)
    return ModelCloud(int(obj_id), pts, normals, float(diameter_mm) / 1000.0, principal_extents(pts))


def read_model_ply(data: bytes) -> tuple[Array, NDArray[np.int64] | None]:
    """Vertices (mm) and triangles (None for a point cloud) of a PLY file's bytes (what
    ``GET /bundle/models/{id}`` sends)."""
    from brave6d.annotation import read_ply_mesh

    mesh = read_ply_mesh(data, "the object model PLY")
    return mesh.vertices, (mesh.faces if len(mesh.faces) else None)

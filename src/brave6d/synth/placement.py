"""Physically plausible resting poses on a support plane (z = 0) without interpenetration.

:func:`resting_poses` gives the stable poses of a mesh (trimesh's quasi-static analysis of its
convex hull: the faces it can rest on and how likely each is); a flat or needle-like mesh, whose
hull has no volume, lies on its widest side instead (principal axes), and a mesh without extent is
a :class:`~brave6d.core.errors.DegenerateGeometryError`. :func:`place_on_plane` drops meshes one by one
at a random stable pose, yaw and position in a disc, lowest point exactly on the plane, and keeps
a candidate only if its footprint (the convex hull of its points projected on the plane) is at
least ``clearance`` away from every placed footprint: disjoint footprints of bodies resting on a
plane cannot interpenetrate, so the check is conservative (no stacking) and exact.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.transforms import make_transform, transform_points

#: Candidate positions tried per mesh before it is left out of the image.
DEFAULT_TRIES = 40
_MIN_EXTENT_M = 1e-6
_MIN_HULL_VOLUME_REL = 1e-9


@dataclass(frozen=True)
class RestingPoses:
    """Stable poses of one mesh: ``transforms`` (N, 4, 4) map model points to a frame where the
    mesh rests on z = 0 centred on the z axis; ``probabilities`` (N,) sum to 1."""

    transforms: NDArray[np.float64]
    probabilities: NDArray[np.float64]


@dataclass(frozen=True)
class Placement:
    """Where :func:`place_on_plane` put the meshes: ``world_T_model`` per mesh (None = no room)."""

    poses: tuple[NDArray[np.float64] | None, ...]

    @property
    def placed(self) -> list[int]:
        """Indices of the meshes that were placed."""
        return [i for i, T in enumerate(self.poses) if T is not None]


def check_vertices(vertices: ArrayLike, where: str) -> NDArray[np.float64]:
    """(V, 3) finite vertices with some extent, else a one-line error naming ``where``."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise DegenerateGeometryError(f"{where}: expected (V, 3) vertices, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise DegenerateGeometryError(f"{where}: vertices contain NaN or inf")
    if float(np.ptp(v, axis=0).max()) < _MIN_EXTENT_M:
        raise DegenerateGeometryError(f"{where}: the mesh has no extent (all vertices within {_MIN_EXTENT_M} m)")
    return v


def resting_poses(vertices: ArrayLike, where: str = "mesh") -> RestingPoses:
    """Stable resting poses of a mesh given by its vertices (see the module docstring)."""
    v = check_vertices(vertices, where)
    found = _stable_hull_poses(v)
    if found is None:
        found = (_principal_axes_pose(v)[None], np.ones(1))
    transforms, probs = found
    out = np.stack([_rest_on_plane(T, v) for T in transforms])
    return RestingPoses(out, probs / probs.sum())


def _stable_hull_poses(v: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """trimesh's stable poses of the convex hull, or None when the hull has no volume."""
    import trimesh
    from scipy.spatial import QhullError

    extent = float(np.ptp(v, axis=0).max())
    try:
        with np.errstate(all="ignore"):  # a flat hull's mass properties divide by zero volume
            hull = trimesh.convex.convex_hull(v)
            volume = float(hull.volume)
    except (QhullError, ValueError, IndexError):
        return None
    if not np.isfinite(volume) or volume < _MIN_HULL_VOLUME_REL * extent ** 3 or not hull.is_volume:
        return None
    try:
        transforms, probs = trimesh.poses.compute_stable_poses(hull, center_mass=hull.center_mass)
    except (ValueError, IndexError, np.linalg.LinAlgError):
        return None
    transforms = np.asarray(transforms, dtype=np.float64)
    probs = np.asarray(probs, dtype=np.float64)
    good = np.all(np.isfinite(transforms.reshape(len(transforms), -1)), axis=1) & np.isfinite(probs) & (probs > 0)
    if not good.any():
        return None
    return transforms[good], probs[good]


def _principal_axes_pose(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Lie a flat or needle-like mesh on its widest side: the axis of least spread becomes z."""
    centred = v - v.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=True)  # rows: axes of decreasing spread
    R = vt.copy()
    if np.linalg.det(R) < 0:
        R[2] = -R[2]
    return make_transform(R, np.zeros(3))


def _rest_on_plane(T: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T`` followed by the shift that puts the lowest point on z = 0 and centres x, y."""
    R = _orthonormal(T[:3, :3])
    pts = v @ R.T
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return make_transform(R, [-(lo[0] + hi[0]) / 2.0, -(lo[1] + hi[1]) / 2.0, -lo[2]])


def _orthonormal(R: NDArray[np.float64]) -> NDArray[np.float64]:
    u, _, vt = np.linalg.svd(R)
    out = u @ vt
    if np.linalg.det(out) < 0:
        u[:, -1] = -u[:, -1]
        out = u @ vt
    return out


def yaw_matrix(yaw: float) -> NDArray[np.float64]:
    """Rotation by ``yaw`` (radians) about the world z axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def place_on_plane(meshes: Sequence[tuple[NDArray[np.float64], RestingPoses]], rng: np.random.Generator,
                   radius_m: float, clearance_m: float = 0.002, tries: int = DEFAULT_TRIES) -> Placement:
    """Place ``(vertices, resting poses)`` meshes in order inside a disc of ``radius_m`` around the
    origin (see the module docstring). Draws a fixed number of random numbers per try."""
    if not (radius_m >= 0 and clearance_m >= 0 and tries >= 1):
        raise ValueError(f"place_on_plane: radius {radius_m}, clearance {clearance_m} and tries {tries} out of range")
    footprints: list[NDArray[np.float64]] = []
    poses: list[NDArray[np.float64] | None] = []
    for vertices, rest in meshes:
        pose = None
        for _ in range(tries):
            k = int(rng.choice(len(rest.probabilities), p=rest.probabilities))
            yaw = float(rng.uniform(0.0, 2.0 * np.pi))
            r = radius_m * float(np.sqrt(rng.uniform(0.0, 1.0)))
            phi = float(rng.uniform(0.0, 2.0 * np.pi))
            T = make_transform(yaw_matrix(yaw), [r * np.cos(phi), r * np.sin(phi), 0.0]) @ rest.transforms[k]
            pts = transform_points(T, vertices)
            T[2, 3] -= pts[:, 2].min()  # exactly on the plane after the rotation's rounding
            outline = footprint(pts[:, :2])
            if all(separated(outline, other, clearance_m) for other in footprints):
                pose = T
                footprints.append(outline)
                break
        poses.append(pose)
    return Placement(tuple(poses))


def footprint(points_xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Convex outline (M, 2) of points on the plane, counter-clockwise; a segment or a point when
    the points are collinear (a needle lying down)."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.unique(np.asarray(points_xy, dtype=np.float64), axis=0)
    if len(pts) >= 3:
        try:
            return pts[ConvexHull(pts).vertices]
        except QhullError:
            pass
    centre = pts.mean(axis=0)
    if len(pts) == 1:
        return pts
    _, _, vt = np.linalg.svd(pts - centre)
    along = (pts - centre) @ vt[0]
    return np.stack([centre + along.min() * vt[0], centre + along.max() * vt[0]])


def separated(a: NDArray[np.float64], b: NDArray[np.float64], clearance: float) -> bool:
    """True when convex outlines ``a`` and ``b`` are more than ``clearance`` apart along some axis
    (the separating axis theorem: edge normals of both, segment directions and the centre line)."""
    axes = [*_edge_normals(a), *_edge_normals(b)]
    for thin in (a, b):  # a segment also needs its own direction (collinear segments)
        if len(thin) == 2 and np.linalg.norm(thin[1] - thin[0]) > 0:
            axes.append((thin[1] - thin[0]) / np.linalg.norm(thin[1] - thin[0]))
    centre_line = b.mean(axis=0) - a.mean(axis=0)
    if np.linalg.norm(centre_line) > 0:
        axes.append(centre_line / np.linalg.norm(centre_line))
    for n in axes:
        pa, pb = a @ n, b @ n
        if pa.max() + clearance < pb.min() or pb.max() + clearance < pa.min():
            return True
    return False


def _edge_normals(poly: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    out = []
    for i in range(len(poly)):
        edge = poly[(i + 1) % len(poly)] - poly[i]
        length = float(np.linalg.norm(edge))
        if length > 0:
            out.append(np.array([-edge[1], edge[0]]) / length)
    return out

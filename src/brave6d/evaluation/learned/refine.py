"""Depth refinement of a learned pose: the PnP translation scaled to the measured depth, then
point-to-plane ICP of the depth points in the box onto the model's surface (Open3D).

PnP on a small object's coordinates gets the image position right but the distance and the
rotation only roughly (tens of degrees on 20 px objects); the measured depth fixes both when the
start is close enough. It starts from PnP's own translation (the mask-area distance of
:mod:`~brave6d.evaluation.learned.silhouette` is the RGB-only pose's; the depth replaces it anyway). ICP keeps its result only when it is finite, moves the object by less than
half its diameter and fits at least as many depth points as the start did.

ICP runs on one Open3D thread: on several, its sums are split among TBB's threads as they steal
work, so the same inputs gave poses a few ULP apart, which the keep-or-reject test and the next
round can grow to millimetres (docs/BENCHMARKS.md, learned/bop section).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from brave6d.evaluation.agents.pointclouds import one_thread

Array = NDArray[np.float64]
#: Surface points sampled per model for ICP.
SURFACE_POINTS = 2000
#: ICP uses at most this many of the box's depth points (evenly spaced in the image's order): a near
#: object fills thousands of pixels and ICP's time grows with them (docs/BENCHMARKS.md prices it).
ICP_MAX_POINTS = 600
_MIN_POINTS = 12


@dataclass(frozen=True)
class Surface:
    """Points and outward normals (metres, model frame) sampled on a model's surface, its diameter."""

    points: Array
    normals: Array
    diameter_m: float


def sample_surface(vertices_m: Array, faces: NDArray[np.int64], diameter_m: float, seed: int = 0) -> Surface:
    """``SURFACE_POINTS`` points of the mesh, area-weighted, with their face normals (seeded)."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices_m, dtype=np.float64), np.asarray(faces, dtype=np.int64), process=False)
    points, face_index = trimesh.sample.sample_surface(mesh, SURFACE_POINTS, seed=seed)
    return Surface(np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals[face_index], dtype=np.float64),
                   float(diameter_m))


def box_points(depth_m: NDArray[np.floating], K: Array, box: tuple[float, float, float, float],
               near_m: float, far_m: float) -> Array:
    """Camera-frame points of the depth pixels inside ``box`` whose depth lies in ``[near_m, far_m]``."""
    depth = np.asarray(depth_m, dtype=np.float64)
    h, w = depth.shape
    x0, y0 = max(0, int(math.floor(box[0]))), max(0, int(math.floor(box[1])))
    x1, y1 = min(w, int(math.ceil(box[2]))), min(h, int(math.ceil(box[3])))
    if x1 <= x0 or y1 <= y0:
        return np.zeros((0, 3))
    z = depth[y0:y1, x0:x1]
    v, u = np.nonzero(np.isfinite(z) & (z >= near_m) & (z <= far_m))
    z = z[v, u]
    u, v = u + x0, v + y0
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)


def thinned(points: Array, at_most: int | None) -> Array:
    """``points`` thinned to ``at_most`` of them, evenly spaced in their order (all when None or fewer)."""
    if at_most is None or len(points) <= at_most:
        return points
    return points[np.linspace(0, len(points) - 1, int(at_most)).astype(np.int64)]


def icp_refine(cam_T_obj: Array, points_cam: Array, surface: Surface, iterations: int = 30,
               max_points: int | None = ICP_MAX_POINTS, eyes: Array | None = None) -> tuple[Array, bool, float]:
    """Point-to-plane ICP of ``points_cam`` (at most ``max_points`` of them, evenly spaced; None: all)
    onto the surface points facing the camera, in two rounds of shrinking reach (a quarter, then a
    tenth of the diameter); (pose, refined?, fit: the fraction of the depth points within 5 % of the
    diameter of the posed surface). ``eyes``: the centres (points' frame, (M, 3)) of the cameras the
    points were seen from when several were (a surface point facing any of them is a target);
    default the origin alone."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    points_cam = thinned(points_cam, None if max_points is None else max(int(max_points), _MIN_POINTS))
    if len(points_cam) < _MIN_POINTS:
        return cam_T_obj, False, 0.0
    eyes = np.zeros((1, 3)) if eyes is None else np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    d = surface.diameter_m
    reg = o3d.pipelines.registration
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_cam))
    T = np.array(cam_T_obj, dtype=np.float64)
    before = _fitness(T, points_cam, surface, 0.05 * d, cKDTree)
    for reach in (0.25 * d, 0.1 * d):
        R, t = T[:3, :3], T[:3, 3]
        posed, normals = surface.points @ R.T + t, surface.normals @ R.T
        facing = (np.einsum("mk,nk->nm", eyes, normals) - (posed * normals).sum(axis=1)[:, None] > 0).any(axis=1)
        if facing.sum() < _MIN_POINTS:
            return cam_T_obj, False, before
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(surface.points[facing]))
        target.normals = o3d.utility.Vector3dVector(surface.normals[facing])
        obj_T_cam = np.linalg.inv(T)
        with one_thread():  # repeatable: the same inputs give the same pose bit for bit (module docstring)
            res = reg.registration_icp(source, target, reach, obj_T_cam, reg.TransformationEstimationPointToPlane(),
                                       reg.ICPConvergenceCriteria(max_iteration=int(iterations)))
        M = np.asarray(res.transformation)
        if res.fitness <= 0 or not np.all(np.isfinite(M)):
            return cam_T_obj, False, before
        T = np.linalg.inv(M)
    moved = float(np.linalg.norm(T[:3, 3] - np.asarray(cam_T_obj)[:3, 3]))
    after = _fitness(T, points_cam, surface, 0.05 * d, cKDTree) if np.all(np.isfinite(T)) else 0.0
    if moved > 0.5 * d or after < before:
        return cam_T_obj, False, before
    return T, True, after


def _fitness(T: Array, points_cam: Array, surface: Surface, tol: float, tree_type: type) -> float:
    """Fraction of the depth points within ``tol`` of the posed surface."""
    posed = surface.points @ T[:3, :3].T + T[:3, 3]
    dist, _ = tree_type(posed).query(points_cam)
    return float(np.mean(dist < tol))

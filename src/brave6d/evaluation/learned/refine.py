"""Depth refinement of a learned pose: the PnP translation scaled to the measured depth, then
point-to-plane ICP of the depth points in the box onto the model's surface.

PnP on a small object's coordinates gets the image position right but the distance and the
rotation only roughly (tens of degrees on 20 px objects); the measured depth fixes both when the
start is close enough. It starts from PnP's own translation (the mask-area distance of
:mod:`~brave6d.evaluation.learned.silhouette` is the RGB-only pose's; the depth replaces it anyway).

The ICP is continuous in its inputs (issue #66 item 4: torch and ONNX Runtime differ by ~1e-7 in
the depth scale, and Open3D's ICP, with its hard correspondence reach, relative-change stopping and
a keep test on an integer count, turned that into rotations of up to 14 deg about a near-symmetry
axis, and a result kept in one run and dropped in the other): damped Gauss-Newton on a smooth
robust kernel (Tukey's biweight, 0 at the reach), Tikhonov damping toward no motion so that what the
points leave free (a rotation about a symmetry axis) stays put, at most a fixed number of steps
(stopping only on a step far below float noise), and a smooth fit score deciding keep-or-reject.
It keeps its result only when it is finite, moves the object by less than half its diameter and
fits the depth points at least as well as the start did. Plain numpy and SciPy's k-d tree: the same
inputs give the same pose bit for bit (no threads split its sums).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
#: Surface points sampled per model for ICP.
SURFACE_POINTS = 2000
#: ICP uses at most this many of the box's depth points (evenly spaced in the image's order): a near
#: object fills thousands of pixels and ICP's time grows with them (docs/BENCHMARKS.md prices it).
ICP_MAX_POINTS = 600
_MIN_POINTS = 12
#: Gauss-Newton steps per ICP round at most (each one nearest-point query of the depth points).
ICP_ITERATIONS = 30
#: Tikhonov damping toward no motion, relative to the weights' sum times the diameter squared.
ICP_DAMPING = 1e-3
_STEP_TOL = 1e-10  # rad / diameters: far below what float noise in the inputs moves a step by


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


def icp_refine(cam_T_obj: Array, points_cam: Array, surface: Surface, iterations: int = ICP_ITERATIONS,
               max_points: int | None = ICP_MAX_POINTS, eyes: Array | None = None) -> tuple[Array, bool, float]:
    """Point-to-plane ICP of ``points_cam`` (at most ``max_points`` of them, evenly spaced; None: all)
    onto the surface points facing the camera, in two rounds of shrinking reach (a quarter, then a
    tenth of the diameter); (pose, refined?, fit: the fraction of the depth points within 5 % of the
    diameter of the posed surface). ``eyes``: the centres (points' frame, (M, 3)) of the cameras the
    points were seen from when several were (a surface point facing any of them is a target);
    default the origin alone. The pose is kept when finite, moved by less than half the diameter
    and its smooth fit score (:func:`_fit_score`) is not lower than the start's."""
    from scipy.spatial import cKDTree

    start = np.asarray(cam_T_obj, dtype=np.float64)
    points_cam = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    points_cam = thinned(points_cam[np.isfinite(points_cam).all(axis=1)],
                         None if max_points is None else max(int(max_points), _MIN_POINTS))
    if len(points_cam) < _MIN_POINTS or not np.all(np.isfinite(start)):
        return start, False, 0.0
    eyes = np.zeros((1, 3)) if eyes is None else np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    d = surface.diameter_m
    tree = cKDTree(surface.points)
    before, before_score = _fit(start, points_cam, tree, d)
    T = start.copy()
    for reach in (0.25 * d, 0.1 * d):
        R, t = T[:3, :3], T[:3, 3]
        posed, normals = surface.points @ R.T + t, surface.normals @ R.T
        facing = (np.einsum("mk,nk->nm", eyes, normals) - (posed * normals).sum(axis=1)[:, None] > 0).any(axis=1)
        if facing.sum() < _MIN_POINTS:
            return start, False, before
        moved = _point_to_plane(T, points_cam, surface.points[facing], surface.normals[facing], reach, d,
                                int(iterations), cKDTree)
        if moved is None:
            return start, False, before
        T = moved
    if not np.all(np.isfinite(T)) or float(np.linalg.norm(T[:3, 3] - start[:3, 3])) > 0.5 * d:
        return start, False, before
    after, after_score = _fit(T, points_cam, tree, d)
    if after_score < before_score:
        return start, False, before
    return T, True, after


def _point_to_plane(cam_T_obj: Array, points_cam: Array, targets: Array, normals: Array, reach: float,
                    diameter: float, iterations: int, tree_type: type) -> Array | None:
    """Damped Gauss-Newton on sum_i w_i r_i^2 + lambda |xi|^2: r_i the point-to-plane distance of
    depth point i to its nearest target (model frame), w_i Tukey's biweight of the point-to-point
    distance scaled to ``reach`` (0 beyond it, smoothly), xi the motion from the start (rotation
    about the model's origin, translation in diameters) and lambda ``ICP_DAMPING`` times the
    weights' sum times the diameter squared: a motion the points do not constrain (a rotation about
    a symmetry axis) stays at none. At most ``iterations`` steps, stopping on a step under
    ``_STEP_TOL``; the pose, or None without enough weighted points."""
    tree = tree_type(targets)
    R0, t0 = cam_T_obj[:3, :3], cam_T_obj[:3, 3]
    q0 = (points_cam - t0) @ R0  # the depth points in the start's model frame
    xi = np.zeros(6)
    for _ in range(max(iterations, 1)):
        Rm = _rotation(xi[:3])
        q = q0 @ Rm.T + diameter * xi[3:]
        dist, j = tree.query(q)
        s, n = targets[j], normals[j]
        w = np.clip(1.0 - (dist / reach) ** 2, 0.0, None) ** 2
        if np.count_nonzero(w) < _MIN_POINTS:
            return None
        r = ((q - s) * n).sum(axis=1)
        J = np.hstack([np.cross(q, n), diameter * n])
        lam = ICP_DAMPING * float(w.sum()) * diameter ** 2
        H = J.T @ (w[:, None] * J) + lam * np.eye(6)
        step = -np.linalg.solve(H, J.T @ (w * r) + lam * xi)
        if not np.all(np.isfinite(step)):
            return None
        xi = xi + step
        if float(np.abs(step).max()) < _STEP_TOL:
            break
    Rm = _rotation(xi[:3])  # obj'_from_obj: q' = Rm q + d u, so cam_T_obj' = cam_T_obj @ inv(motion)
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = Rm, diameter * xi[3:]
    return cam_T_obj @ np.linalg.inv(motion)


def _rotation(omega: Array) -> Array:
    """Rodrigues: the rotation matrix of the rotation vector ``omega`` (continuous through 0)."""
    theta = float(np.linalg.norm(omega))
    K = np.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + math.sin(theta) / theta * K + (1.0 - math.cos(theta)) / theta ** 2 * K @ K


def _fit(T: Array, points_cam: Array, tree: Any, diameter: float) -> tuple[float, float]:
    """Fraction of the depth points within 5 % of the diameter of the posed surface, and the smooth
    fit score that decides keep-or-reject: the mean Tukey biweight of each point's distance to the
    surface scaled to 10 % of the diameter (a continuous function of the pose, unlike the count)."""
    q = (points_cam - T[:3, 3]) @ T[:3, :3]  # model frame: the surface's tree is built once
    dist, _ = tree.query(q)
    return float(np.mean(dist < 0.05 * diameter)), float(np.mean(np.clip(1.0 - (dist / (0.1 * diameter)) ** 2, 0.0, None) ** 2))

"""Perception: find the target's cluster of points above the table in one depth image.

Back-project the depth image, fit the table plane with RANSAC (a plane whose normal is near world
up, which the agent knows from its own ``world_T_cam``; :func:`perceive_up` takes up in the camera
frame, as the single-frame estimator has it from the table) around where the target is expected, keep
the points a little above it, cluster them with DBSCAN, and pick the cluster near that place whose
extent best fits the target's model. The plane is then refitted around the chosen cluster and the
segmentation repeated: splat depth is not flat over a whole table (each Gaussian has one depth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from brave6d.core.transforms import invert
from brave6d.evaluation.agents.model import ModelCloud, principal_extents
from brave6d.evaluation.agents.pointclouds import one_thread, open3d, point_cloud

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PerceptionOptions:
    """How the table plane is fitted."""

    plane_ransac_m: float = 0.003  # inlier distance of the table plane fit
    seed: int = 0  # RANSAC seed
    max_tilt_deg: float = 30.0  # the table's normal within this angle of world up
    plane_voxel_m: float = 0.0  # the cloud is thinned to this before the plane fit (0: plane_ransac_m)
    plane_iterations: int = 500  # RANSAC iterations of each plane fit


@dataclass(frozen=True)
class Plane:
    """``n . p + d = 0`` in the camera frame, ``n`` unit, the camera on the positive side."""

    n: Array
    d: float

    def height(self, points: Array) -> Array:
        return np.asarray(points) @ self.n + self.d


@dataclass(frozen=True)
class Cluster:
    """Points (camera frame) above the table that DBSCAN grouped together, with their pixels."""

    points: Array
    pixels: NDArray[np.int64]  # (N, 2) column, row

    @property
    def centroid(self) -> Array:
        return self.points.mean(axis=0)

    @property
    def extents(self) -> Array:
        return principal_extents(self.points)

    @property
    def box_px(self) -> float:
        """Geometric mean of the width and height of its pixel box."""
        w = self.pixels[:, 0].max() - self.pixels[:, 0].min() + 1
        h = self.pixels[:, 1].max() - self.pixels[:, 1].min() + 1
        return float(math.sqrt(w * h))


@dataclass(frozen=True)
class Perception:
    """What the agent made of one view: the table plane and the target's cluster (or None)."""

    plane: Plane | None
    cluster: Cluster | None
    candidates: int
    min_height: float = 0.0  # the cut above the plane (points below it count as table)


class View(NamedTuple):
    """One view of an episode: the server's observation (``depth``, ``K``, ``world_T_cam``) and
    what the agent made of it."""

    observation: Any
    perception: Perception


def backproject(depth: NDArray[np.floating], K: Array) -> tuple[Array, NDArray[np.int64]]:
    """Camera-frame points (m) of the valid depth pixels and their pixels (column, row).

    ``K`` is the project's (OpenCV): pixel (column, row) is centred at those integer coordinates.
    """
    d = np.asarray(depth, dtype=np.float64)
    rows, cols = np.nonzero(np.isfinite(d) & (d > 0))
    z = d[rows, cols]
    x = (cols - K[0, 2]) / K[0, 0] * z
    y = (rows - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1), np.stack([cols, rows], axis=1).astype(np.int64)


def pixels_of(points: Array, K: Array, shape: tuple[int, ...]) -> tuple[NDArray[np.int64], NDArray[np.int64],
                                                                     NDArray[np.bool_]]:
    """The inverse of :func:`backproject`: each camera-frame point's nearest pixel (column ``u``, row
    ``v``) and whether it lies in front of the camera and inside an image of ``shape`` (H, W, ...);
    ``u`` and ``v`` are 0 where it does not (NaN and inf points included)."""
    z = points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        u = np.rint(K[0, 0] * points[:, 0] / z + K[0, 2])
        v = np.rint(K[1, 1] * points[:, 1] / z + K[1, 2])
    inside = (z > 0) & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    return np.where(inside, u, 0).astype(np.int64), np.where(inside, v, 0).astype(np.int64), inside


def fit_table_plane(points: Array, up_cam: Array, distance: float, seed: int = 0, max_planes: int = 3,
                    max_tilt_deg: float = 30.0, voxel: float = 0.0, iterations: int = 500) -> Plane | None:
    """The largest RANSAC plane whose normal is within ``max_tilt_deg`` of ``up_cam`` (world up in
    the camera frame), among up to ``max_planes`` planes peeled off in turn; None if none fits."""
    o3d = open3d()
    if len(points) < 50:
        return None
    pcd = point_cloud(points).voxel_down_sample(max(voxel if voxel > 0 else distance, 1e-4))
    cos_max = math.cos(math.radians(max_tilt_deg))
    for _ in range(max_planes):
        if len(pcd.points) < 50:
            return None
        o3d.utility.random.seed(seed)
        model, inliers = pcd.segment_plane(distance, 3, int(iterations))
        n = np.asarray(model[:3], dtype=np.float64)
        norm = float(np.linalg.norm(n))
        if norm > 0 and len(inliers) >= 30:
            n, d = n / norm, float(model[3]) / norm
            if d < 0:  # camera (the origin) on the positive side
                n, d = -n, -d
            if float(n @ up_cam) >= cos_max:
                return Plane(n, d)
        pcd = pcd.select_by_index(inliers, invert=True)
    return None


def clusters_above(points: Array, pixels: NDArray[np.int64], plane: Plane, K: Array, min_height: float,
                   max_height: float, min_points: int = 8) -> list[Cluster]:
    """DBSCAN clusters of the points between ``min_height`` and ``max_height`` above ``plane``
    (eps: three pixel footprints at the points' median depth, at least 3 mm)."""
    h = plane.height(points)
    keep = (h > min_height) & (h < max_height)
    pts, pix = points[keep], pixels[keep]
    if len(pts) < min_points:
        return []
    eps = max(0.003, 3.0 * float(np.median(pts[:, 2])) / float(K[0, 0]))
    labels = np.asarray(point_cloud(pts).cluster_dbscan(eps, min_points), dtype=np.int64)
    return [Cluster(pts[labels == k], pix[labels == k]) for k in range(int(labels.max(initial=-1)) + 1)
            if np.count_nonzero(labels == k) >= min_points]


def select_cluster(clusters: list[Cluster], model: ModelCloud, anchor: Array, max_offset: float) -> Cluster | None:
    """Among the clusters whose centroid lies within ``max_offset`` of ``anchor`` (camera frame)
    and whose size is plausible for the model, the one whose largest extent best fits the
    model's (log ratio) and lies nearest ``anchor`` (in model diameters)."""
    best, best_cost = None, math.inf
    size = float(model.extents[0])
    for c in clusters:
        ext = c.extents
        offset = float(np.linalg.norm(c.centroid - anchor))
        if offset > max_offset or ext[0] > 2.0 * model.diameter_m or ext[0] < 0.2 * size:
            continue
        cost = abs(math.log(max(ext[0], 1e-6) / size)) + offset / model.diameter_m
        if cost < best_cost:
            best, best_cost = c, cost
    return best


def perceive(depth: NDArray[np.floating], K: Array, world_T_cam: Array, model: ModelCloud,
             prior_cam: Array | None, options: PerceptionOptions = PerceptionOptions()) -> Perception:
    """Find the target's cluster in one depth image (see the module docstring).

    ``prior_cam``: where the target is expected (camera frame); None: on the optical axis (the
    start view looks at the target). The plane is fitted locally: around the prior, then around
    the cluster."""
    up_cam = np.asarray(world_T_cam, dtype=np.float64)[2, :3]  # world +z in the camera frame
    return perceive_up(depth, K, up_cam, model, prior_cam, options)


def perceive_up(depth: NDArray[np.floating], K: Array, up_cam: Array, model: ModelCloud, prior_cam: Array | None,
                options: PerceptionOptions = PerceptionOptions()) -> Perception:
    """:func:`perceive` given the world's up direction in the camera frame (unit ``up_cam``)
    instead of the camera's world pose: what a frame without a world pose has (its table's normal)."""
    with one_thread():
        return _perceive(depth, K, np.asarray(up_cam, dtype=np.float64), model, prior_cam, options)


def perceive_near(observation: Any, target_w: Array, model: ModelCloud,
                  options: PerceptionOptions = PerceptionOptions()) -> Perception:
    """:func:`perceive` in an observation (``depth``, ``K``, ``world_T_cam``) with the prior where
    the target was last seen (``target_w``, world frame)."""
    cam_T_world = invert(observation.world_T_cam)
    return perceive(observation.depth, observation.K, observation.world_T_cam, model,
                    cam_T_world[:3, :3] @ target_w + cam_T_world[:3, 3], options)


def axis_anchor(points: Array, pixels: NDArray[np.int64], K: Array) -> Array:
    """The point on the optical axis at the median depth of the pixels near the principal point
    (where the start view, which looks at the target, expects it)."""
    if len(points) == 0:
        return np.array([0.0, 0.0, 0.3])
    r = np.hypot(pixels[:, 0] - K[0, 2], pixels[:, 1] - K[1, 2])
    close = points[r < max(4.0, 0.03 * K[0, 0])]
    z = float(np.median(close[:, 2])) if len(close) else float(np.median(points[:, 2]))
    return np.array([0.0, 0.0, z])


def _perceive(depth: NDArray[np.floating], K: Array, up_cam: Array, model: ModelCloud,
              prior_cam: Array | None, options: PerceptionOptions) -> Perception:
    points, pixels = backproject(depth, K)
    min_h = float(np.clip(0.15 * model.diameter_m, 0.002, 0.006))
    if len(points) < 50:
        return Perception(None, None, 0, min_h)
    anchor = np.asarray(prior_cam, dtype=np.float64) if prior_cam is not None else axis_anchor(points, pixels, K)
    max_h = 1.5 * model.diameter_m + min_h
    plane, chosen, candidates = None, None, 0
    for radius in (4.0 * model.diameter_m, 8.0 * model.diameter_m, math.inf):
        near = np.linalg.norm(points - anchor, axis=1) < radius
        plane = fit_table_plane(points[near], up_cam, options.plane_ransac_m, options.seed,
                                max_tilt_deg=options.max_tilt_deg, voxel=options.plane_voxel_m,
                                iterations=options.plane_iterations)
        if plane is None:
            continue
        clusters = clusters_above(points[near], pixels[near], plane, K, min_h, max_h)
        candidates = len(clusters)
        chosen = select_cluster(clusters, model, anchor, 2.0 * model.diameter_m)
        if chosen is not None:
            break
    if chosen is None:
        return Perception(plane, None, candidates, min_h)
    centre = chosen.centroid  # refit the plane around the chosen cluster and segment again
    near = np.linalg.norm(points - centre, axis=1) < 3.0 * model.diameter_m
    local = fit_table_plane(points[near], up_cam, options.plane_ransac_m, options.seed,
                            max_tilt_deg=options.max_tilt_deg, voxel=options.plane_voxel_m,
                            iterations=options.plane_iterations)
    if local is not None:
        refined = select_cluster(clusters_above(points[near], pixels[near], local, K, min_h, max_h), model, centre,
                                 model.diameter_m)
        if refined is not None:
            return Perception(local, refined, candidates, min_h)
    return Perception(plane, chosen, candidates, min_h)

"""A weight-free baseline agent: find the target in the depth image, move closer, register its model.

Nothing is learned and nothing is downloaded; every step is classical geometry (Open3D):

1. **Perception** (:func:`perceive`): back-project the depth image, fit the table plane with
   RANSAC (``segment_plane``; a plane whose normal is near world up, which the agent knows from
   its own ``world_T_cam``) around where the target is expected (the start view looks at the
   target: the optical axis at first), keep the points a little above it, cluster them with
   DBSCAN, and pick the cluster near that place whose extent best fits the target's model. The
   plane is then refitted around the chosen cluster and the segmentation repeated: splat depth
   is not flat over a whole table (each Gaussian has one depth).
2. **Approach** (active variant only, and only towards a target it found): while the cluster
   covers less than ``min_box_px`` (geometric mean of its pixel box), teleport along the line
   of sight so that it covers about ``approach_box_px`` (not more: MSPD counts pixels), keeping
   the elevation, but never nearer than the standoff (by default the bundle's nearest capture
   ring: closer than any training view a splat shows artefacts, not detail, so a small object may
   stay below ``min_box_px``); refused poses are retried 10 degrees higher or lower, then farther.
   A move that loses the target is followed by one look from ``relook_lift_deg`` higher (a splat
   table seen obliquely can look centimetres higher than it is and swallow a small object). Then
   it looks from ``orbit_deg`` azimuth offsets at that distance (the sides one view misses).
3. **Registration** (:func:`register_model`): the model (a surface sample of the BOP model, mm
   -> m) is aligned to the cluster with FPFH + RANSAC from several seeds, plus 48 "resting on
   the table" hypotheses (each model axis up, 8 yaws); every hypothesis is refined with
   point-to-plane ICP on the model points facing the camera, and scored by how well the model
   and the cluster explain each other, minus clear penetration of the table, model points in
   observed free space and (weakly) tilt. Voxel sizes are fractions of the model diameter, so
   tiny objects work alike. The best hypothesis is submitted, its score as the confidence; with
   no cluster at all, a guess where the target was last seen (at first: on the optical axis).
4. **Back to the start** (active, ``report_from_start``): the agent returns to its start pose
   (one more adjustment) and submits there. The start lies on the capture rings, where the splat
   was trained and its depth is trustworthy; the final view is where VSD (on that depth) and
   MSPD (in pixels) are scored.
5. **All views together** (active, :func:`register_views`): the start view's own
   registration (the static variant's answer) is refined by point-to-plane ICP on the clusters
   of every view at once, expressed in the start view's frame (the views see more sides of the
   object than one), and the refined pose is kept if it explains the views at least as well
   (reliability-weighted mean score: each view weighted by how well its own best registration
   explains it). Optionally (a finite ``switch_margin``) another view's registration, refined in
   the start view, replaces it when it scores better by more than the margin; measured over 192
   episodes on two trainings of the demo scene, switching won on one and lost on the other, so
   it is off by default.

The static variant does 1 and 3 on the first view only. The agent reads from ``GET /bundle``
only what a user of the benchmark is given about the target: its ``obj_id``, model and
diameter, never any ``world_T_obj``. Deterministic: every random choice is seeded and Open3D
runs on one thread while the agent computes (its RANSAC and parallel sums vary otherwise).
"""

from __future__ import annotations

import io
import logging
import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.errors import BraveError
from brave6d.transforms import invert, look_at, make_transform

log = logging.getLogger(__name__)

Array = NDArray[np.float64]
ACTIVE_AGENT = "baseline-active"
STATIC_AGENT = "baseline-static"
UPRIGHT_WEIGHT = 0.1  # weight of the "resting on a face" prior in the registration score
DEFAULT_STANDOFF_M = 0.10  # nearest approach when neither the config nor the bundle says


@dataclass(frozen=True)
class BaselineConfig:
    """What shapes the baseline; distances in metres, sizes relative to the model diameter."""

    active: bool = True
    min_box_px: float = 32.0  # move while the target's box (geometric mean of w, h) is smaller
    approach_box_px: float = 40.0  # ... aiming for about this size (MSPD, in pixels, punishes large boxes)
    max_moves: int = 4
    min_distance_m: float | None = None  # never nearer (nor than 3 diameters); None: the nearest capture ring
    min_elevation_deg: float = 0.0  # also move when the target is seen from lower than this
    approach_elevation_deg: float | None = None  # None: keep the elevation (at least the minimum)
    relook_lift_deg: float = 30.0  # a move lost the target: look again from this much higher
    orbit_deg: tuple[float, ...] = (35.0, -35.0)  # then look from these azimuth offsets too (active)
    select_across_views: bool = True  # active: weigh every view's registration against all views
    view_weighting: str = "reliability"  # "mean": every view alike; "reliability": by its own best score
    report_from_start: bool = True  # active: go back to the start view to submit (step 5)
    switch_margin: float | None = math.inf  # keep the final view's own fit unless outvoted by this; None: best mean
    multiview_refine: bool = True  # active: ICP the submitted pose onto all the views' clusters at once
    refine_in_final_view: bool = True  # switch_margin None: ICP the chosen pose onto the final view's cluster
    plane_ransac_m: float = 0.003  # inlier distance of the table plane fit
    voxel_fraction: float = 0.08  # registration voxel = fraction x diameter
    ransac_seeds: tuple[int, ...] = (0, 1, 2, 3)
    ransac_iterations: int = 20_000
    yaw_steps: int = 8  # resting hypotheses: 6 up-axes x yaw_steps
    model_points: int = 2000
    seed: int = 0

    @property
    def agent(self) -> str:
        return ACTIVE_AGENT if self.active else STATIC_AGENT


def _o3d() -> Any:
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - open3d is a dependency
        raise BraveError(f"the baseline agent needs Open3D ({exc})") from None
    return o3d


@contextmanager
def one_thread() -> Iterator[None]:
    """Open3D on one thread for the duration: its seeded RANSAC and its parallel sums (ICP,
    plane fits) are reproducible only then; the agent's clouds are small, so it costs little."""
    o3d = _o3d()
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(threads)


def _cloud(points: Array, normals: Array | None = None) -> Any:
    o3d = _o3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals, dtype=np.float64))
    return pcd


# ----------------------------------------------------------------------------- the model
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
    import trimesh

    try:
        geom = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types on broken files
        raise BraveError(f"cannot read the object model PLY ({type(exc).__name__}: {exc})") from None
    verts = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    if len(verts) == 0:
        raise BraveError("the object model PLY has no vertices")
    faces = getattr(geom, "faces", None)
    return verts, (np.asarray(faces, dtype=np.int64) if faces is not None and len(faces) else None)


# ----------------------------------------------------------------------------- perception
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


def fit_table_plane(points: Array, up_cam: Array, distance: float, seed: int = 0, max_planes: int = 3,
                    max_tilt_deg: float = 30.0) -> Plane | None:
    """The largest RANSAC plane whose normal is within ``max_tilt_deg`` of ``up_cam`` (world up in
    the camera frame), among up to ``max_planes`` planes peeled off in turn; None if none fits."""
    o3d = _o3d()
    if len(points) < 50:
        return None
    pcd = _cloud(points).voxel_down_sample(max(distance, 1e-4))
    cos_max = math.cos(math.radians(max_tilt_deg))
    for _ in range(max_planes):
        if len(pcd.points) < 50:
            return None
        o3d.utility.random.seed(seed)
        model, inliers = pcd.segment_plane(distance, 3, 500)
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
    labels = np.asarray(_cloud(pts).cluster_dbscan(eps, min_points), dtype=np.int64)
    return [Cluster(pts[labels == k], pix[labels == k]) for k in range(int(labels.max(initial=-1)) + 1)
            if np.count_nonzero(labels == k) >= min_points]


def select_cluster(clusters: list[Cluster], model: ModelCloud, anchor: Array, max_offset: float) -> Cluster | None:
    """Among the clusters whose centroid lies within ``max_offset`` of ``anchor`` (camera frame)
    and whose size is plausible for the model, the one whose largest extent best fits the
    model's (log ratio), plus its distance to ``anchor`` in model diameters."""
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
             prior_cam: Array | None, config: BaselineConfig) -> Perception:
    """Find the target's cluster in one depth image (see the module docstring, step 1).

    ``prior_cam``: where the target is expected (camera frame); None: on the optical axis (the
    start view looks at the target). Splat depth is not flat over a whole table (each Gaussian
    has one depth), so the plane is fitted locally: around the prior, then around the cluster."""
    with one_thread():
        return _perceive(depth, K, world_T_cam, model, prior_cam, config)


def _perceive(depth: NDArray[np.floating], K: Array, world_T_cam: Array, model: ModelCloud,
              prior_cam: Array | None, config: BaselineConfig) -> Perception:
    points, pixels = backproject(depth, K)
    min_h = float(np.clip(0.15 * model.diameter_m, 0.002, 0.006))
    if len(points) < 50:
        return Perception(None, None, 0, min_h)
    up_cam = np.asarray(world_T_cam, dtype=np.float64)[2, :3]  # world +z in the camera frame
    anchor = np.asarray(prior_cam, dtype=np.float64) if prior_cam is not None else _axis_anchor(points, pixels, K)
    max_h = 1.5 * model.diameter_m + min_h
    plane, chosen, candidates = None, None, 0
    for radius in (4.0 * model.diameter_m, 8.0 * model.diameter_m, math.inf):
        near = np.linalg.norm(points - anchor, axis=1) < radius
        plane = fit_table_plane(points[near], up_cam, config.plane_ransac_m, config.seed)
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
    local = fit_table_plane(points[near], up_cam, config.plane_ransac_m, config.seed)
    if local is not None:
        refined = select_cluster(clusters_above(points[near], pixels[near], local, K, min_h, max_h), model, centre,
                                 model.diameter_m)
        if refined is not None:
            return Perception(local, refined, candidates, min_h)
    return Perception(plane, chosen, candidates, min_h)


def _axis_anchor(points: Array, pixels: NDArray[np.int64], K: Array) -> Array:
    """The point on the optical axis at the median depth of the pixels near the principal point."""
    if len(points) == 0:
        return np.array([0.0, 0.0, 0.3])
    r = np.hypot(pixels[:, 0] - K[0, 2], pixels[:, 1] - K[1, 2])
    close = points[r < max(4.0, 0.03 * K[0, 0])]
    z = float(np.median(close[:, 2])) if len(close) else float(np.median(points[:, 2]))
    return np.array([0.0, 0.0, z])


# ----------------------------------------------------------------------------- registration
@dataclass(frozen=True)
class Registration:
    """``cam_T_obj`` of the best hypothesis, its score (higher is better, at most 1) and how it
    was found ("ransac", "resting", "centroid"; "axis": no cluster, a guess on the optical axis)."""

    cam_T_obj: Array
    score: float
    fitness: float
    method: str
    hypotheses: int


def _visible(model: ModelCloud, cam_T_obj: Array) -> NDArray[np.int64]:
    """Indices of the model points whose (outward) normal faces the camera under ``cam_T_obj``
    (back-face culling; self-occlusion of concave parts is ignored)."""
    R, t = cam_T_obj[:3, :3], cam_T_obj[:3, 3]
    facing = np.einsum("ij,ij->i", model.normals @ R.T, model.points @ R.T + t) < 0.0
    idx = np.flatnonzero(facing)
    return idx if len(idx) >= 10 else np.arange(len(model.points))


@dataclass
class _Scene:
    """The cluster and what scoring needs about the view."""

    points: Array
    tree: Any  # scipy cKDTree of points
    plane: Plane | None
    min_height: float  # the segmentation's cut above the plane
    depth: NDArray[np.floating]
    K: Array
    tol: float


def _score(model: ModelCloud, T: Array, scene: _Scene) -> tuple[float, float]:
    """(score, fitness) of ``T``. Fitness: mean of the fraction of cluster points near the model
    and the fraction of visible model points above the segmentation cut near the cluster. Score:
    fitness minus the fractions of model points deep below the table (splat tables look higher
    than they are, so only clear penetration counts) and of visible model points in observed
    free space (the depth image sees through them), and a small penalty for tilt (:func:`_tilt`)."""
    from scipy.spatial import cKDTree

    vis = _visible(model, T)
    pts = model.points[vis] @ T[:3, :3].T + T[:3, 3]
    d_scene, _ = cKDTree(pts).query(scene.points)
    covered = pts
    below = 0.0
    if scene.plane is not None:
        covered = pts[scene.plane.height(pts) > scene.min_height]
        all_pts = model.points @ T[:3, :3].T + T[:3, 3]
        below = float(np.mean(scene.plane.height(all_pts) < -(0.25 * model.diameter_m + scene.tol)))
    coverage = float(np.mean(scene.tree.query(covered)[0] < scene.tol)) if len(covered) else 0.0
    fitness = 0.5 * (float(np.mean(d_scene < scene.tol)) + coverage)
    return fitness - below - _free_space(pts, scene) - UPRIGHT_WEIGHT * _tilt(T, scene.plane), fitness


def _tilt(T: Array, plane: Plane | None) -> float:
    """0 when a model axis is along the table normal, up to 1 at the largest possible tilt: a weak
    prior that objects rest on a face (breaks near-ties between flipped and tilted fits)."""
    if plane is None:
        return 0.0
    cos = float(np.max(np.abs(T[:3, :3].T @ plane.n)))
    return math.degrees(math.acos(min(1.0, cos))) / math.degrees(math.acos(1.0 / math.sqrt(3.0)))


def _free_space(pts: Array, scene: _Scene) -> float:
    """Fraction of camera-frame points that the depth image sees through (observed depth farther
    than the point by more than the tolerance); 1 when a point is behind the camera."""
    z = pts[:, 2]
    if np.any(z <= 1e-3):
        return 1.0
    h, w = scene.depth.shape
    u = np.rint(scene.K[0, 0] * pts[:, 0] / z + scene.K[0, 2]).astype(np.int64)
    v = np.rint(scene.K[1, 1] * pts[:, 1] / z + scene.K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    observed = scene.depth[v[inside], u[inside]]
    valid = observed > 0
    if not np.any(valid):
        return 0.0
    return float(np.mean(observed[valid] > z[inside][valid] + scene.tol))


def _icp(model: ModelCloud, T: Array, scene: _Scene, scene_pcd: Any, voxel: float) -> Array:
    """Point-to-plane ICP of the cluster onto the visible model points; returns the refined
    ``cam_T_obj``."""
    return _icp_rounds(model, T, scene_pcd, lambda T_now: _visible(model, T_now), voxel)


def _icp_rounds(model: ModelCloud, T: Array, source: Any, facing: Any, voxel: float) -> Array:
    """Two rounds of point-to-plane ICP of the ``source`` cloud onto the model points that
    ``facing(T)`` selects for the current pose, shrinking the correspondence distance."""
    reg = _o3d().pipelines.registration
    for dist in (3.0 * voxel, 1.5 * voxel):
        vis = facing(T)
        target = _cloud(model.points[vis], model.normals[vis])
        res = reg.registration_icp(source, target, dist, invert(T), reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(max_iteration=30))
        if res.fitness > 0 and np.all(np.isfinite(res.transformation)):
            T = invert(np.asarray(res.transformation))
    return T


def _multiview_icp(model: ModelCloud, ref_T_obj: Array, scenes: list[_Scene], refs_T_cam: list[Array],
                   voxel: float) -> Array:
    """Point-to-plane ICP of every view's cluster at once, in the reference view's frame
    (``refs_T_cam``: each view's camera in that frame), onto the model points facing any of
    the views: the views together see more sides of the object than one, which pins the
    pose down better. Returns the refined ``ref_T_obj``."""
    pts = np.concatenate([sc.points @ T[:3, :3].T + T[:3, 3] for sc, T in zip(scenes, refs_T_cam)])
    source = _cloud(pts).voxel_down_sample(0.5 * voxel)

    def facing_any(T: Array) -> NDArray[np.int64]:
        return np.unique(np.concatenate([_visible(model, invert(ref_T_cam) @ T) for ref_T_cam in refs_T_cam]))

    return _icp_rounds(model, ref_T_obj, source, facing_any, voxel)


def _resting_rotations(plane: Plane | None, yaw_steps: int) -> list[Array]:
    """Rotations putting each model axis (+-x, +-y, +-z) along the table normal, at ``yaw_steps`` yaws."""
    up = plane.n if plane is not None else np.array([0.0, -1.0, 0.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, up)
    x /= np.linalg.norm(x)
    frame = np.stack([x, np.cross(up, x), up], axis=1)  # table frame -> camera
    ups = [np.eye(3)]
    for axis, angle in (((1, 0, 0), 180), ((1, 0, 0), 90), ((1, 0, 0), -90), ((0, 1, 0), 90), ((0, 1, 0), -90)):
        from scipy.spatial.transform import Rotation

        ups.append(Rotation.from_rotvec(np.radians(angle) * np.asarray(axis, float)).as_matrix())
    out = []
    for k in range(yaw_steps):
        c, s = math.cos(2 * math.pi * k / yaw_steps), math.sin(2 * math.pi * k / yaw_steps)
        yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.extend(frame @ yaw @ u for u in ups)
    return out


def _resting_pose(model: ModelCloud, R: Array, cluster: Array, plane: Plane | None) -> Array:
    """``cam_T_obj`` with rotation ``R``, the model's centre behind the cluster centroid (pushed
    back along the view ray by a quarter of its size) and its top level with the cluster's top
    (the top is what a splat shows best; its table looks higher than it is)."""
    centroid = cluster.mean(axis=0)
    centre = centroid + centroid / np.linalg.norm(centroid) * 0.25 * float(model.extents[-1])
    pts = model.points @ R.T
    t = centre - pts.mean(axis=0)
    if plane is not None:
        top = float(np.percentile(plane.height(cluster), 98))
        t = t + plane.n * (top - float(np.max(plane.height(pts + t))))
    return make_transform(R, t)


def register_model(model: ModelCloud, cluster: Cluster, plane: Plane | None, depth: NDArray[np.floating], K: Array,
                   config: BaselineConfig, min_height: float = 0.0) -> Registration:
    """The model's pose in the camera frame from the cluster (see the module docstring, step 3)."""
    with one_thread():
        voxel = _voxel_size(model, config)
        scene, scene_pcd = _view_scene(cluster, plane, min_height, depth, K, voxel)
        return _register(model, scene, scene_pcd, config, voxel)


def _voxel_size(model: ModelCloud, config: BaselineConfig) -> float:
    """Registration voxel (m): a fraction of the model diameter, so tiny objects work alike."""
    return max(config.voxel_fraction * model.diameter_m, 5e-4)


def _view_scene(cluster: Cluster, plane: Plane | None, min_height: float, depth: NDArray[np.floating], K: Array,
                voxel: float) -> tuple[_Scene, Any]:
    """What registration and scoring need about one view: the cluster thinned to half a voxel
    (all its points when that leaves fewer than 5) as a :class:`_Scene` and an Open3D cloud."""
    from scipy.spatial import cKDTree

    scene_pcd = _cloud(cluster.points).voxel_down_sample(0.5 * voxel)
    if len(scene_pcd.points) < 5:
        scene_pcd = _cloud(cluster.points)
    scene_pts = np.asarray(scene_pcd.points)
    scene = _Scene(scene_pts, cKDTree(scene_pts), plane, min_height, np.asarray(depth), np.asarray(K), 1.5 * voxel)
    return scene, scene_pcd


def _register(model: ModelCloud, scene: _Scene, scene_pcd: Any, config: BaselineConfig, voxel: float) -> Registration:
    scene_pts, plane = scene.points, scene.plane
    hypotheses: list[tuple[str, Array]] = []
    if len(scene_pts) >= 15:
        hypotheses += [("ransac", T) for T in _ransac(model, scene_pcd, voxel, config)]
    hypotheses += [("resting", _resting_pose(model, R, scene_pts, plane))
                   for R in _resting_rotations(plane, config.yaw_steps)]
    best: Registration | None = None
    for method, T0 in hypotheses:
        T = _icp(model, T0, scene, scene_pcd, voxel) if len(scene_pts) >= 6 else T0
        score, fitness = _score(model, T, scene)
        if best is None or score > best.score + 1e-12:
            best = Registration(T, score, fitness, method, len(hypotheses))
    if best is None or not np.all(np.isfinite(best.cam_T_obj)):  # pragma: no cover - defensive
        T = _resting_pose(model, np.eye(3), scene_pts, plane)
        return Registration(T, 0.0, 0.0, "centroid", len(hypotheses))
    return best


def _ransac(model: ModelCloud, scene_pcd: Any, voxel: float, config: BaselineConfig) -> list[Array]:
    """FPFH + RANSAC alignments of the model to the cluster, one per seed (failures left out)."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    src = _cloud(model.points, model.normals).voxel_down_sample(voxel)
    tgt = o3d.geometry.PointCloud(scene_pcd)
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    tgt.orient_normals_towards_camera_location(np.zeros(3))
    feat = o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    f_src = reg.compute_fpfh_feature(src, feat)
    f_tgt = reg.compute_fpfh_feature(tgt, feat)
    out = []
    for seed in config.ransac_seeds:
        o3d.utility.random.seed(int(seed))
        res = reg.registration_ransac_based_on_feature_matching(
            src, tgt, f_src, f_tgt, False, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(config.ransac_iterations, 0.999))
        T = np.asarray(res.transformation, dtype=np.float64)
        if res.fitness > 0 and np.all(np.isfinite(T)):
            out.append(T)
    return out


# ----------------------------------------------------------------------------- the agent
@dataclass
class EpisodeOutcome:
    """What one baseline episode did (the scores come from the logs, see evaluation.metrics.episodes)."""

    episode_id: str
    agent: str
    target: str
    obj_id: int
    seed: int
    adjustments: int
    refused: int
    found: bool
    box_px_start: float | None
    box_px_final: float | None
    registration: Registration | None
    seconds: float
    submission: dict[str, Any] = field(default_factory=dict)


class BaselineAgent:
    """Runs baseline episodes through a :class:`serve.client.BraveClient` (models cached per object)."""

    def __init__(self, client: Any, config: BaselineConfig = BaselineConfig()) -> None:
        self.client = client
        self.config = config
        self._models: dict[int, ModelCloud] = {}
        self._bundle: dict[str, Any] | None = None

    @property
    def bundle_info(self) -> dict[str, Any]:
        """``GET /bundle`` (fetched once)."""
        if self._bundle is None:
            self._bundle = self.client.bundle()
        return self._bundle

    def standoff_m(self, cfg: BaselineConfig) -> float:
        """The nearest the agent goes: ``cfg.min_distance_m``, or by default the nearest capture
        ring of the bundle (``GET /bundle`` ``start.distances_m``): a splat renders artefacts where
        it was never trained, so a closer look shows less, not more. 0.10 m if the bundle lists none."""
        if cfg.min_distance_m is not None:
            return float(cfg.min_distance_m)
        rings = (self.bundle_info.get("start") or {}).get("distances_m") or []
        return float(min(rings)) if rings else DEFAULT_STANDOFF_M

    def model(self, obj_id: int) -> ModelCloud:
        """The target's model cloud from the server (``GET /bundle`` diameter, model PLY)."""
        if obj_id not in self._models:
            info = next((o for o in self.bundle_info["objects"] if int(o["obj_id"]) == obj_id), None)
            if info is None:
                raise BraveError(f"the server knows no object with obj_id {obj_id}")
            verts, faces = read_model_ply(self.client.model(obj_id))
            self._models[obj_id] = sample_model(obj_id, verts, faces, float(info["diameter_mm"]),
                                                 self.config.model_points, self.config.seed)
        return self._models[obj_id]

    def run_episode(self, target: int | str, *, seed: int, width: int, height: int,
                    config: BaselineConfig | None = None) -> EpisodeOutcome:
        """Reset, (approach), register, submit; one episode of the active or static variant."""
        cfg = config or self.config
        t0 = time.perf_counter()
        step = self.client.reset(target=target, width=width, height=height, seed=seed, agent=cfg.agent)
        obj_id = int(step.target["obj_id"])
        model = self.model(obj_id)
        obs = step.observation
        seen = perceive(obs.depth, obs.K, obs.world_T_cam, model, None, cfg)
        box_start = seen.cluster.box_px if seen.cluster is not None else None
        if seen.cluster is not None:
            target_w = _to_world(obs, seen.cluster.centroid)
        else:
            target_w = _to_world(obs, _axis_anchor(*backproject(obs.depth, obs.K), obs.K))
        refused = 0
        trail = [(obs, seen)]  # every view of the episode and what the agent made of it
        if cfg.active and seen.cluster is not None:  # never fly towards something not found
            obs, seen, target_w, refused = self._approach(obs, seen, target_w, model, cfg, trail)
            if cfg.orbit_deg:
                obs, seen, n_refused = self._orbit(obs, seen, target_w, model, cfg, trail)
                refused += n_refused
        if cfg.active and cfg.report_from_start and len(trail) > 1 and trail[0][1].cluster is not None:
            step_back, n_refused = self._return_to(trail[0][0].world_T_cam)
            refused += n_refused
            if step_back is not None:  # the same view as at the start: the same perception (no prior to bias it)
                obs, seen = step_back.observation, trail[0][1]
                if not np.array_equal(obs.depth, trail[0][0].depth):
                    seen = _perceive_near(obs, target_w, model, cfg)
        registration = None
        if cfg.active and cfg.select_across_views and sum(p.cluster is not None for _, p in trail) > 1:
            registration = register_views(model, trail, cfg, final=(obs, seen))
        elif seen.cluster is not None:
            registration = register_model(model, seen.cluster, seen.plane, obs.depth, obs.K, cfg, seen.min_height)
        if registration is None:  # nothing (more) found: a guess where the target was last seen (at first: the view's centre)
            anchor = invert(obs.world_T_cam) @ np.append(target_w, 1.0)
            registration = Registration(_resting_pose(model, np.eye(3), anchor[None, :3], seen.plane), 0.0, 0.0,
                                        "axis", 0)
        from serve.client import PoseEstimate

        estimate = PoseEstimate(obj_id, registration.cam_T_obj, float(np.clip(registration.score, 0.0, 1.0)))
        reply = self.client.submit([estimate], agent=cfg.agent)
        return EpisodeOutcome(step.episode_id, cfg.agent, str(step.target.get("name", target)), obj_id, seed,
                              int(reply.get("adjustments", 0)), refused, seen.cluster is not None, box_start,
                              seen.cluster.box_px if seen.cluster is not None else None, registration,
                              time.perf_counter() - t0, reply)

    def _approach(self, obs: Any, seen: Perception, target_w: Array, model: ModelCloud,
                  cfg: BaselineConfig, trail: list[tuple[Any, Perception]]) -> tuple[Any, Perception, Array, int]:
        """Move until the target covers ``min_box_px`` and is seen from at least
        ``min_elevation_deg`` above the table (step 2 of the module docstring). When a move
        loses the target, look once more from ``relook_lift_deg`` higher (a splat's table can
        swallow small objects seen obliquely); then stop (``target_w``, world, is where the
        target was last seen)."""
        refused = 0
        relooked = False
        for _ in range(cfg.max_moves):
            if seen.cluster is None:
                if relooked or cfg.relook_lift_deg <= 0:
                    break
                relooked = True
                eye = obs.world_T_cam[:3, 3]
                step, n_refused = self._look_from(target_w, float(np.linalg.norm(eye - target_w)),
                                                  _azimuth(eye, target_w),
                                                  _elevation_deg(eye, target_w) + cfg.relook_lift_deg, cfg)
            else:
                target_w = _to_world(obs, seen.cluster.centroid)
                if seen.cluster.box_px >= cfg.min_box_px and \
                        _elevation_deg(obs.world_T_cam[:3, 3], target_w) >= cfg.min_elevation_deg:
                    break
                step, n_refused = self._move_towards(obs, target_w, seen.cluster.box_px, model, cfg)
            refused += n_refused
            if step is None:
                break
            obs = step.observation
            seen = _perceive_near(obs, target_w, model, cfg)
            trail.append((obs, seen))
        return obs, seen, target_w, refused

    def _orbit(self, obs: Any, seen: Perception, target_w: Array, model: ModelCloud, cfg: BaselineConfig,
               trail: list[tuple[Any, Perception]]) -> tuple[Any, Perception, int]:
        """Look at the target from ``orbit_deg`` azimuth offsets at the current distance and
        elevation (the sides a single view misses); returns the last view and the refusals."""
        eye = obs.world_T_cam[:3, 3]
        dist, azimuth, elevation = float(np.linalg.norm(eye - target_w)), _azimuth(eye, target_w), \
            _elevation_deg(eye, target_w)
        refused = 0
        for offset in cfg.orbit_deg:
            step, n_refused = self._look_from(target_w, dist, azimuth + math.radians(offset), elevation, cfg)
            refused += n_refused
            if step is None:
                continue
            obs = step.observation
            seen = _perceive_near(obs, target_w, model, cfg)
            trail.append((obs, seen))
        return obs, seen, refused

    def _move_towards(self, obs: Any, target_w: Array, size_px: float, model: ModelCloud,
                      cfg: BaselineConfig) -> tuple[Any, int]:
        """Look at ``target_w`` from the distance where it covers about ``approach_box_px`` (never
        farther than now, never nearer than :meth:`standoff_m` or 3 diameters), from the same
        azimuth and elevation (or ``approach_elevation_deg``, at least ``min_elevation_deg``)."""
        eye = obs.world_T_cam[:3, 3]
        dist = float(np.linalg.norm(eye - target_w))
        near = max(self.standoff_m(cfg), 3.0 * model.diameter_m)
        goal = max(dist * min(size_px / cfg.approach_box_px, 1.0), near)
        if goal > 0.9 * dist:  # too little to gain for an adjustment (or it would back off)
            return None, 0
        elevation = cfg.approach_elevation_deg
        if elevation is None:
            elevation = max(_elevation_deg(eye, target_w), cfg.min_elevation_deg)
        return self._look_from(target_w, goal, _azimuth(eye, target_w), elevation, cfg)

    def _return_to(self, world_T_cam: Array) -> tuple[Any, int]:
        """Teleport back to ``world_T_cam`` (a pose the episode already held, so normally free);
        returns the accepted step (None if refused) and the number of refusals."""
        step = self.client.set_pose(np.asarray(world_T_cam, dtype=np.float64))
        return (step, 0) if step.accepted else (None, 1)

    def _look_from(self, target_w: Array, distance: float, azimuth: float, elevation_deg: float,
                   cfg: BaselineConfig) -> tuple[Any, int]:
        """Teleport to look at ``target_w`` from ``distance``, ``azimuth`` (rad), ``elevation_deg``;
        a refused pose is retried 10 degrees higher and lower, then 40 % farther. Returns the
        accepted step (None if every try was refused) and the number of refusals."""
        refused = 0
        for scale in (1.0, 1.4):
            for delta in (0.0, 10.0, -10.0):
                el = math.radians(float(np.clip(elevation_deg + delta, max(cfg.min_elevation_deg, 5.0), 88.0)))
                d = np.array([math.cos(el) * math.cos(azimuth), math.cos(el) * math.sin(azimuth), math.sin(el)])
                step = self.client.set_pose(look_at(target_w + d * distance * scale, target_w))
                if step.accepted:
                    return step, refused
                refused += 1
        return None, refused


def register_views(model: ModelCloud, trail: list[tuple[Any, Perception]], config: BaselineConfig,
                   final: tuple[Any, Perception] | None = None) -> Registration | None:
    """The target's pose in the final view's camera frame (``final``, default the last view of
    ``trail``) from the registrations of every view of ``trail`` (observations with
    ``world_T_cam``, ``depth``, ``K``, and the agent's :class:`Perception`), each judged by its
    weighted mean score over all the views' clusters and depth images (:func:`view_weights`; a
    registration of something the other views do not see scores badly in them).

    With ``config.switch_margin`` (and a cluster in the final view) the final view's own
    registration is submitted unless another view's registration, refined by ICP in the final
    view, beats its weighted mean score by more than the margin (never, with the default inf):
    the final view is where VSD and MSPD are scored. With ``config.multiview_refine`` that pose
    is then refined on all the views' clusters at once (:func:`_multiview_icp`) and the refined
    pose kept unless its weighted mean score is lower.
    Without a margin the registration with the best weighted mean is submitted, ICP-refined in
    the final view when ``config.refine_in_final_view``. A final view whose :class:`Perception`
    is one of the trail's (the same object) is not registered again. None when no view has a
    cluster."""
    found = [(o, p) for o, p in trail if p.cluster is not None]
    if not found:
        return None
    final_obs, final_seen = final if final is not None else trail[-1]
    with one_thread():
        voxel = _voxel_size(model, config)
        scenes = [_view_scene(p.cluster, p.plane, p.min_height, o.depth, o.K, voxel) for o, p in found]
        cams_T_world = [invert(np.asarray(o.world_T_cam, dtype=np.float64)) for o, _ in found]
        regs = [_register(model, scene, scene_pcd, config, voxel) for scene, scene_pcd in scenes]
        weights = view_weights([r.score for r in regs], config.view_weighting)
        world_T_ref = np.asarray(final_obs.world_T_cam, dtype=np.float64)

        def mean_score(cam_T_obj: Array) -> float:  # a pose in the final view's frame
            world_T_obj = world_T_ref @ cam_T_obj
            return float(np.dot(weights, [_score(model, cam_T_world @ world_T_obj, scene)[0]
                                          for (scene, _), cam_T_world in zip(scenes, cams_T_world)]))

        refs_T_cam = [invert(world_T_ref) @ np.asarray(o.world_T_cam, dtype=np.float64) for o, _ in found]
        in_final = [ref_T_cam @ r.cam_T_obj for ref_T_cam, r in zip(refs_T_cam, regs)]
        # the final view is often one of the trail's (the agent went back to its start): reuse its work
        i_final = next((i for i, (_, p) in enumerate(found) if p is final_seen), None)
        final_scene = None
        if i_final is not None:
            final_scene = scenes[i_final]
        elif final_seen.cluster is not None:
            final_scene = _view_scene(final_seen.cluster, final_seen.plane, final_seen.min_height,
                                      final_obs.depth, final_obs.K, voxel)
        if config.switch_margin is not None and final_scene is not None:
            if i_final is not None:
                own, own_T = regs[i_final], in_final[i_final]
            else:
                own = _register(model, *final_scene, config, voxel)
                own_T = own.cam_T_obj
            score, cam_T_obj, reg = mean_score(own_T), own_T, own
            if math.isfinite(config.switch_margin):  # inf (the default): never switch
                challengers = [(mean_score(T), T, r) for T, r in
                               ((_icp(model, T0, *final_scene, voxel), r) for T0, r in zip(in_final, regs))]
                best = max(challengers, key=lambda c: c[0])
                if best[0] > score + config.switch_margin:
                    score, cam_T_obj, reg = best
            if config.multiview_refine and len(found) > 1:
                refined = _multiview_icp(model, cam_T_obj, [sc for sc, _ in scenes], refs_T_cam, voxel)
                refined_score = mean_score(refined)
                if refined_score >= score:
                    score, cam_T_obj = refined_score, refined
            return Registration(cam_T_obj, score, reg.fitness, reg.method, reg.hypotheses)
        score, cam_T_obj, reg = max(((mean_score(T), T, r) for T, r in zip(in_final, regs)), key=lambda c: c[0])
        if config.refine_in_final_view and final_scene is not None:  # scored in this view: fit its depth
            cam_T_obj = _icp(model, cam_T_obj, *final_scene, voxel)
            score = mean_score(cam_T_obj)
    return Registration(cam_T_obj, score, reg.fitness, reg.method, reg.hypotheses)


def view_weights(own_scores: list[float], weighting: str) -> Array:
    """Weights (summing to 1) of the views in :func:`register_views`'s mean score. "mean": all
    alike. "reliability": each view by the score of its own best registration (clipped at 0): a
    view that no model pose explains well (a splat artefact or a neighbour taken for the target)
    votes less, one that none explains at all not at all. All alike if none is positive."""
    n = len(own_scores)
    if weighting not in ("mean", "reliability"):
        raise BraveError(f"baseline: view_weighting must be 'mean' or 'reliability', got {weighting!r}")
    w = np.clip(np.asarray(own_scores, dtype=np.float64), 0.0, None) if weighting == "reliability" else np.ones(n)
    w = np.where(np.isfinite(w), w, 0.0)
    top = float(w.max(initial=0.0))
    if not top > 0:
        return np.full(n, 1.0 / n)
    w = w / top  # first to at most 1: the sum of huge scores must not overflow
    return w / float(w.sum())


def _perceive_near(obs: Any, target_w: Array, model: ModelCloud, cfg: BaselineConfig) -> Perception:
    """:func:`perceive` in ``obs`` with the prior where the target was last seen (``target_w``, world)."""
    cam_T_world = invert(obs.world_T_cam)
    return perceive(obs.depth, obs.K, obs.world_T_cam, model, cam_T_world[:3, :3] @ target_w + cam_T_world[:3, 3], cfg)


def _azimuth(eye: Array, target: Array) -> float:
    return math.atan2(float(eye[1] - target[1]), float(eye[0] - target[0]))


def _to_world(obs: Any, point_cam: Array) -> Array:
    return obs.world_T_cam[:3, :3] @ point_cam + obs.world_T_cam[:3, 3]


def _elevation_deg(eye: Array, target: Array) -> float:
    """Elevation (degrees) of ``eye`` seen from ``target`` above the world's horizontal plane."""
    v = np.asarray(eye, dtype=np.float64) - np.asarray(target, dtype=np.float64)
    return math.degrees(math.atan2(float(v[2]), float(np.hypot(v[0], v[1]))))


def static_config(config: BaselineConfig = BaselineConfig()) -> BaselineConfig:
    """The static variant of ``config`` (estimates from the first view, no move)."""
    return replace(config, active=False)

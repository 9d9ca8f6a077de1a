"""Registration: the model's pose in the camera frame from the target's cluster in one view.

The model (a surface sample, metres) is aligned to the cluster with FPFH + RANSAC from several
seeds, plus "resting on the table" hypotheses (each model axis up, at several yaws). Every
hypothesis is refined with point-to-plane ICP on the model points facing the camera and scored by
how well the model and the cluster explain each other, minus clear penetration of the table,
model points in observed free space, (weakly) tilt and, when the view has colour and the model
colours, how badly the image's colours match the model's under the pose
(:mod:`~brave6d.evaluation.agents.appearance`: it breaks the ties between an object and its
180 degree flip that depth leaves to noise). Voxel sizes are fractions of the model
diameter, so tiny objects work alike. The best hypothesis wins; its score is the confidence.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.core.transforms import invert, make_transform
from brave6d.evaluation.agents.appearance import color_disagreement
from brave6d.evaluation.agents.model import ModelCloud
from brave6d.evaluation.agents.perception import Cluster, Plane, pixels_of
from brave6d.evaluation.agents.pointclouds import one_thread, open3d, point_cloud

Array = NDArray[np.float64]
UPRIGHT_WEIGHT = 0.1  # weight of the "resting on a face" prior in the score
COLOR_WEIGHT = 0.1  # weight of the colour disagreement: set by benchmarks/flip_colour.py


@dataclass(frozen=True)
class RegistrationOptions:
    """How hypotheses are made; sizes relative to the model diameter."""

    voxel_fraction: float = 0.08  # registration voxel = fraction x diameter
    ransac_seeds: tuple[int, ...] = (0, 1, 2, 3)
    ransac_iterations: int = 20_000
    yaw_steps: int = 8  # resting hypotheses: 6 up-axes x yaw_steps
    icp_iterations: int = 30  # per ICP round (two rounds per hypothesis)
    color_weight: float = COLOR_WEIGHT  # weight of the colour disagreement (in [-1, 1]) in the score

    def __post_init__(self) -> None:
        if not (math.isfinite(self.color_weight) and self.color_weight >= 0.0):
            raise BraveError(f"RegistrationOptions.color_weight must be a finite number >= 0 (0: depth alone), "
                             f"got {self.color_weight}")


@dataclass(frozen=True)
class Registration:
    """``cam_T_obj`` of the best hypothesis, its score (higher is better, at most 1) and how it
    was found ("ransac", "resting", "centroid"; "axis": no cluster, a guess on the optical axis)."""

    cam_T_obj: Array
    score: float
    fitness: float
    method: str
    hypotheses: int


@dataclass
class ViewScene:
    """What registration and scoring need about one view: the thinned cluster (as points, a
    KD-tree and an Open3D cloud), the table plane, the segmentation cut, the depth image and the
    colour image (None: scored on depth alone)."""

    points: Array
    tree: Any  # scipy cKDTree of points
    cloud: Any  # Open3D point cloud of points
    plane: Plane | None
    min_height: float  # the segmentation's cut above the plane
    depth: NDArray[np.floating]
    K: Array
    tol: float
    rgb: NDArray[np.uint8] | None = None


def voxel_size(model: ModelCloud, options: RegistrationOptions) -> float:
    """Registration voxel (m): a fraction of the model diameter, so tiny objects work alike."""
    return max(options.voxel_fraction * model.diameter_m, 5e-4)


def view_scene(cluster: Cluster, plane: Plane | None, min_height: float, depth: NDArray[np.floating], K: Array,
               voxel: float, rgb: NDArray[np.uint8] | None = None) -> ViewScene:
    """The :class:`ViewScene` of a cluster thinned to half a voxel (all its points when that
    leaves fewer than 5); ``rgb`` (H, W, 3) uint8 of the same size as ``depth``, or None."""
    from scipy.spatial import cKDTree

    cloud = point_cloud(cluster.points).voxel_down_sample(0.5 * voxel)
    if len(cloud.points) < 5:
        cloud = point_cloud(cluster.points)
    pts = np.asarray(cloud.points)
    depth = np.asarray(depth)
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape[:2] != depth.shape or rgb.ndim != 3 or rgb.shape[2] < 3:
            raise BraveError(f"the colour image is {rgb.shape}, the depth image {depth.shape}: not one view")
    return ViewScene(pts, cKDTree(pts), cloud, plane, min_height, depth, np.asarray(K), 1.5 * voxel, rgb)


def register_model(model: ModelCloud, cluster: Cluster, plane: Plane | None, depth: NDArray[np.floating], K: Array,
                   options: RegistrationOptions = RegistrationOptions(), min_height: float = 0.0,
                   rgb: NDArray[np.uint8] | None = None) -> Registration:
    """The model's pose in the camera frame from the cluster of one view (see the module
    docstring); ``rgb``: the view's colour image (None: depth alone)."""
    with one_thread():
        voxel = voxel_size(model, options)
        return register_scene(model, view_scene(cluster, plane, min_height, depth, K, voxel, rgb), options, voxel)


def register_scene(model: ModelCloud, scene: ViewScene, options: RegistrationOptions, voxel: float) -> Registration:
    """:func:`register_model` on a prepared :class:`ViewScene` (call it under :func:`one_thread`)."""
    hypotheses: list[tuple[str, Array]] = []
    if len(scene.points) >= 15:
        hypotheses += [("ransac", T) for T in _ransac(model, scene.cloud, voxel, options)]
    hypotheses += [("resting", resting_pose(model, R, scene.points, scene.plane))
                   for R in _resting_rotations(scene.plane, options.yaw_steps)]
    best: Registration | None = None
    for method, T0 in hypotheses:
        T = icp(model, T0, scene, voxel, options.icp_iterations) if len(scene.points) >= 6 else T0
        score, fitness = score_pose(model, T, scene, options.color_weight)
        if best is None or score > best.score + 1e-12:
            best = Registration(T, score, fitness, method, len(hypotheses))
    if best is None or not np.all(np.isfinite(best.cam_T_obj)):  # pragma: no cover - defensive
        T = resting_pose(model, np.eye(3), scene.points, scene.plane)
        return Registration(T, 0.0, 0.0, "centroid", len(hypotheses))
    return best


def visible_points(model: ModelCloud, cam_T_obj: Array) -> NDArray[np.int64]:
    """Indices of the model points whose (outward) normal faces the camera under ``cam_T_obj``
    (back-face culling; self-occlusion of concave parts is ignored); all when fewer than 10."""
    R, t = cam_T_obj[:3, :3], cam_T_obj[:3, 3]
    facing = np.einsum("ij,ij->i", model.normals @ R.T, model.points @ R.T + t) < 0.0
    idx = np.flatnonzero(facing)
    return idx if len(idx) >= 10 else np.arange(len(model.points))


def score_pose(model: ModelCloud, T: Array, scene: ViewScene, color_weight: float = COLOR_WEIGHT) -> tuple[float, float]:
    """(score, fitness) of ``cam_T_obj = T``. Fitness: mean of the fraction of cluster points near
    the model and the fraction of visible model points above the segmentation cut near the
    cluster. Score: fitness minus the fractions of model points deep below the table (splat tables
    look higher than they are, so only clear penetration counts) and of visible model points in
    observed free space (the depth image sees through them), a small penalty for tilt and
    ``color_weight`` times the colour disagreement (when the view has colour)."""
    from scipy.spatial import cKDTree

    vis = visible_points(model, T)
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
    score = fitness - below - _free_space(pts, scene) - UPRIGHT_WEIGHT * _tilt(T, scene.plane)
    if scene.rgb is not None and color_weight != 0.0:
        colors = model.colors[vis] if model.colors is not None else None
        score -= color_weight * color_disagreement(colors, pts, scene.rgb, scene.depth, scene.K, scene.tol)
    return score, fitness


def icp(model: ModelCloud, T: Array, scene: ViewScene, voxel: float, iterations: int = 30) -> Array:
    """Point-to-plane ICP of the view's cluster onto the visible model points; the refined ``cam_T_obj``."""
    return icp_rounds(model, T, scene.cloud, lambda T_now: visible_points(model, T_now), voxel, iterations)


def icp_rounds(model: ModelCloud, T: Array, source: Any, facing: Callable[[Array], NDArray[np.int64]],
               voxel: float, iterations: int = 30) -> Array:
    """Two rounds of point-to-plane ICP of the ``source`` cloud onto the model points that
    ``facing(T)`` selects for the current pose, shrinking the correspondence distance."""
    reg = open3d().pipelines.registration
    for dist in (3.0 * voxel, 1.5 * voxel):
        vis = facing(T)
        target = point_cloud(model.points[vis], model.normals[vis])
        res = reg.registration_icp(source, target, dist, invert(T), reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(max_iteration=int(iterations)))
        if res.fitness > 0 and np.all(np.isfinite(res.transformation)):
            T = invert(np.asarray(res.transformation))
    return T


def resting_pose(model: ModelCloud, R: Array, cluster: Array, plane: Plane | None) -> Array:
    """``cam_T_obj`` with rotation ``R``, the model's centre behind the centroid of the points
    ``cluster`` (pushed back along the view ray by a quarter of its size) and its top level with
    the cluster's top (the top is what a splat shows best; its table looks higher than it is)."""
    centroid = cluster.mean(axis=0)
    centre = centroid + centroid / np.linalg.norm(centroid) * 0.25 * float(model.extents[-1])
    pts = model.points @ R.T
    t = centre - pts.mean(axis=0)
    if plane is not None:
        top = float(np.percentile(plane.height(cluster), 98))
        t = t + plane.n * (top - float(np.max(plane.height(pts + t))))
    return make_transform(R, t)


def _tilt(T: Array, plane: Plane | None) -> float:
    """0 when a model axis is along the table normal, up to 1 at the largest possible tilt: a weak
    prior that objects rest on a face (breaks near-ties between flipped and tilted fits)."""
    if plane is None:
        return 0.0
    cos = float(np.max(np.abs(T[:3, :3].T @ plane.n)))
    return math.degrees(math.acos(min(1.0, cos))) / math.degrees(math.acos(1.0 / math.sqrt(3.0)))


def _free_space(pts: Array, scene: ViewScene) -> float:
    """Fraction of camera-frame points that the depth image sees through (observed depth farther
    than the point by more than the tolerance); 1 when a point is behind the camera."""
    z = pts[:, 2]
    if np.any(z <= 1e-3):
        return 1.0
    u, v, inside = pixels_of(pts, scene.K, scene.depth.shape)
    observed = scene.depth[v[inside], u[inside]]
    valid = observed > 0
    if not np.any(valid):
        return 0.0
    return float(np.mean(observed[valid] > z[inside][valid] + scene.tol))


def _resting_rotations(plane: Plane | None, yaw_steps: int) -> list[Array]:
    """Rotations putting each model axis (+-x, +-y, +-z) along the table normal, at ``yaw_steps`` yaws."""
    from scipy.spatial.transform import Rotation

    up = plane.n if plane is not None else np.array([0.0, -1.0, 0.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, up)
    x /= np.linalg.norm(x)
    frame = np.stack([x, np.cross(up, x), up], axis=1)  # table frame -> camera
    ups = [np.eye(3)]
    for axis, angle in (((1, 0, 0), 180), ((1, 0, 0), 90), ((1, 0, 0), -90), ((0, 1, 0), 90), ((0, 1, 0), -90)):
        ups.append(Rotation.from_rotvec(np.radians(angle) * np.asarray(axis, float)).as_matrix())
    out = []
    for k in range(yaw_steps):
        c, s = math.cos(2 * math.pi * k / yaw_steps), math.sin(2 * math.pi * k / yaw_steps)
        yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.extend(frame @ yaw @ u for u in ups)
    return out


def _ransac(model: ModelCloud, scene_cloud: Any, voxel: float, options: RegistrationOptions) -> list[Array]:
    """FPFH + RANSAC alignments of the model to the cluster, one per seed (failures left out)."""
    o3d = open3d()
    reg = o3d.pipelines.registration
    src = point_cloud(model.points, model.normals).voxel_down_sample(voxel)
    tgt = o3d.geometry.PointCloud(scene_cloud)
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    tgt.orient_normals_towards_camera_location(np.zeros(3))
    feat = o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    f_src = reg.compute_fpfh_feature(src, feat)
    f_tgt = reg.compute_fpfh_feature(tgt, feat)
    out = []
    for seed in options.ransac_seeds:
        o3d.utility.random.seed(int(seed))
        res = reg.registration_ransac_based_on_feature_matching(
            src, tgt, f_src, f_tgt, False, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(options.ransac_iterations, 0.999))
        T = np.asarray(res.transformation, dtype=np.float64)
        if res.fitness > 0 and np.all(np.isfinite(T)):
            out.append(T)
    return out

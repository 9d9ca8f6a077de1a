"""The baseline's static estimator on any RGB-D frame: ``cam_T_obj`` of one object, or a refusal.

:func:`estimate_pose` takes a depth image in metres, ``K`` (OpenCV convention: pixel (u, v) centred
at integer (u, v)), the object's model (:func:`prepare_model`: a PLY path or points, in mm or m) and
a hint where the object is (:class:`PixelHint` or :class:`BoxHint`). Steps:

1. the inputs are checked; missing depth (0, NaN, inf, negative) is ignored;
2. the expected point: on the hint's ray (a box: its centre) at the median valid depth near the
   hint (a pixel: within a few pixels; a box: its central half);
3. "up": the caller's (world up in the camera frame, e.g. ``world_T_cam[2, :3]``), or, with none,
   the normal of the table: the largest RANSAC plane (Open3D ``segment_plane``) around the
   expected point with that point on the camera's side of it;
4. the baseline's perception (:func:`~brave6d.evaluation.agents.perception.perceive_up`): the table
   plane within ``max_tilt_deg`` of up, the clusters above it, the one of the model's size near the
   expected point; a box keeps the cluster's pixels inside it;
5. the baseline's registration (:func:`~brave6d.evaluation.agents.registration.register_model`):
   FPFH + RANSAC and "resting on the table" hypotheses refined by ICP and scored; a best score
   under ``min_score`` is refused.

Nothing is returned silently empty: every way to find nothing raises :class:`EstimateRefused`,
whose ``cause`` (one of :data:`REFUSAL_CAUSES`) names the step. The RGB image, when given, must match the
depth's size; with a model that has vertex colours it scores each pose's colours too, which tells a
near-symmetric object from its flip. Deterministic (seeded, Open3D on one thread).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import BraveError
from brave6d.evaluation.agents.model import ModelCloud, sample_model
from brave6d.evaluation.agents.perception import (
    Cluster,
    Perception,
    PerceptionOptions,
    Plane,
    backproject,
    perceive_up,
)
from brave6d.evaluation.agents.pointclouds import one_thread, open3d, point_cloud
from brave6d.evaluation.agents.registration import RegistrationOptions, register_model

Array = NDArray[np.float64]

#: Why :func:`estimate_pose` refused, in the order of its steps.
REFUSAL_CAUSES = ("bad_input", "hint_outside", "no_depth_at_hint", "scale_mismatch", "no_plane", "up_mismatch",
                  "no_object", "no_fit")
#: An object seen this many times larger (pixels) than the model would project at its depth is refused
#: ("scale_mismatch": the depth's scale or the model's units are wrong). Merged neighbours stay under it.
MAX_SIZE_RATIO = 3.0
#: Model units :func:`prepare_model` takes.
UNITS = ("mm", "m")
#: Model diameters outside this range (mm) are refused as a units mistake.
DIAMETER_RANGE_MM = (1.0, 10_000.0)
#: Depths beyond this (m) are refused as a units mistake (millimetres passed as metres).
MAX_DEPTH_M = 100.0


class EstimateRefused(BraveError):
    """No pose: ``cause`` (one of :data:`REFUSAL_CAUSES`) names the step that found nothing, the message says why."""

    def __init__(self, cause: str, message: str) -> None:
        assert cause in REFUSAL_CAUSES, cause
        super().__init__(f"{cause}: {message}")
        self.cause = cause


@dataclass(frozen=True)
class PixelHint:
    """The object is seen at pixel (``u``, ``v``) (column, row; OpenCV convention)."""

    u: float
    v: float


@dataclass(frozen=True)
class BoxHint:
    """The object is seen inside the box ``[x, y, w, h]`` (pixels, BOP's ``bbox_visib`` form)."""

    x: float
    y: float
    w: float
    h: float


Hint = PixelHint | BoxHint


@dataclass(frozen=True)
class FrameOptions:
    """What the single-frame estimator does; the registration's settings trade accuracy for time
    (``benchmarks/estimate_frame.py`` measures them)."""

    perception: PerceptionOptions = PerceptionOptions()
    registration: RegistrationOptions = RegistrationOptions()
    min_score: float = 0.25  # best hypothesis below this: refused ("no_fit")
    up_plane_ransac_m: float = 0.005  # inlier distance of the plane fit that finds "up"
    up_plane_iterations: int = 1000  # its RANSAC iterations (thinned like perception's: plane_voxel_m)
    hint_radius_px: float = 6.0  # a pixel hint: valid depth searched within this radius
    box_margin: float = 0.1  # a box hint keeps cluster pixels inside the box grown by this fraction
    min_cluster_points: int = 30  # fewer depth pixels on the object: refused ("no_object")


@dataclass(frozen=True)
class FramePose:
    """An estimate: ``cam_T_obj`` (metres), its score (higher is better, at most 1), how it was found
    and where "up" came from (``"caller"`` or ``"table plane"``)."""

    cam_T_obj: Array
    score: float
    fitness: float
    method: str
    up_cam: Array
    up_source: str
    table: Plane
    cluster_points: int
    seconds: float
    hypotheses: int = 0
    notes: dict[str, Any] = field(default_factory=dict)

    @property
    def R(self) -> Array:
        return self.cam_T_obj[:3, :3]

    @property
    def t_mm(self) -> Array:
        return self.cam_T_obj[:3, 3] * 1000.0

    def to_json(self) -> dict[str, Any]:
        """The estimate as JSON: ``cam_T_obj`` (m) and BOP's ``R`` (row-major) and ``t`` (mm)."""
        return {"cam_T_obj": self.cam_T_obj.tolist(), "R": self.R.reshape(-1).tolist(), "t_mm": self.t_mm.tolist(),
                "score": self.score, "fitness": self.fitness, "method": self.method, "up_cam": self.up_cam.tolist(),
                "up_source": self.up_source, "table": {"n": self.table.n.tolist(), "d_m": self.table.d},
                "cluster_points": self.cluster_points, "hypotheses": self.hypotheses, "seconds": self.seconds}


# ----------------------------------------------------------------------------- inputs
def prepare_model(source: str | Path | ArrayLike, units: str = "mm", *, faces: ArrayLike | None = None,
                  obj_id: int = 0, diameter: float | None = None, points: int = 2000, seed: int = 0) -> ModelCloud:
    """The model as the estimator uses it (a seeded surface sample in metres with normals).

    ``source``: a mesh PLY path (BOP models are PLY in mm) or vertices ``(N, 3)`` (with ``faces``
    ``(M, 3)``, or none: a point cloud); ``units``: ``"mm"`` or ``"m"``, of the file or the array;
    ``diameter`` in the same units (default: the largest vertex distance). A diameter outside
    :data:`DIAMETER_RANGE_MM` is refused: it is almost always the wrong ``units``."""
    if units not in UNITS:
        raise EstimateRefused("bad_input", f"model units must be one of {UNITS}, got {units!r}")
    if int(points) < 50:
        raise EstimateRefused("bad_input", f"the model sample needs at least 50 points, got {points}")
    label = "the model points"
    if isinstance(source, (str, Path)):
        from brave6d.annotation import read_ply_mesh

        label = str(source)
        if Path(source).suffix.lower() != ".ply":
            raise EstimateRefused("bad_input", f"{source}: the model must be a PLY mesh (BOP models are)")
        mesh = read_ply_mesh(source)
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        tri = mesh.faces if len(mesh.faces) else None
        colors = mesh.vertex_colors
    else:
        vertices = np.asarray(source, dtype=np.float64)
        tri = None if faces is None else np.asarray(faces, dtype=np.int64)
        colors = None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
        raise EstimateRefused("bad_input", f"{label}: expected vertices of shape (N>=3, 3), got {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise EstimateRefused("bad_input", f"{label}: vertices contain NaN or inf")
    if tri is not None and (tri.ndim != 2 or tri.shape[1] != 3 or tri.min(initial=0) < 0
                            or tri.max(initial=0) >= len(vertices)):
        raise EstimateRefused("bad_input", f"{label}: faces must be (M, 3) indices into the {len(vertices)} "
                                           "vertices")
    to_mm = 1000.0 if units == "m" else 1.0
    vertices_mm = vertices * to_mm
    if diameter is None:
        from brave6d.annotation import model_diameter

        diameter_mm = float(model_diameter(vertices_mm))
    else:
        diameter_mm = float(diameter) * to_mm
    lo, hi = DIAMETER_RANGE_MM
    if not (math.isfinite(diameter_mm) and lo <= diameter_mm <= hi):
        other = "m" if units == "mm" else "mm"
        raise EstimateRefused("bad_input", f"{label}: model diameter {diameter_mm:.4g} mm (units {units!r}) is outside "
                                           f"{lo:g}..{hi:g} mm: are the model's units {other!r}?")
    try:
        return sample_model(int(obj_id), vertices_mm, tri, diameter_mm, int(points), int(seed), colors)
    except BraveError as exc:
        raise EstimateRefused("bad_input", f"{label}: {exc}") from None


def read_depth_png(path: str | Path, depth_scale_mm: float = 1.0) -> Array:
    """A 16-bit depth PNG in metres: ``value * depth_scale_mm / 1000`` (BOP's ``depth_scale``: 1 for
    millimetres, 0.1 for tenths of a millimetre); 0 stays 0 (no depth)."""
    from brave6d.core.atomic import read_png

    scale = float(depth_scale_mm)
    if not (math.isfinite(scale) and scale > 0):
        raise EstimateRefused("bad_input", f"{path}: depth_scale must be a positive number of mm, "
                                           f"got {depth_scale_mm}")
    return read_png(path, "depth").astype(np.float64) * (scale / 1000.0)


def _check_depth(depth_m: ArrayLike) -> Array:
    d = np.asarray(depth_m)
    if d.ndim != 2 or min(d.shape) < 2:
        raise EstimateRefused("bad_input", f"depth must be a 2-D image, got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        raise EstimateRefused("bad_input", f"depth must be float metres, got {d.dtype} (a 16-bit PNG: read it with "
                                           "read_depth_png(path, depth_scale_mm))")
    d = d.astype(np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    if d.max(initial=0.0) > MAX_DEPTH_M:
        raise EstimateRefused("bad_input", f"depth reaches {d.max():.4g} m: is it in millimetres? "
                                           "(pass metres: PNG value x depth_scale / 1000)")
    return d


def _check_K(K: ArrayLike) -> Array:
    k = np.asarray(K, dtype=np.float64)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)):
        raise EstimateRefused("bad_input", f"K must be a finite 3x3 matrix, got shape {k.shape}")
    if not (k[0, 0] > 0 and k[1, 1] > 0) or not np.allclose(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0:
        raise EstimateRefused("bad_input", "K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    return k


def _check_up(up: ArrayLike) -> Array:
    u = np.asarray(up, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(u)) if u.shape == (3,) and np.all(np.isfinite(u)) else 0.0
    if norm < 1e-9:
        raise EstimateRefused("bad_input", f"up must be a finite non-zero 3-vector, got {np.asarray(up).tolist()}")
    return u / norm


# ----------------------------------------------------------------------------- hint -> expected point
def _hint_window(hint: Hint, shape: tuple[int, int], radius_px: float) -> tuple[float, float, tuple[slice, slice]]:
    """The hint's pixel (u, v) and the image window whose depth gives its distance."""
    h, w = shape
    if isinstance(hint, PixelHint):
        u, v = float(hint.u), float(hint.v)
        if not (math.isfinite(u) and math.isfinite(v)):
            raise EstimateRefused("bad_input", f"the hint pixel must be finite, got ({hint.u}, {hint.v})")
        if not (-0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5):
            raise EstimateRefused("hint_outside", f"pixel ({u:g}, {v:g}) is outside the {w}x{h} image")
        r = max(1.0, float(radius_px))
        rows = slice(max(0, int(math.floor(v - r))), min(h, int(math.ceil(v + r)) + 1))
        cols = slice(max(0, int(math.floor(u - r))), min(w, int(math.ceil(u + r)) + 1))
        return u, v, (rows, cols)
    if isinstance(hint, BoxHint):
        x, y, bw, bh = (float(hint.x), float(hint.y), float(hint.w), float(hint.h))
        if not all(math.isfinite(c) for c in (x, y, bw, bh)) or bw <= 0 or bh <= 0:
            raise EstimateRefused("bad_input", f"the hint box [x, y, w, h] needs finite values and w, h > 0, "
                                               f"got [{hint.x}, {hint.y}, {hint.w}, {hint.h}]")
        x0, y0, x1, y1 = max(x, 0.0), max(y, 0.0), min(x + bw, float(w)), min(y + bh, float(h))
        if x1 - x0 < 1 or y1 - y0 < 1:
            raise EstimateRefused("hint_outside", f"box [{x:g}, {y:g}, {bw:g}, {bh:g}] does not overlap the "
                                                  f"{w}x{h} image")
        u, v = 0.5 * (x0 + x1) - 0.5, 0.5 * (y0 + y1) - 0.5  # box edges are pixel edges; pixel centres are integers
        qx, qy = 0.25 * (x1 - x0), 0.25 * (y1 - y0)  # the central half
        rows = slice(int(math.floor(y0 + qy)), max(int(math.floor(y0 + qy)) + 1, int(math.ceil(y1 - qy))))
        cols = slice(int(math.floor(x0 + qx)), max(int(math.floor(x0 + qx)) + 1, int(math.ceil(x1 - qx))))
        return u, v, (rows, cols)
    raise EstimateRefused("bad_input", f"the hint must be a PixelHint or a BoxHint, got {type(hint).__name__}")


def expected_point(depth_m: Array, K: Array, hint: Hint, radius_px: float = 6.0) -> Array:
    """The camera-frame point (m) on the hint's ray at the median valid depth of the hint's window."""
    u, v, (rows, cols) = _hint_window(hint, depth_m.shape, radius_px)
    window = depth_m[rows, cols]
    valid = window[window > 0]
    if len(valid) == 0:
        covered = float(np.mean(depth_m > 0))
        where = f"within {radius_px:g} px of pixel ({u:g}, {v:g})" if isinstance(hint, PixelHint) else \
            f"in the central half of box [{hint.x:g}, {hint.y:g}, {hint.w:g}, {hint.h:g}]"
        raise EstimateRefused("no_depth_at_hint", f"no valid depth {where} ({100 * covered:.1f}% of the image "
                                                  "has depth)")
    z = float(np.median(valid))
    return np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])


# ----------------------------------------------------------------------------- up from the table
def table_plane(points: Array, anchor: Array, diameter_m: float, ransac_m: float = 0.005, seed: int = 0,
                max_planes: int = 3, voxel: float = 0.0, iterations: int = 1000) -> Plane | None:
    """The table under ``anchor``: among up to ``max_planes`` RANSAC planes peeled off in turn (largest
    first) from the points within 4, then 8 model diameters of it, then all, the first with
    ``anchor`` on the camera's side (less half a diameter: the object rests on it) and its normal
    facing the camera; None when there is none. The cloud is thinned to ``voxel`` (0: ``ransac_m``)."""
    o3d = open3d()
    for radius in (4.0 * diameter_m, 8.0 * diameter_m, math.inf):
        near = points[np.linalg.norm(points - anchor, axis=1) < radius]
        if len(near) < 100:
            continue
        pcd = point_cloud(near).voxel_down_sample(max(voxel if voxel > 0 else ransac_m, 1e-4))
        for _ in range(max_planes):
            if len(pcd.points) < 50:
                break
            o3d.utility.random.seed(seed)
            model, inliers = pcd.segment_plane(ransac_m, 3, int(iterations))
            n = np.asarray(model[:3], dtype=np.float64)
            norm = float(np.linalg.norm(n))
            if norm == 0 or len(inliers) < 30:
                break
            n, d = n / norm, float(model[3]) / norm
            if d < 0:  # the camera (origin) on the positive side
                n, d = -n, -d
            if float(n @ anchor + d) > -0.5 * diameter_m:
                return Plane(n, d)
            pcd = pcd.select_by_index(inliers, invert=True)
    return None


def _angle_deg(a: Array, b: Array) -> float:
    return math.degrees(math.acos(float(np.clip(a @ b, -1.0, 1.0))))


# ----------------------------------------------------------------------------- the estimate
def estimate_pose(depth_m: ArrayLike, K: ArrayLike, model: ModelCloud, hint: Hint, *, up: ArrayLike | None = None,
                  rgb: ArrayLike | None = None, options: FrameOptions = FrameOptions()) -> FramePose:
    """``cam_T_obj`` of ``model`` in one RGB-D frame (see the module docstring), or
    :class:`EstimateRefused` naming why not.

    ``depth_m``: (H, W) float metres, 0 / NaN = no depth; ``K``: 3x3, OpenCV convention;
    ``hint``: :class:`PixelHint` or :class:`BoxHint`; ``up``: world up in the camera frame
    (``world_T_cam[2, :3]``), None to take it from the table plane; ``rgb``: (H, W, 3), which
    breaks the ties between the object and its flip when the model has colours (None: depth alone)."""
    t0 = time.perf_counter()
    depth = _check_depth(depth_m)
    k = _check_K(K)
    if rgb is not None and np.asarray(rgb).shape[:2] != depth.shape:
        raise EstimateRefused("bad_input", f"rgb is {np.asarray(rgb).shape}, depth is {depth.shape}: not one frame")
    up_given = None if up is None else _check_up(up)
    if not isinstance(model, ModelCloud):
        raise EstimateRefused("bad_input", f"model must be a ModelCloud (prepare_model), got {type(model).__name__}")
    if not (math.isfinite(model.diameter_m) and model.diameter_m > 0 and len(model.points) >= 3
            and np.all(np.isfinite(model.points)) and np.all(np.isfinite(model.normals))):
        raise EstimateRefused("bad_input", "the model needs a positive diameter and finite points and normals "
                                           "(build it with prepare_model)")
    anchor = expected_point(depth, k, hint, options.hint_radius_px)
    if isinstance(hint, BoxHint):
        _check_scale(math.hypot(hint.w, hint.h), "the hint box", model, k, float(anchor[2]))
    points, _ = backproject(depth, k)

    def table() -> Plane | None:
        with one_thread():
            return table_plane(points, anchor, model.diameter_m, options.up_plane_ransac_m, options.perception.seed,
                               voxel=options.perception.plane_voxel_m, iterations=options.up_plane_iterations)

    tilt = options.perception.max_tilt_deg
    if up_given is None:
        plane = table()
        if plane is None:
            raise EstimateRefused("no_plane", f"no plane under the hint's point {_fmt(anchor)} m to take 'up' from; "
                                              "pass up (world up in the camera frame)")
        up_cam, up_source = plane.n, "table plane"
    else:
        up_cam, up_source = up_given, "caller"
    seen = perceive_up(depth, k, up_cam, model, anchor, options.perception)
    if seen.plane is None:
        plane = table() if up_given is not None else None
        if plane is not None:
            raise EstimateRefused("up_mismatch", f"no table plane within {tilt:g} deg of the given up {_fmt(up_cam)}: "
                                                 f"the plane under the hint is {_angle_deg(up_cam, plane.n):.1f} deg "
                                                 f"from it (its normal {_fmt(plane.n)}); pass up=None to take up "
                                                 "from the table, or fix world_T_cam")
        raise EstimateRefused("no_plane", f"no table plane within {tilt:g} deg of up {_fmt(up_cam)} near the hint's "
                                          f"point {_fmt(anchor)} m")
    cluster = _object_cluster(seen, model, hint, options, anchor)
    span = cluster.pixels.max(axis=0) - cluster.pixels.min(axis=0) + 1
    _check_scale(float(np.hypot(*span)), "the object found at the hint", model, k,
                 float(np.median(cluster.points[:, 2])))
    reg = register_model(model, cluster, seen.plane, depth, k, options.registration, seen.min_height,
                         None if rgb is None else np.asarray(rgb))
    if not (np.all(np.isfinite(reg.cam_T_obj)) and math.isfinite(reg.score)):
        raise EstimateRefused("no_fit", "the registration gave no finite pose")
    if reg.score < options.min_score:
        raise EstimateRefused("no_fit", f"the best of {reg.hypotheses} hypotheses ({reg.method}) scores "
                                        f"{reg.score:.3f} < min_score {options.min_score:g} "
                                        f"(fitness {reg.fitness:.3f})")
    return FramePose(np.asarray(reg.cam_T_obj, dtype=np.float64), float(min(reg.score, 1.0)), float(reg.fitness),
                     reg.method, up_cam, up_source, seen.plane, len(cluster.points), time.perf_counter() - t0,
                     reg.hypotheses, {"candidates": seen.candidates})


def _object_cluster(seen: Perception, model: ModelCloud, hint: Hint, options: FrameOptions, anchor: Array) -> Cluster:
    """The perceived cluster (a box: its pixels inside the grown box), or a refusal saying what was near."""
    size_mm = 1000.0 * float(model.extents[0])
    if seen.cluster is None:
        if seen.candidates == 0:
            raise EstimateRefused("no_object", f"nothing stands above the table near the hint's point "
                                               f"{_fmt(anchor)} m")
        raise EstimateRefused("no_object", f"{seen.candidates} object(s) above the table near the hint, none of the "
                                           f"model's size ({size_mm:.4g} mm) within {2 * model.diameter_m:.3g} m "
                                           "of the hint's point: wrong hint, model, model units or depth scale?")
    cluster = seen.cluster
    where = "near the hint"
    if isinstance(hint, BoxHint):
        mx, my = options.box_margin * hint.w, options.box_margin * hint.h
        px = cluster.pixels
        inside = ((px[:, 0] >= hint.x - mx) & (px[:, 0] < hint.x + hint.w + mx)
                  & (px[:, 1] >= hint.y - my) & (px[:, 1] < hint.y + hint.h + my))
        cluster, where = Cluster(cluster.points[inside], cluster.pixels[inside]), "inside the hint box"
    if len(cluster.points) < options.min_cluster_points:
        raise EstimateRefused("no_object", f"the object found {where} has {len(cluster.points)} depth pixels "
                                           f"({options.min_cluster_points} needed)")
    return cluster


def _check_scale(observed_px: float, what: str, model: ModelCloud, K: Array, z_m: float) -> None:
    """Refuse an object that spans far more pixels than the model could at depth ``z_m``."""
    expected_px = model.diameter_m * float(max(K[0, 0], K[1, 1])) / max(z_m, 1e-9)
    if observed_px > MAX_SIZE_RATIO * expected_px:
        raise EstimateRefused("scale_mismatch", f"{what} spans {observed_px:.0f} px, but the model "
                                                f"({1000 * model.diameter_m:.4g} mm across) would span at most "
                                                f"{expected_px:.1f} px at {z_m:.3g} m: is the depth's scale "
                                                "(depth_scale, metres) or the model's units wrong?")


def _fmt(v: Array) -> str:
    return "(" + ", ".join(f"{float(x):.3f}" for x in np.asarray(v).reshape(-1)) + ")"

"""BOP pose error functions: VSD, MSSD and MSPD (BOP Challenge 2019 definitions, BOP units).

Everything here is in BOP units: model points, translations, depth images and the VSD
tolerance ``delta`` in **millimetres**, pixels for MSPD. Poses map model points to the camera
frame, ``x_cam = R @ x_model + t`` (BOP's ``cam_R_m2c``, ``cam_t_m2c``).

Definitions follow bop_toolkit (``pose_error.py``, ``visibility.py``, ``misc.py``):

- MSSD = min over symmetries S of max over model points of ``|(R_e x + t_e) - (R_g S x + t_g')|``.
- MSPD = the same in the image, on pinhole projections with ``K`` (pixels, not yet scaled to a
  640 px wide image: that is done when the error is thresholded, see :func:`mspd_normalized`).
- VSD = ``(sum of step costs on the visible intersection + |union \\ intersection|) / |union|``
  over the visibility masks of the rendered model in both poses (``bop19`` visibility mode:
  a pixel with missing test depth counts as visible), per misalignment tolerance ``tau``.

Symmetries come from ``models_info.json`` as bop_toolkit reads them: ``symmetries_discrete``
(flattened 4x4, mm) and ``symmetries_continuous`` (``{axis, offset}``), the continuous ones
discretised so that the point farthest from the axis moves at most ``max_sym_disc_step`` times
the diameter between two steps: ``ceil(pi / max_sym_disc_step)`` steps (315 for 0.01).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

# ----------------------------------------------------------------------------- BOP19 constants
#: VSD tolerance for the visibility test (mm) used for every BOP19 dataset but ITODD.
VSD_DELTA_MM = 15.0
#: VSD misalignment tolerances, as fractions of the object diameter (bop_toolkit's
#: ``np.arange(0.05, 0.51, 0.05)``, floating-point values kept bit for bit).
VSD_TAUS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
#: Correctness thresholds of VSD (error, unitless).
VSD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
#: Correctness thresholds of MSSD, as fractions of the object diameter.
MSSD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
#: Correctness thresholds of MSPD, in pixels of a 640 px wide image.
MSPD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(5, 51, 5))
#: Reference image width of MSPD thresholds (px).
MSPD_REFERENCE_WIDTH = 640.0
#: Default step of the discretisation of continuous symmetries (fraction of the diameter).
MAX_SYM_DISC_STEP = 0.01

# Work-size cap of the vectorised symmetry loops (symmetries x points per chunk).
_CHUNK_ELEMS = 1 << 21
# Points with |z| below this (mm) are projected as if at this depth (BOP would divide by 0).
_MIN_ABS_Z_MM = 1e-9


@dataclass(frozen=True, eq=False)
class Symmetries:
    """A set of symmetry transformations ``x -> R[i] @ x + t[i]`` (model frame, mm); ``R`` is
    (S, 3, 3), ``t`` (S, 3). Sets built here always start with the identity."""

    R: NDArray[np.float64]
    t: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.R.shape[0])


def identity_symmetries() -> Symmetries:
    """The trivial set (no symmetry): only the identity."""
    return Symmetries(np.eye(3)[None], np.zeros((1, 3)))


def symmetry_transformations(model_info: Mapping[str, Any], max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> Symmetries:
    """Symmetry transformations of an object from its ``models_info.json`` entry (mm).

    As bop_toolkit's ``get_symmetry_transformations``: the identity plus each discrete symmetry
    (flattened 4x4, translation in mm), each combined with every discretised continuous
    rotation ``R_c = rot(axis, i * 2 pi / n)``, ``t_c = offset - R_c @ offset`` with
    ``n = ceil(pi / max_sym_disc_step)``; combination ``R = R_c @ R_d``, ``t = R_c @ t_d + t_c``.
    """
    if not (max_sym_disc_step > 0 and math.isfinite(max_sym_disc_step)):
        raise ValueError(f"max_sym_disc_step must be positive, got {max_sym_disc_step}")
    disc_R = [np.eye(3)]
    disc_t = [np.zeros(3)]
    for i, sym in enumerate(model_info.get("symmetries_discrete", []) or []):
        m = np.asarray(sym, dtype=np.float64).reshape(-1)
        if m.size != 16 or not np.all(np.isfinite(m)):
            raise ValueError(f"symmetries_discrete[{i}] must be 16 finite numbers (flattened 4x4), got {m.size}")
        m = m.reshape(4, 4)
        disc_R.append(m[:3, :3])
        disc_t.append(m[:3, 3])
    Rd = np.stack(disc_R)
    td = np.stack(disc_t)

    cont_R: list[NDArray[np.float64]] = []
    cont_t: list[NDArray[np.float64]] = []
    for i, sym in enumerate(model_info.get("symmetries_continuous", []) or []):
        try:
            axis = np.asarray(sym["axis"], dtype=np.float64).reshape(3)
            offset = np.asarray(sym.get("offset", (0.0, 0.0, 0.0)), dtype=np.float64).reshape(3)
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"symmetries_continuous[{i}] must be {{'axis': [3], 'offset': [3]}}, got {sym!r}") from None
        norm = float(np.linalg.norm(axis))
        if not math.isfinite(norm) or norm < 1e-12 or not np.all(np.isfinite(offset)):
            raise ValueError(f"symmetries_continuous[{i}]: axis must be a finite non-zero vector, got {axis.tolist()}")
        n_steps = int(math.ceil(math.pi / max_sym_disc_step))
        angles = np.arange(n_steps) * (2.0 * math.pi / n_steps)
        Rc = Rotation.from_rotvec(angles[:, None] * (axis / norm)[None, :]).as_matrix()
        cont_R.append(Rc)
        cont_t.append(offset[None, :] - Rc @ offset)
    if not cont_R:
        return Symmetries(Rd, td)
    Rc = np.concatenate(cont_R)
    tc = np.concatenate(cont_t)
    # For each discrete d (outer), each continuous c (inner): R = Rc Rd, t = Rc td + tc.
    R = np.einsum("cij,djk->dcik", Rc, Rd).reshape(-1, 3, 3)
    t = (np.einsum("cij,dj->dci", Rc, td) + tc[None, :, :]).reshape(-1, 3)
    return Symmetries(R, t)


def as_symmetries(syms: Symmetries | Sequence[Mapping[str, ArrayLike]] | tuple[ArrayLike, ArrayLike] | None) -> Symmetries:
    """Accept a :class:`Symmetries`, bop_toolkit's list of ``{'R', 't'}`` dicts, an ``(R, t)``
    pair of stacked arrays, or None (= identity only)."""
    if syms is None:
        return identity_symmetries()
    if isinstance(syms, Symmetries):
        R, t = syms.R, syms.t
    elif isinstance(syms, tuple) and len(syms) == 2 and not isinstance(syms[0], Mapping):
        R, t = syms
    else:
        items = list(syms)  # type: ignore[arg-type]
        if not items:
            return identity_symmetries()
        R = np.stack([np.asarray(s["R"], dtype=np.float64).reshape(3, 3) for s in items])  # type: ignore[index]
        t = np.stack([np.asarray(s["t"], dtype=np.float64).reshape(3) for s in items])  # type: ignore[index]
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    if len(R) != len(t) or len(R) == 0:
        raise ValueError(f"symmetries: {len(R)} rotations but {len(t)} translations")
    return Symmetries(R, t)


# ----------------------------------------------------------------------------- helpers
def _pose(R: ArrayLike, t: ArrayLike, name: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    Rm = np.asarray(R, dtype=np.float64)
    tv = np.asarray(t, dtype=np.float64)
    if Rm.size != 9 or tv.size != 3:
        raise ValueError(f"{name}: R must be 3x3 and t 3 values, got shapes {Rm.shape} and {tv.shape}")
    return Rm.reshape(3, 3), tv.reshape(3)


def _points(pts_mm: ArrayLike) -> NDArray[np.float64]:
    p = np.asarray(pts_mm, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"model points must be a non-empty (N, 3) array, got shape {p.shape}")
    return p


def _chunks(n_syms: int, n_pts: int) -> Iterable[slice]:
    step = max(1, _CHUNK_ELEMS // max(n_pts, 1))
    for s in range(0, n_syms, step):
        yield slice(s, min(s + step, n_syms))


def _gt_sym_poses(
    R_gt: NDArray[np.float64], t_gt: NDArray[np.float64], syms: Symmetries
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """GT pose composed with every symmetry: ``R_gt @ R_s``, ``R_gt @ t_s + t_gt``."""
    return R_gt[None] @ syms.R, syms.t @ R_gt.T + t_gt


def _nan_to_inf(value: float) -> float:
    return float("inf") if not math.isfinite(value) else value


# ----------------------------------------------------------------------------- MSSD
def mssd(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    pts_mm: ArrayLike,
    syms: Symmetries | Sequence[Mapping[str, ArrayLike]] | None = None,
) -> float:
    """Maximum Symmetry-aware Surface Distance (mm).

    ``min_S max_x |(R_est x + t_est) - (R_gt (R_S x + t_S) + t_gt)|`` over the model points
    ``pts_mm`` (N, 3) and the symmetry set ``syms`` (see :func:`symmetry_transformations`;
    None = no symmetry). Non-finite input poses give ``inf``; never NaN.
    """
    Re, te = _pose(R_est, t_est, "estimate")
    Rg, tg = _pose(R_gt, t_gt, "ground truth")
    pts = _points(pts_mm)
    sym = as_symmetries(syms)
    if not (np.all(np.isfinite(Re)) and np.all(np.isfinite(te)) and np.all(np.isfinite(Rg)) and np.all(np.isfinite(tg))):
        return float("inf")
    A, b = _gt_sym_poses(Rg, tg, sym)
    M = Re[None] - A  # (S, 3, 3): difference of the linear parts
    c = te[None] - b  # (S, 3)
    best = float("inf")
    for sl in _chunks(len(sym), len(pts)):
        diff = np.einsum("nj,sij->sni", pts, M[sl]) + c[sl, None, :]
        per_sym = np.sqrt(np.max(np.einsum("sni,sni->sn", diff, diff), axis=1))
        best = min(best, float(per_sym.min()))
    return _nan_to_inf(best)


# ----------------------------------------------------------------------------- MSPD
def _project(pts_cam: NDArray[np.float64], K: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pinhole projection of (..., 3) camera points (as bop_toolkit: K [R|t] x, divided by z)."""
    uvw = pts_cam @ K.T
    w = uvw[..., 2:3]
    w_safe = np.where(np.abs(w) < _MIN_ABS_Z_MM, np.where(w < 0, -_MIN_ABS_Z_MM, _MIN_ABS_Z_MM), w)
    return uvw[..., :2] / w_safe


def mspd(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    K: ArrayLike,
    pts_mm: ArrayLike,
    syms: Symmetries | Sequence[Mapping[str, ArrayLike]] | None = None,
) -> float:
    """Maximum Symmetry-aware Projection Distance (px of the actual image, not scaled).

    ``min_S max_x |proj(K, R_est x + t_est) - proj(K, R_gt (R_S x + t_S) + t_gt)|``. BOP scales
    this by ``640 / image_width`` before comparing it with the 5..50 px thresholds: use
    :func:`mspd_normalized` for that. Points at |z| < 1e-9 mm are projected at that depth
    (BOP would divide by zero), so the result is finite for finite inputs; never NaN.
    """
    Re, te = _pose(R_est, t_est, "estimate")
    Rg, tg = _pose(R_gt, t_gt, "ground truth")
    Km = np.asarray(K, dtype=np.float64).reshape(3, 3)
    pts = _points(pts_mm)
    sym = as_symmetries(syms)
    if not all(np.all(np.isfinite(a)) for a in (Re, te, Rg, tg, Km)):
        return float("inf")
    proj_est = _project(pts @ Re.T + te, Km)  # (N, 2)
    A, b = _gt_sym_poses(Rg, tg, sym)
    best = float("inf")
    for sl in _chunks(len(sym), len(pts)):
        cam = np.einsum("nj,sij->sni", pts, A[sl]) + b[sl, None, :]
        diff = _project(cam, Km) - proj_est[None]
        per_sym = np.sqrt(np.max(np.einsum("sni,sni->sn", diff, diff), axis=1))
        best = min(best, float(per_sym.min()))
    return _nan_to_inf(best)


def mspd_normalized(mspd_px: float, image_width: int) -> float:
    """MSPD scaled to a 640 px wide image, the unit of the BOP thresholds 5..50 px."""
    if image_width <= 0:
        raise ValueError(f"image width must be positive, got {image_width}")
    return float(mspd_px) * (MSPD_REFERENCE_WIDTH / float(image_width))


# ----------------------------------------------------------------------------- VSD
@lru_cache(maxsize=8)
def _pixel_rays(h: int, w: int, K_key: tuple[float, ...]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """bop_toolkit's ``Precomputer``: ``(x - cx) / fx`` and ``(y - cy) / fy`` per pixel (integer x, y)."""
    fx, cx, fy, cy = K_key
    xs, ys = np.meshgrid(np.arange(w), np.arange(h))
    pre_x, pre_y = (xs - cx) / np.float64(fx), (ys - cy) / np.float64(fy)
    pre_x.setflags(write=False)
    pre_y.setflags(write=False)
    return pre_x, pre_y


def depth_to_distance(depth_mm: ArrayLike, K: ArrayLike) -> NDArray[np.float64]:
    """Z-depth image -> distance from the camera centre along each pixel's ray (0 stays 0), with
    bop_toolkit's arithmetic (``misc.depth_im_to_dist_im_fast``), so VSD's decisions are its own to
    the last bit: ``sqrt((px * d)^2 + (py * d)^2 + d^2)`` with ``px = (x - cx) / fx`` at integer
    pixel coordinates and ``cx, cy`` the BOP ``cam_K``'s (the project's (OpenCV) ``K`` + 0.5 px, as
    the split's ``scene_camera.json`` holds it: bop_toolkit applies the formula to that K while its
    renderer puts pixel centres at +0.5; the two conventions scale the test and the rendered
    distances alike by at most 0.25 / fx). Non-finite or negative depth is treated as missing (0).
    """
    d = np.asarray(depth_mm, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth image must be (H, W), got shape {d.shape}")
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    k = np.asarray(K, dtype=np.float64).reshape(3, 3)
    key = (float(k[0, 0]), float(k[0, 2]) + 0.5, float(k[1, 1]), float(k[1, 2]) + 0.5)
    if not (math.isfinite(sum(key)) and key[0] > 0 and key[2] > 0):
        raise ValueError(f"K must be finite with positive focal lengths, got {k.tolist()}")
    pre_x, pre_y = _pixel_rays(d.shape[0], d.shape[1], key)
    return np.sqrt(np.multiply(pre_x, d) ** 2 + np.multiply(pre_y, d) ** 2 + d ** 2)


def estimate_visib_mask(
    dist_test: NDArray[np.floating], dist_model: NDArray[np.floating], delta: float, visib_mode: str = "bop19"
) -> NDArray[np.bool_]:
    """Visible surface of a rendered model (bop_toolkit ``_estimate_visib_mask``).

    ``bop19``: visible where the model is rendered and either it is at most ``delta`` behind the
    test surface or the test depth is missing (0). ``bop18``: missing test depth = not visible.
    Differences are taken in float32 as bop_toolkit does.
    """
    if dist_test.shape != dist_model.shape:
        raise ValueError(f"test and rendered images differ in size: {dist_test.shape} vs {dist_model.shape}")
    d_diff = dist_model.astype(np.float32) - dist_test.astype(np.float32)
    if visib_mode == "bop19":
        return ((d_diff <= delta) | (dist_test == 0)) & (dist_model > 0)
    if visib_mode == "bop18":
        return (d_diff <= delta) & (dist_test > 0) & (dist_model > 0)
    raise ValueError(f"unknown visibility mode {visib_mode!r} (bop18 or bop19)")


def estimate_visib_mask_gt(
    dist_test: NDArray[np.floating], dist_gt: NDArray[np.floating], delta: float, visib_mode: str = "bop19"
) -> NDArray[np.bool_]:
    """Visibility mask of the model in the ground-truth pose."""
    return estimate_visib_mask(dist_test, dist_gt, delta, visib_mode)


def estimate_visib_mask_est(
    dist_test: NDArray[np.floating],
    dist_est: NDArray[np.floating],
    visib_gt: NDArray[np.bool_],
    delta: float,
    visib_mode: str = "bop19",
) -> NDArray[np.bool_]:
    """Visibility mask of the model in the estimated pose: its own visibility test, plus every
    pixel where it is rendered inside the GT-visible area (Hodan et al. ECCVW'16, eq. 14)."""
    visib_est = estimate_visib_mask(dist_test, dist_est, delta, visib_mode)
    return visib_est | (visib_gt & (dist_est > 0))


def vsd_from_depths(
    depth_est_mm: ArrayLike,
    depth_gt_mm: ArrayLike,
    depth_test_mm: ArrayLike,
    K: ArrayLike,
    delta: float,
    taus: Sequence[float],
    normalized_by_diameter: bool,
    diameter: float,
    cost_type: str = "step",
    visib_mode: str = "bop19",
) -> list[float]:
    """VSD from already rendered depth images (mm) of the model in the estimated and GT poses.

    Returns one error in [0, 1] per ``tau``; 1.0 for every tau when both visibility masks are
    empty. ``taus`` are fractions of ``diameter`` when ``normalized_by_diameter`` (BOP19), mm
    otherwise.
    """
    if normalized_by_diameter and not (diameter > 0 and math.isfinite(diameter)):
        raise ValueError(f"VSD: the diameter must be positive to normalise by it, got {diameter}")
    if cost_type not in ("step", "tlinear"):
        raise ValueError(f"VSD: unknown pixel matching cost {cost_type!r} (step or tlinear)")
    taus = [float(x) for x in taus]
    d_est = np.asarray(depth_est_mm, dtype=np.float64)
    d_gt = np.asarray(depth_gt_mm, dtype=np.float64)
    d_test = np.asarray(depth_test_mm, dtype=np.float64)
    if d_test.ndim != 2 or not (d_test.shape == d_gt.shape == d_est.shape):
        raise ValueError(f"VSD: image sizes differ (test {d_test.shape}, gt {d_gt.shape}, est {d_est.shape})")
    # Both visibility masks lie inside the rendered pixels: work on their bounding box only
    # (the principal point moves with the crop, so distances are unchanged).
    rendered = (np.isfinite(d_est) & (d_est > 0)) | (np.isfinite(d_gt) & (d_gt > 0))
    rows = np.flatnonzero(rendered.any(axis=1))
    if rows.size == 0:
        return [1.0] * len(taus)
    cols = np.flatnonzero(rendered.any(axis=0))
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    k = np.array(np.asarray(K, dtype=np.float64).reshape(3, 3))
    k[0, 2] -= c0
    k[1, 2] -= r0
    dist_test = depth_to_distance(d_test[r0:r1, c0:c1], k)
    dist_gt = depth_to_distance(d_gt[r0:r1, c0:c1], k)
    dist_est = depth_to_distance(d_est[r0:r1, c0:c1], k)
    visib_gt = estimate_visib_mask_gt(dist_test, dist_gt, delta, visib_mode)
    visib_est = estimate_visib_mask_est(dist_test, dist_est, visib_gt, delta, visib_mode)
    inter = visib_gt & visib_est
    union_count = int(np.count_nonzero(visib_gt | visib_est))
    if union_count == 0:
        return [1.0] * len(taus)
    comp_count = union_count - int(np.count_nonzero(inter))
    dists = np.abs(dist_gt[inter] - dist_est[inter])
    if normalized_by_diameter:
        dists = dists / float(diameter)
    errors = []
    for tau in taus:
        if cost_type == "step":
            cost_sum = float(np.count_nonzero(dists >= tau))
        else:
            cost_sum = float(np.minimum(dists / tau, 1.0).sum()) if tau > 0 else float(np.count_nonzero(dists > 0))
        errors.append((cost_sum + comp_count) / float(union_count))
    return errors


def vsd(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    depth_test_mm: ArrayLike,
    K: ArrayLike,
    delta: float,
    taus: Sequence[float],
    normalized_by_diameter: bool,
    diameter: float,
    render_fn: Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.floating]],
    cost_type: str = "step",
) -> list[float]:
    """Visible Surface Discrepancy (Hodan, Michel et al., ECCV'18), one error per ``tau``.

    ``depth_test_mm`` is the test depth image (mm, 0 = missing); ``render_fn(R, t)`` renders the
    object's z-depth (mm, 0 = background) for the camera ``K`` at the test image's size
    (e.g. ``DepthRenderer.render_fn(obj_id, K, w, h)``). BOP19: ``delta`` = 15 mm,
    ``taus`` = :data:`VSD_TAUS` (fractions of the diameter, ``normalized_by_diameter=True``),
    step cost, bop19 visibility. Errors lie in [0, 1].
    """
    Re, te = _pose(R_est, t_est, "estimate")
    Rg, tg = _pose(R_gt, t_gt, "ground truth")
    depth_est = np.asarray(render_fn(Re, te), dtype=np.float64)
    depth_gt = np.asarray(render_fn(Rg, tg), dtype=np.float64)
    return vsd_from_depths(depth_est, depth_gt, depth_test_mm, K, delta, taus, normalized_by_diameter, diameter, cost_type)


def overlapping_sphere_projections(radius: float, p1: ArrayLike, p2: ArrayLike) -> bool:
    """bop_toolkit's approximate test whether the image projections of two spheres of ``radius``
    centred at camera-frame points ``p1`` and ``p2`` overlap (used to skip VSD renders)."""
    a = np.asarray(p1, dtype=np.float64).reshape(3)
    b = np.asarray(p2, dtype=np.float64).reshape(3)
    if a[2] == 0 or b[2] == 0 or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return False
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # a depth near 0: inf, compared as such
        proj_dist = float(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2]))
        return bool(proj_dist < radius * (1.0 / a[2] + 1.0 / b[2]))

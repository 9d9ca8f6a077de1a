"""Camera intrinsics from ChArUco detections (pinhole + OpenCV distortion), with outlier views.

:func:`calibrate_intrinsics` runs ``cv2.calibrateCameraExtended`` on the matched board/image
corners of every usable view, then drops views whose reprojection RMS exceeds
``outlier_factor`` times the median (and ``outlier_floor_px``), one round at a time, each with
a recorded reason, and recalibrates until no view is dropped. :func:`evaluate_intrinsics` is
the "factory intrinsics" path: it keeps a given K/dist and only measures its reprojection
error (per-view PnP). Both return an :class:`IntrinsicsResult`; its JSON
(``calibration/intrinsics.json``) carries the camera under ``"camera"`` in the form that
:func:`brave6d.core.calibration_io.read_intrinsics` reads.

Distortion models (``distortion=``, the length of OpenCV's coefficient vector):
``"0"`` none, ``"4"`` k1 k2 p1 p2, ``"5"`` + k3 (default), ``"8"`` rational (k4-k6),
``"12"`` + thin prism (s1-s4), ``"14"`` + tilted sensor (tx, ty); ``"radial"``: the five
coefficients with the tangential ones held at zero (k1 k2 0 0 k3).

Tangential distortion (p1, p2) trades off against the principal point: fitting it to a lens
that has none triples the principal point's uncertainty (demo camera, 30 board views, 0.06 px
corner noise: cx 1-sigma 0.36 px with "5", 0.11 px with "radial"), and a principal point
error of 1 px turns the hand-eye rotation by 1/f rad. :func:`calibrate_intrinsics_auto` fits
"5" and keeps it only when p1 or p2 differs from zero by :data:`TANGENTIAL_SIGNIFICANCE`
sigma or more; otherwise it refits "radial" (the choice is in :attr:`IntrinsicsResult.notes`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.atomic import read_json_as
from brave6d.core.calibration_io import write_intrinsics_file
from brave6d.core.camera import CameraError, PinholeCamera
from brave6d.core.errors import DataError, DegenerateGeometryError
from brave6d.calibration.board import CharucoDetection
from brave6d.calibration.intrinsics_covariance import INTRINSIC_NAMES, IntrinsicsCovariance, intrinsics_covariance
from brave6d.calibration.opencv_threads import on_one_opencv_thread

__all__ = [
    "DISTORTION_MODELS",
    "TANGENTIAL_SIGNIFICANCE",
    "IntrinsicsResult",
    "IntrinsicsView",
    "calibrate_intrinsics",
    "calibrate_intrinsics_auto",
    "evaluate_intrinsics",
]

SCHEMA = "brave6d.intrinsics/1"
Array = NDArray[np.float64]

#: distortion model -> (cv2 flags, number of coefficients kept)
DISTORTION_MODELS: dict[str, tuple[int, int]] = {
    "0": (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST, 0),
    "4": (cv2.CALIB_FIX_K3, 4),
    "5": (0, 5),
    "8": (cv2.CALIB_RATIONAL_MODEL, 8),
    "12": (cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL, 12),
    "14": (cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL | cv2.CALIB_TILTED_MODEL, 14),
    "radial": (cv2.CALIB_ZERO_TANGENT_DIST, 5),
}

#: :func:`calibrate_intrinsics_auto` keeps tangential distortion when ``|p| / sigma`` reaches this.
TANGENTIAL_SIGNIFICANCE = 3.0


@dataclass(frozen=True)
class IntrinsicsView:
    """One input view: used or dropped (``reason``), its corner count and reprojection RMS (px;
    for dropped views, measured with the final intrinsics when a pose could be fitted)."""

    index: int
    name: str
    used: bool
    reason: str
    n_corners: int
    rms_px: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @staticmethod
    def from_json(d: dict[str, Any]) -> IntrinsicsView:
        return IntrinsicsView(int(d["index"]), str(d["name"]), bool(d["used"]), str(d["reason"]), int(d["n_corners"]),
                              None if d.get("rms_px") is None else float(d["rms_px"]))


@dataclass(frozen=True)
class IntrinsicsResult:
    """Intrinsics and how well they explain the detections.

    ``source``: ``"charuco"`` (calibrated) or ``"factory"`` (given, only evaluated);
    ``rms_px``: overall corner reprojection RMS of the used views; ``std``: 1-sigma of
    fx, fy, cx, cy and the distortion coefficients from OpenCV (empty for ``factory``);
    ``notes``: how the model was chosen (:func:`calibrate_intrinsics_auto`);
    ``covariance``: the full covariance of the estimated parameters, correlations included
    (:mod:`brave6d.calibration.intrinsics_covariance`; None for ``factory`` or a fixed aspect ratio).
    """

    source: str
    width: int
    height: int
    K: Array
    dist: Array
    distortion_model: str
    rms_px: float
    views: tuple[IntrinsicsView, ...]
    std: dict[str, float]
    rounds: int
    warnings: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    covariance: IntrinsicsCovariance | None = None

    @property
    def dropped_views(self) -> list[IntrinsicsView]:
        return [v for v in self.views if not v.used]

    def camera(self) -> PinholeCamera:
        """The intrinsics as the kernel's :class:`~brave6d.core.camera.PinholeCamera`."""
        return PinholeCamera.from_K(self.K, self.width, self.height, self.dist)

    def to_json(self) -> dict[str, Any]:
        """JSON form; ``camera`` is :meth:`PinholeCamera.to_json` (what ``brave6d.core.calibration_io`` reads)."""
        return {
            "schema": SCHEMA,
            "camera": self.camera().to_json(),
            "source": self.source,
            "distortion_model": self.distortion_model,
            "rms_px": self.rms_px,
            "std": dict(self.std),
            "rounds": self.rounds,
            "views": [v.to_json() for v in self.views],
            "dropped_views": [{"index": v.index, "name": v.name, "reason": v.reason} for v in self.dropped_views],
            "warnings": list(self.warnings),
            "notes": list(self.notes),
            "covariance": None if self.covariance is None else self.covariance.to_json(),
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> IntrinsicsResult:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            got = d.get("schema") if isinstance(d, dict) else type(d).__name__
            raise DataError(f"intrinsics: expected schema {SCHEMA!r}, got {got!r}")
        try:
            cam = PinholeCamera.from_json(d["camera"])  # the kernel owns the camera's JSON form
            return IntrinsicsResult(
                str(d["source"]), cam.width, cam.height, cam.K, cam.dist_array, str(d["distortion_model"]),
                float(d["rms_px"]), tuple(IntrinsicsView.from_json(v) for v in d["views"]),
                {str(k): float(v) for k, v in d.get("std", {}).items()}, int(d["rounds"]),
                tuple(str(w) for w in d.get("warnings", ())), tuple(str(n) for n in d.get("notes", ())),
                None if d.get("covariance") is None else IntrinsicsCovariance.from_json(d["covariance"]),
            )
        except CameraError as exc:
            raise DataError(f"intrinsics: field 'camera.{exc.field}': {exc.problem}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"intrinsics: missing or malformed field ({type(exc).__name__}: {exc})") from None

    def save(self, path: Path | str, **extra: Any) -> Path:
        """Write :meth:`to_json` (plus ``extra`` keys) through the intrinsics file's one writer."""
        details = {**self.to_json(), **extra}
        details.pop("camera")
        return write_intrinsics_file(path, self.camera(), **details)

    @staticmethod
    def load(path: Path | str) -> IntrinsicsResult:
        """Read a file written by :meth:`save`; errors name the file."""
        return read_json_as(path, IntrinsicsResult.from_json)


# ----------------------------------------------------------------------------- helpers
def _matched(det: CharucoDetection, object_points: Array) -> tuple[Array, Array]:
    ids = np.asarray(det.corner_ids, dtype=np.int64).reshape(-1)
    px = np.asarray(det.corners_px, dtype=np.float64).reshape(-1, 2)
    keep = np.all(np.isfinite(px), axis=1) & (ids >= 0) & (ids < len(object_points))
    return object_points[ids[keep]].astype(np.float32), px[keep].astype(np.float32)


def _usable(obj: Array, min_corners: int) -> str:
    """Empty string if the view can be used, else the reason it cannot."""
    if len(obj) == 0:
        return "no board detected"
    if len(obj) < min_corners:
        return f"only {len(obj)} ChArUco corners (< {min_corners})"
    sv = np.linalg.svd(obj[:, :2] - obj[:, :2].mean(axis=0), compute_uv=False)
    if sv[1] <= 1e-6 * max(sv[0], 1e-12):
        return "corners are collinear (a single row or column of the board)"
    return ""


def _view_rms(obj: Array, img: Array, K: Array, dist: Array) -> float | None:
    """Reprojection RMS of one view with fixed intrinsics (pose by PnP), or None."""
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    except cv2.error:
        return None
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
    return rms if np.isfinite(rms) else None


def _names(n: int, names: Sequence[str] | None) -> list[str]:
    if names is None:
        return [f"view_{k:03d}" for k in range(n)]
    if len(names) != n:
        raise ValueError(f"{n} detections but {len(names)} names")
    return list(names)


# ----------------------------------------------------------------------------- calibration
@on_one_opencv_thread
def calibrate_intrinsics(
    detections: Sequence[CharucoDetection],
    object_points: ArrayLike,
    image_size: tuple[int, int],
    *,
    distortion: str = "5",
    names: Sequence[str] | None = None,
    min_corners: int = 8,
    min_views: int = 4,
    outlier_factor: float = 3.0,
    outlier_floor_px: float = 0.5,
    max_rounds: int = 5,
    K_guess: ArrayLike | None = None,
    fix_principal_point: bool = False,
    fix_aspect_ratio: bool = False,
) -> IntrinsicsResult:
    """Calibrate K and distortion from per-view ChArUco detections of one camera.

    ``object_points``: (M, 3) board corners, row = corner id; ``image_size``: (width, height).
    Views with fewer than ``min_corners`` corners or collinear corners are dropped first; then
    each round drops views whose RMS exceeds ``max(outlier_factor * median, outlier_floor_px)``
    (never below ``min_views`` views). ``K_guess`` starts the optimisation from given
    intrinsics (``fix_*`` need it or a sensible default centre). Raises
    :class:`DegenerateGeometryError` when fewer than ``min_views`` usable views remain.
    """
    if distortion not in DISTORTION_MODELS:
        raise ValueError(f"unknown distortion model {distortion!r}; choose from {list(DISTORTION_MODELS)}")
    obj_all = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)
    label = _names(len(detections), names)
    w, h = int(image_size[0]), int(image_size[1])
    matched = [_matched(d, obj_all) for d in detections]
    reasons = {k: _usable(o, min_corners) for k, (o, _) in enumerate(matched)}
    active = [k for k, r in reasons.items() if not r]
    if len(active) < min_views:
        shown = "; ".join(f"{label[k]}: {r}" for k, r in reasons.items() if r)[:400]
        raise DegenerateGeometryError(
            f"intrinsics: {len(active)} usable views of {len(detections)}, at least {min_views} needed"
            + (f" (dropped: {shown})" if shown else "")
        )
    flags, n_coef = DISTORTION_MODELS[distortion]
    if fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    if fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    K0 = np.asarray(K_guess, dtype=np.float64).reshape(3, 3).copy() if K_guess is not None else None
    if K0 is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    elif fix_principal_point or fix_aspect_ratio:
        f0 = float(max(w, h))
        K0 = np.array([[f0, 0.0, (w - 1) / 2.0], [0.0, f0, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    dist0 = np.zeros(max(n_coef, 5))

    rounds = 0
    per_view: dict[int, float] = {}
    while True:
        rounds += 1
        objs = [matched[k][0] for k in active]
        imgs = [matched[k][1] for k in active]
        try:
            rms, K, dist, rvecs, tvecs, std_i, _, per = cv2.calibrateCameraExtended(
                objs, imgs, (w, h), None if K0 is None else K0.copy(), dist0.copy(), flags=flags,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12),
            )
        except cv2.error as exc:
            raise DegenerateGeometryError(f"intrinsics: OpenCV calibration failed ({exc.err})") from None
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and np.isfinite(rms)):
            raise DegenerateGeometryError("intrinsics: calibration diverged (non-finite result); vary the board tilt")
        per_view = {k: float(e) for k, e in zip(active, np.asarray(per).reshape(-1), strict=True)}
        median = float(np.median(list(per_view.values())))
        limit = max(outlier_factor * median, outlier_floor_px)
        bad = sorted((k for k, e in per_view.items() if e > limit), key=lambda k: -per_view[k])
        bad = bad[: max(len(active) - min_views, 0)]
        if not bad or rounds >= max_rounds:
            break
        for k in bad:
            reasons[k] = (f"reprojection RMS {per_view[k]:.2f} px > {outlier_factor:g} x median "
                          f"({median:.2f} px) in round {rounds}")
        active = [k for k in active if k not in bad]

    dist = np.asarray(dist, dtype=np.float64).reshape(-1)[:n_coef]
    K = np.asarray(K, dtype=np.float64)
    std_v = np.asarray(std_i, dtype=np.float64).reshape(-1)
    coef_names = ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty"][:n_coef]
    std = {name: float(std_v[i]) for i, name in enumerate(["fx", "fy", "cx", "cy"])}
    std.update({name: float(std_v[4 + i]) for i, name in enumerate(coef_names)})
    views = []
    for k in range(len(detections)):
        n = len(matched[k][0])
        if k in active:
            views.append(IntrinsicsView(k, label[k], True, "used", n, per_view[k]))
        else:
            rms_k = _view_rms(matched[k][0], matched[k][1], K, dist) if n >= 4 and "collinear" not in reasons[k] else None
            views.append(IntrinsicsView(k, label[k], False, reasons[k], n, rms_k))
    warnings = []
    if std["fx"] > 0.01 * K[0, 0] or std["fy"] > 0.01 * K[1, 1]:
        warnings.append(f"focal length poorly determined (1-sigma fx {std['fx']:.1f} px, fy {std['fy']:.1f} px): "
                        "add views with the board tilted 30-45 deg in different directions")
    covariance = None
    if not fix_aspect_ratio:  # a tied fy is not a parameter of its own: keep OpenCV's 1-sigmas only
        free = [n for n in INTRINSIC_NAMES[: 4 + n_coef] if std.get(n, 0.0) > 0.0]
        try:
            covariance = intrinsics_covariance([matched[k][0] for k in active], [matched[k][1] for k in active], K,
                                               dist, rvecs, tvecs, free)
        except np.linalg.LinAlgError:
            warnings.append("the intrinsics' covariance could not be computed (singular); 1-sigmas only")
    # The overall RMS over the finally used views (OpenCV's value is over corners of those views).
    return IntrinsicsResult("charuco", w, h, K, dist, distortion, float(rms), tuple(views), std, rounds, tuple(warnings),
                            covariance=covariance)


def calibrate_intrinsics_auto(
    detections: Sequence[CharucoDetection],
    object_points: ArrayLike,
    image_size: tuple[int, int],
    **kwargs: Any,
) -> IntrinsicsResult:
    """:func:`calibrate_intrinsics` with model ``"5"`` when the data show tangential distortion,
    else ``"radial"`` (see the module docstring); ``kwargs`` as for :func:`calibrate_intrinsics`."""
    full = calibrate_intrinsics(detections, object_points, image_size, distortion="5", **kwargs)
    z = {k: abs(float(full.dist[i])) / full.std[k] if full.std.get(k, 0.0) > 0 else math.inf
         for i, k in ((2, "p1"), (3, "p2"))}
    shown = ", ".join(f"{k} {full.dist[i]:+.5f} ({z[k]:.1f} sigma)" for i, k in ((2, "p1"), (3, "p2")))
    if max(z.values()) >= TANGENTIAL_SIGNIFICANCE:
        note = f"tangential distortion kept: {shown} (>= {TANGENTIAL_SIGNIFICANCE:g} sigma)"
        return replace(full, notes=(*full.notes, note))
    radial = calibrate_intrinsics(detections, object_points, image_size, distortion="radial", **kwargs)
    note = (f"tangential distortion held at zero: {shown} not significant (< {TANGENTIAL_SIGNIFICANCE:g} sigma); "
            f"principal point 1-sigma {full.std['cx']:.3f}/{full.std['cy']:.3f} px with it, "
            f"{radial.std['cx']:.3f}/{radial.std['cy']:.3f} px without")
    return replace(radial, notes=(*radial.notes, note))


def evaluate_intrinsics(
    detections: Sequence[CharucoDetection],
    object_points: ArrayLike,
    image_size: tuple[int, int],
    K: ArrayLike,
    dist: ArrayLike = (),
    *,
    names: Sequence[str] | None = None,
    min_corners: int = 8,
) -> IntrinsicsResult:
    """Keep given ("factory") intrinsics and measure how well they explain the detections:
    per-view PnP with fixed K/dist, per-view and overall reprojection RMS."""
    obj_all = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)
    K_arr = np.asarray(K, dtype=np.float64).reshape(3, 3)
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    if len(d) not in (0, 4, 5, 8, 12, 14):
        raise ValueError(f"dist needs 0, 4, 5, 8, 12 or 14 coefficients, got {len(d)}")
    label = _names(len(detections), names)
    views = []
    sq, count = 0.0, 0
    for k, det in enumerate(detections):
        obj, img = _matched(det, obj_all)
        reason = _usable(obj, min_corners)
        rms = None if reason else _view_rms(obj, img, K_arr, d)
        if not reason and rms is None:
            reason = "solvePnP failed"
        if rms is not None:
            sq += rms**2 * len(obj)
            count += len(obj)
        views.append(IntrinsicsView(k, label[k], not reason, reason or "used", len(obj), rms))
    if count == 0:
        raise DegenerateGeometryError(f"intrinsics: none of the {len(detections)} views shows a usable board")
    return IntrinsicsResult(
        "factory", int(image_size[0]), int(image_size[1]), K_arr, d, str(len(d)), float(np.sqrt(sq / count)),
        tuple(views), {}, 0,
    )

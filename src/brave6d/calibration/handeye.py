"""Eye-in-hand calibration: ``tcp_T_cam`` from robot poses and ChArUco detections.

:func:`calibrate_handeye` runs:

1. per view: skip it with a reason when the board is missing, has too few or collinear
   corners, or solvePnP fails or fits badly; else ``cam_T_board`` by IPPE + Levenberg-Marquardt;
2. :func:`~brave6d.calibration.closed_form.handeye_motions`, the gate shared with
   :func:`~brave6d.calibration.closed_form.solve_closed_form`: the conditioning check on the usable
   views (clear error naming the cause: too few / duplicated poses, pure translations, small
   rotation span, near-parallel rotation axes, robot and camera motions that disagree);
3. every closed-form solver of :mod:`brave6d.calibration.closed_form`; for each, the best-fitting
   board pose and its residuals;
4. the joint refinement of :mod:`brave6d.calibration.refine` from the closed-form solution with the
   lowest reprojection RMS, with the robot's pose noise re-estimated from its corrections (the
   configured sigmas are starting values; a robot 10x noisier than configured no longer makes
   the answer worse than the closed forms, nor its 1-sigma too small);
5. residuals in px, mm and deg, a 1-sigma uncertainty, per-view reports. A result whose
   uncertainty exceeds ``max_sigma_mm``/``max_sigma_deg`` raises
   :class:`~brave6d.calibration.refusal.HandEyeRefusedError` instead of being returned, naming the
   dominant cause (intrinsics uncertainty, pose conditioning, detection count, reprojection error)
   with its share (:mod:`brave6d.calibration.refusal`).

The intrinsics are held fixed, their uncertainty propagated (``intrinsics_cov``, or
``intrinsics_std`` taken as independent), unless ``refine_intrinsics`` names parameters to solve
jointly (:mod:`brave6d.calibration.refine`). A static camera looking at a board on the tool is
calibrated by :func:`~brave6d.calibration.eye_to_hand.calibrate_eye_to_hand` with the same steps.

A view with part of the board hidden contributes fewer residuals (natural down-weighting);
a view that disagrees with the rest (bad detection, robot pose error) is down-weighted by the
robust loss and flagged in :attr:`HandEyeResult.views`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.errors import BraveError, DegenerateGeometryError
from brave6d.core.transforms import check_rigid, make_transform
from brave6d.calibration.board import CharucoDetection
from brave6d.calibration.closed_form import CLOSED_FORM_METHODS, PairMode, handeye_motions
from brave6d.calibration.conditioning import ConditioningThresholds, check_handeye_conditioning
from brave6d.calibration.handeye_result import (
    FitSummary,
    HandEyeResult,
    MethodResult,
    ViewReport,
)
from brave6d.calibration.intrinsics_covariance import IntrinsicsCovariance
from brave6d.calibration.refine import (
    CornerData,
    Refinement,
    RefineSettings,
    evaluate,
    fit_board,
    initial_board,
    loss_weights,
    pixel_noise_from_pnp,
    refine_handeye,
    reprojection_errors,
    solution_uncertainty,
)
from brave6d.calibration.opencv_threads import on_one_opencv_thread
from brave6d.calibration.refusal import HandEyeRefusedError, explain_uncertainty

__all__ = ["HandEyeOptions", "HandEyeView", "calibrate_handeye", "estimate_board_pose", "solve_handeye"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class HandEyeView:
    """One calibration view: the robot pose reported with the image and the corners found in it."""

    base_T_tcp: Array
    corner_ids: NDArray[np.int32]
    corners_px: Array
    name: str = ""

    @staticmethod
    def from_detection(base_T_tcp: ArrayLike, detection: CharucoDetection, name: str = "") -> HandEyeView:
        """Pair a robot pose with a :func:`~brave6d.calibration.board.detect_charuco` result."""
        return HandEyeView(np.asarray(base_T_tcp, dtype=np.float64), detection.corner_ids, detection.corners_px, name)


@dataclass(frozen=True)
class HandEyeOptions:
    """Settings of :func:`calibrate_handeye`.

    ``methods``/``pairs``: closed-form solvers and which view pairs they use.
    ``loss``/``f_scale_px``: robust loss of scipy's ``least_squares`` and its scale in pixels.
    ``robot_sigma_mm``/``robot_sigma_deg``/``pixel_sigma_px``: noise model of the refinement
    (:mod:`brave6d.calibration.refine`; robot sigmas None = robot poses taken as exact).
    ``estimate_robot_noise``: the robot sigmas are starting values, re-estimated from the
    refinement's robot pose corrections (a robot 10x less accurate than configured would
    otherwise bend the result and shrink its 1-sigma); a warning names an estimate more than
    2x off the configured value. False keeps them fixed.
    ``min_corners``: fewer corners in a view -> view skipped. ``max_pnp_rms_px``: a view whose
    own PnP fit is worse is skipped (wrong detection or wrong intrinsics).
    ``max_sigma_mm``/``max_sigma_deg``: a result whose 1-sigma uncertainty (norm over the axes)
    exceeds these raises :class:`~brave6d.calibration.refusal.HandEyeRefusedError`, a
    :class:`DegenerateGeometryError` naming the dominant cause (None: no limit).
    ``refine_intrinsics``: intrinsic parameters (``"fx"``, ``"fy"``, ``"cx"``, ``"cy"``, ``"k1"``, ...)
    solved jointly with the hand-eye transform (the robot's motions constrain them too); empty:
    held as given.
    ``downweight_flag``: used views whose mean robust weight falls below it are flagged.
    ``max_correction_sigma``/``max_outlier_fraction``: with the robot model, a view whose robot
    pose needs a correction above this many sigmas (RMS over the 6 components) and above 3x
    the median view is dropped as an outlier and the refinement repeated, for at most this
    fraction of the views.
    ``refine``: False returns the best closed-form result (with its uncertainty from the model).
    """

    methods: tuple[str, ...] = ("tsai", "park", "daniilidis")
    pairs: PairMode = "all"
    loss: str = "soft_l1"
    f_scale_px: float = 1.0
    robot_sigma_mm: float | None = 0.1
    robot_sigma_deg: float | None = 0.01
    pixel_sigma_px: float | None = None
    estimate_robot_noise: bool = True
    min_corners: int = 6
    max_pnp_rms_px: float = 5.0
    conditioning: ConditioningThresholds = field(default_factory=ConditioningThresholds)
    max_sigma_mm: float | None = 2.0
    max_sigma_deg: float | None = 0.2
    max_nfev: int = 100
    downweight_flag: float = 0.5
    max_correction_sigma: float = 4.0
    max_outlier_fraction: float = 0.25
    refine: bool = True
    refine_intrinsics: tuple[str, ...] = ()

    def refine_settings(self, robot: bool = True, intrinsics_std: Mapping[str, float] | None = None,
                        intrinsics_cov: IntrinsicsCovariance | None = None) -> RefineSettings:
        return RefineSettings(
            loss=self.loss, f_scale_px=self.f_scale_px,
            robot_sigma_mm=self.robot_sigma_mm if robot else None,
            robot_sigma_deg=self.robot_sigma_deg if robot else None,
            pixel_sigma_px=self.pixel_sigma_px, max_nfev=self.max_nfev, intrinsics_std=intrinsics_std,
            estimate_robot_sigma=self.estimate_robot_noise, intrinsics_cov=intrinsics_cov,
            refine_intrinsics=tuple(self.refine_intrinsics) if robot else (),
        )


# ----------------------------------------------------------------------------- per-view PnP
@on_one_opencv_thread
def _pnp(obj: Array, img: Array, K: Array, dist: Array) -> tuple[Array, float] | None:
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if n == 0:
            return None
        best = int(np.argmin(np.asarray(errs).reshape(-1))) if errs is not None and len(errs) else 0
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[best].copy(), tvecs[best].copy())
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    except cv2.error:
        return None
    T = make_transform(Rotation.from_rotvec(rvec.reshape(3)).as_matrix(), tvec.reshape(3))
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    if not (np.all(np.isfinite(T)) and math.isfinite(rms)) or T[2, 3] <= 0:
        return None
    return T, rms


def estimate_board_pose(
    corner_ids: ArrayLike, corners_px: ArrayLike, object_points: ArrayLike, K: ArrayLike, dist: ArrayLike = ()
) -> tuple[Array, float] | None:
    """``(cam_T_board, PnP RMS px)`` of one detection (IPPE + LM), or None if PnP fails."""
    ids = np.asarray(corner_ids, dtype=np.int64).reshape(-1)
    obj = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)[ids]
    return _pnp(obj, np.asarray(corners_px, dtype=np.float64).reshape(-1, 2),
                np.asarray(K, dtype=np.float64).reshape(3, 3), np.asarray(dist, dtype=np.float64).reshape(-1))


def _prepare(
    views: Sequence[HandEyeView], object_points: Array, K: Array, dist: Array, opts: HandEyeOptions
) -> tuple[CornerData, list[int], list[ViewReport]]:
    """Usable views stacked as :class:`CornerData`, their input indices, and one report per view."""
    reports: list[ViewReport] = []
    used: list[tuple[int, Array, Array, Array, Array]] = []
    n_obj = len(object_points)
    for k, view in enumerate(views):
        name = view.name or f"view_{k:03d}"
        G = check_rigid(view.base_T_tcp, f"{name}: base_T_tcp")
        ids = np.asarray(view.corner_ids).reshape(-1).astype(np.int64)
        px = np.asarray(view.corners_px, dtype=np.float64).reshape(-1, 2)
        if len(ids) != len(px):
            raise BraveError(f"{name}: {len(ids)} corner ids but {len(px)} corner positions")
        if len(ids) and (ids.min() < 0 or ids.max() >= n_obj):
            raise BraveError(f"{name}: corner ids {ids.min()}..{ids.max()} outside the board's 0..{n_obj - 1}")
        if len(np.unique(ids)) != len(ids):
            raise BraveError(f"{name}: repeated corner ids")
        finite = np.all(np.isfinite(px), axis=1)
        ids, px = ids[finite], px[finite]
        reason = ""
        if len(ids) == 0:
            reason = "no board detected"
        elif len(ids) < opts.min_corners:
            reason = f"only {len(ids)} ChArUco corners (< {opts.min_corners})"
        else:
            obj = object_points[ids]
            sv = np.linalg.svd(obj[:, :2] - obj[:, :2].mean(axis=0), compute_uv=False)
            if sv[1] <= 1e-9 * max(sv[0], 1e-12):
                reason = "corners are collinear (a single row or column of the board)"
            else:
                pnp = _pnp(obj, px, K, dist)
                if pnp is None:
                    reason = "solvePnP failed"
                elif pnp[1] > opts.max_pnp_rms_px:
                    reason = (f"board pose fits badly: PnP reprojection RMS {pnp[1]:.2f} px > "
                              f"{opts.max_pnp_rms_px:g} px (wrong detection or wrong intrinsics)")
                else:
                    used.append((k, G, pnp[0], obj, px))
        reports.append(ViewReport(k, name, not reason, reason or "used", len(ids)))
    if not used:
        empty = CornerData(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros((0, 2)),
                           np.zeros(0, np.int64))
        return empty, [], reports
    data = CornerData(
        G=np.stack([u[1] for u in used]),
        C=np.stack([u[2] for u in used]),
        obj=np.concatenate([u[3] for u in used]),
        img=np.concatenate([u[4] for u in used]),
        view_of=np.concatenate([np.full(len(u[3]), v, np.int64) for v, u in enumerate(used)]),
    )
    return data, [u[0] for u in used], reports


def _closed_form_as_refinement(
    X: Array, W: Array, data: CornerData, K: Array, dist: Array, settings: RefineSettings
) -> Refinement:
    """A closed-form answer packaged like a refinement (plain model, no corrections)."""
    unc, weights = solution_uncertainty(X, W, data, K, dist, settings)
    errors = reprojection_errors(X, W, data, K, dist)[0]
    sigma = settings.pixel_sigma_px or pixel_noise_from_pnp(data, K, dist)
    return Refinement(X, W, np.zeros((data.n_views, 6)), errors, weights, float(sigma), unc, 0)


# ----------------------------------------------------------------------------- main entry
def calibrate_handeye(
    views: Sequence[HandEyeView],
    object_points: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike = (),
    options: HandEyeOptions | None = None,
    intrinsics_std: Mapping[str, float] | None = None,
    intrinsics_cov: IntrinsicsCovariance | None = None,
) -> HandEyeResult:
    """Eye-in-hand calibration from robot poses and ChArUco corners (see the module docstring).

    ``object_points``: (M, 3) board corners, row = corner id (e.g.
    :func:`~brave6d.calibration.board.board_corner_points`); ``K``, ``dist``: camera intrinsics (OpenCV);
    ``intrinsics_cov``: their covariance (:attr:`IntrinsicsResult.covariance`) or ``intrinsics_std``
    their 1-sigma (:attr:`IntrinsicsResult.std`, taken as independent), added to the uncertainty.
    Raises :class:`DegenerateGeometryError` naming the cause when the usable views cannot
    determine ``tcp_T_cam`` reliably (:class:`~brave6d.calibration.refusal.HandEyeRefusedError` when
    its uncertainty exceeds the options' limits).
    """
    return solve_handeye(views, object_points, K, dist, options, intrinsics_std, intrinsics_cov, "eye-in-hand")


def solve_handeye(
    views: Sequence[HandEyeView],
    object_points: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike,
    options: HandEyeOptions | None,
    intrinsics_std: Mapping[str, float] | None,
    intrinsics_cov: IntrinsicsCovariance | None,
    setup: str,
) -> HandEyeResult:
    """:func:`calibrate_handeye`'s steps for ``setup`` (``"eye-in-hand"``; ``"eye-to-hand"``: the views
    carry the inverted robot poses, :func:`~brave6d.calibration.eye_to_hand.calibrate_eye_to_hand`)."""
    opts = options or HandEyeOptions()
    if not opts.methods:
        raise ValueError("HandEyeOptions.methods must name at least one closed-form method")
    for m in opts.methods:
        if m not in CLOSED_FORM_METHODS:
            raise ValueError(f"unknown hand-eye method {m!r}; choose from {sorted(CLOSED_FORM_METHODS)}")
    loss_weights(np.zeros(1), opts.loss, 1.0)  # validates the loss name early
    obj_pts = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)
    K_arr = np.asarray(K, dtype=np.float64).reshape(3, 3)
    dist_arr = np.asarray(dist, dtype=np.float64).reshape(-1)
    if not (np.all(np.isfinite(K_arr)) and np.all(np.isfinite(dist_arr))):
        raise BraveError("hand-eye: K and dist must be finite")

    data, used_index, reports = _prepare(views, obj_pts, K_arr, dist_arr, opts)
    skipped = [r for r in reports if not r.used]
    if data.n_views < opts.conditioning.min_poses and skipped:
        reasons = "; ".join(f"{r.name}: {r.reason}" for r in skipped[:6])
        raise DegenerateGeometryError(
            f"too few poses for hand-eye calibration: {data.n_views} usable of {len(views)} views, at least "
            f"{opts.conditioning.min_poses} needed (skipped: {reasons})"
        )
    names = [r.name for r in reports if r.used]
    A, B, conditioning = handeye_motions(list(data.G), list(data.C), opts.pairs, opts.conditioning, names, setup)

    t_start = time.perf_counter()
    rows = _closed_form_rows(A, B, data, K_arr, dist_arr, opts)
    good = [r for r in rows if r.tcp_T_cam is not None and r.base_T_board is not None and r.residuals is not None]
    if not good:
        raise DegenerateGeometryError(
            "every closed-form hand-eye method failed: " + "; ".join(f"{r.method}: {r.error}" for r in rows)
        )
    start = min(good, key=lambda r: r.residuals.reprojection_rms_px)  # type: ignore[union-attr]
    assert start.tcp_T_cam is not None and start.base_T_board is not None

    settings = opts.refine_settings(robot=opts.refine, intrinsics_std=intrinsics_std, intrinsics_cov=intrinsics_cov)
    kept = list(range(data.n_views))
    dropped: dict[int, str] = {}
    if opts.refine:
        ref, kept, dropped = _refine_dropping_outliers(start.tcp_T_cam, start.base_T_board, data, K_arr, dist_arr,
                                                       settings, opts, names, setup)
        robot_text = "with per-view robot pose corrections" if settings.models_robot else "robot poses exact"
        method_name = f"refined ({opts.loss} loss, {robot_text}; start: {start.method})"
    else:
        ref = _closed_form_as_refinement(start.tcp_T_cam, start.base_T_board, data, K_arr, dist_arr, settings)
        method_name = start.method
    final_data = data.subset(kept) if dropped else data
    if dropped:  # judge every method on the views that were finally kept
        conditioning = check_handeye_conditioning(list(final_data.G), list(final_data.C), opts.conditioning,
                                                  [names[v] for v in kept], setup)
        rows = [_rejudge(r, final_data, K_arr, dist_arr, opts) for r in rows]
    X, W, unc = ref.tcp_T_cam, ref.base_T_board, ref.uncertainty
    K_fit = ref.K if ref.K is not None else K_arr
    dist_fit = ref.dist if ref.dist is not None else dist_arr
    residuals = evaluate(X, W, final_data, K_fit, dist_fit)
    if opts.refine:
        rows.append(MethodResult("refined", X, W, residuals, time.perf_counter() - t_start))
    breakdown = explain_uncertainty(
        unc, limit_mm=opts.max_sigma_mm, limit_deg=opts.max_sigma_deg, pixel_sigma_px=ref.pixel_sigma_px,
        n_corners=len(final_data.obj), n_views=final_data.n_views, n_input_views=len(views),
        board_corners=len(obj_pts), weakest_rotation_deg=conditioning.weakest_rotation_deg or 0.0,
        recommended_views=opts.conditioning.recommended_poses,
        recommended_weakest_deg=opts.conditioning.recommended_weakest_deg,
    )
    if breakdown.exceeded:
        raise HandEyeRefusedError(breakdown)

    warnings = list(conditioning.warnings)
    robot = settings.models_robot
    corr_sigma = _correction_sigmas(ref) if robot else np.zeros(len(kept))
    corr_mm = 1000.0 * np.linalg.norm(ref.corrections[:, 3:], axis=1)
    corr_deg = np.degrees(np.linalg.norm(ref.corrections[:, :3], axis=1))
    final: dict[int, ViewReport] = {r.index: r for r in skipped}
    by_index = {r.index: r for r in reports}
    for v, reason in dropped.items():
        base = by_index[used_index[v]]
        final[base.index] = ViewReport(base.index, base.name, False, reason, base.n_corners)
        warnings.append(f"{base.name}: {reason}")
    for j, v in enumerate(kept):
        k = used_index[v]
        sel = final_data.view_of == j
        e = ref.fit_errors_px[sel]
        rms = float(np.sqrt(np.mean(e**2)))
        mean_w = float(ref.weights[sel].mean())
        base = by_index[k]
        reason = "used"
        if mean_w < opts.downweight_flag:
            reason = f"used, down-weighted by the robust loss (mean corner weight {mean_w:.2f})"
        elif robot and corr_sigma[j] > opts.max_correction_sigma:
            reason = f"used, robot pose corrected by {corr_sigma[j]:.1f} sigma of the robot error model"
        if reason != "used":
            warnings.append(f"{base.name}: {reason}; reprojection RMS {rms:.2f} px")
        final[k] = ViewReport(
            k, base.name, True, reason, base.n_corners, rms, mean_w,
            float(corr_mm[j]) if robot else None, float(corr_deg[j]) if robot else None, tuple(float(x) for x in e),
        )
    if robot:
        warnings += _robot_noise_warnings(ref, corr_sigma, opts)
    estimated = robot and opts.estimate_robot_noise
    fit = FitSummary(
        fit_rms_px=float(np.sqrt(np.mean(ref.fit_errors_px**2))), pixel_sigma_px=ref.pixel_sigma_px,
        robot_sigma_mm=ref.robot_sigma_mm if robot else None, robot_sigma_deg=ref.robot_sigma_deg if robot else None,
        robot_correction_rms_mm=float(np.sqrt(np.mean(corr_mm**2))) if robot else None,
        robot_correction_rms_deg=float(np.sqrt(np.mean(corr_deg**2))) if robot else None,
        iterations=ref.nfev,
        robot_sigma_configured_mm=opts.robot_sigma_mm if estimated else None,
        robot_sigma_configured_deg=opts.robot_sigma_deg if estimated else None,
    )
    return HandEyeResult(
        method=method_name, tcp_T_cam=X, base_T_board=W, residuals=residuals, fit=fit, uncertainty=unc,
        methods=tuple(rows), views=tuple(final[k] for k in sorted(final)), conditioning=conditioning,
        K=K_fit, dist=dist_fit, loss=opts.loss, f_scale_px=opts.f_scale_px, warnings=tuple(warnings),
        intrinsics_std=ref.intrinsics_std,
    )


def _closed_form_rows(
    A: Array, B: Array, data: CornerData, K: Array, dist: Array, opts: HandEyeOptions
) -> list[MethodResult]:
    """Every closed-form method on the checked motions ``A, B`` (:func:`handeye_motions`) with
    its best board pose and residuals (or its failure)."""
    rows: list[MethodResult] = []
    for method in opts.methods:
        t0 = time.perf_counter()
        try:
            X = CLOSED_FORM_METHODS[method](A, B)
            if not np.all(np.isfinite(X)):
                raise DegenerateGeometryError("non-finite solution")
        except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError) as exc:
            rows.append(MethodResult(method, None, None, None, time.perf_counter() - t0, f"failed: {exc}"))
            continue
        dt = time.perf_counter() - t0
        W = fit_board(X, initial_board(X, data), data, K, dist, opts.loss, opts.f_scale_px, opts.max_nfev)
        rows.append(MethodResult(method, X, W, evaluate(X, W, data, K, dist), dt))
    return rows


def _rejudge(row: MethodResult, data: CornerData, K: Array, dist: Array, opts: HandEyeOptions) -> MethodResult:
    """A closed-form row re-evaluated (board pose refitted) on another set of views."""
    if row.tcp_T_cam is None or row.base_T_board is None:
        return row
    W = fit_board(row.tcp_T_cam, row.base_T_board, data, K, dist, opts.loss, opts.f_scale_px, opts.max_nfev)
    return replace(row, base_T_board=W, residuals=evaluate(row.tcp_T_cam, W, data, K, dist))


def _correction_sigmas(ref: Refinement) -> Array:
    """Per view: RMS over the 6 components of the robot pose correction in units of the sigma of
    the refinement's robot error model."""
    assert ref.robot_sigma_deg is not None and ref.robot_sigma_mm is not None
    scale = np.r_[[1.0 / math.radians(ref.robot_sigma_deg)] * 3, [1.0 / (ref.robot_sigma_mm * 1e-3)] * 3]
    return np.sqrt(np.mean((ref.corrections * scale) ** 2, axis=1))


def _robot_noise_warnings(ref: Refinement, corr_sigma: Array, opts: HandEyeOptions) -> list[str]:
    """A warning when the robot is (estimated to be, or its corrections say it is) much less or
    more accurate than configured."""
    assert ref.robot_sigma_mm and ref.robot_sigma_deg and opts.robot_sigma_mm and opts.robot_sigma_deg
    configured = f"{opts.robot_sigma_mm:g} mm / {opts.robot_sigma_deg:g} deg"
    advice = ("give the robot's real accuracy with --robot-sigma-mm / --robot-sigma-deg "
              "(HandEyeOptions.robot_sigma_mm / robot_sigma_deg)")
    if opts.estimate_robot_noise:
        ratios = (ref.robot_sigma_mm / opts.robot_sigma_mm, ref.robot_sigma_deg / opts.robot_sigma_deg)
        if max(max(ratios), 1.0 / min(ratios)) <= 2.0:
            return []
        return [f"robot pose noise estimated from the refinement's corrections is {ref.robot_sigma_mm:.3g} mm / "
                f"{ref.robot_sigma_deg:.3g} deg per axis ({ratios[0]:.2g}x / {ratios[1]:.2g}x the configured "
                f"{configured}); the refinement used the estimate; {advice}"]
    if len(corr_sigma) and float(np.median(corr_sigma)) > 2.0:
        return [f"the typical robot pose correction is {float(np.median(corr_sigma)):.1f} sigma of the robot error "
                f"model ({configured}): the robot is less accurate than assumed; {advice}"]
    return []


def _refine_dropping_outliers(
    X0: Array, W0: Array, data: CornerData, K: Array, dist: Array, settings: RefineSettings,
    opts: HandEyeOptions, names: list[str], setup: str = "eye-in-hand",
) -> tuple[Refinement, list[int], dict[int, str]]:
    """Refine; while the worst view needs a robot pose correction far beyond the error model
    (``max_correction_sigma`` and 3x the median view), drop it with a reason and refine again.
    Such a view's image and robot pose disagree (wrong pose/image pairing, robot moved, bad
    detection); with its own free pose it would carry no information anyway. The error model is
    the refinement's own (estimated robot noise); each new refinement starts from it."""
    kept = list(range(data.n_views))
    dropped: dict[int, str] = {}
    max_drop = int(opts.max_outlier_fraction * data.n_views)
    while True:
        sub = data.subset(kept) if dropped else data
        ref = refine_handeye(X0, W0, sub, K, dist, settings)
        if not settings.models_robot or len(dropped) >= max_drop:
            return ref, kept, dropped
        settings = replace(settings, robot_sigma_mm=ref.robot_sigma_mm, robot_sigma_deg=ref.robot_sigma_deg)
        c = _correction_sigmas(ref)
        worst = int(np.argmax(c))
        if c[worst] <= opts.max_correction_sigma or c[worst] <= 3.0 * float(np.median(c)):
            return ref, kept, dropped
        if len(kept) - 1 < opts.conditioning.min_poses:
            return ref, kept, dropped
        v = kept[worst]
        mm = 1000.0 * float(np.linalg.norm(ref.corrections[worst, 3:]))
        deg = math.degrees(float(np.linalg.norm(ref.corrections[worst, :3])))
        dropped[v] = (
            f"dropped as an outlier: image and robot pose disagree (the view needs a robot pose correction of "
            f"{mm:.2f} mm / {deg:.3f} deg, {c[worst]:.0f} sigma of the robot error model); check the pose/image "
            "pairing and the detection"
        )
        kept = [k for k in kept if k != v]
        X0, W0 = ref.tcp_T_cam, ref.base_T_board
        check_handeye_conditioning([data.G[k] for k in kept], [data.C[k] for k in kept], opts.conditioning,
                                   [names[k] for k in kept], setup)



"""Reprojection model of an eye-in-hand capture and the joint refinement of ``tcp_T_cam``.

Model: a board corner ``P`` (board frame) seen in view ``i`` projects through
``cam_T_board_i = inv(tcp_T_cam) inv(base_T_tcp_i E_i) base_T_board`` with the camera's ``K``
and ``dist`` (OpenCV). :func:`refine_handeye` minimises, with scipy's ``least_squares`` and a
robust loss, the reprojection error of all corners of all views over ``tcp_T_cam`` and
``base_T_board`` (6 + 6 unknowns, each a rotation vector and a translation applied to the
starting estimate: ``R = exp([r]x) R_0``, ``t = t_0 + dt``, so no singularity near the solution).

Robot pose error. Robot poses are not exact (repeatability, backlash, timing). Taken as
exact, a 0.1 mm TCP error, which shifts the board image like a 0.01 deg camera tilt, leaks
into the rotation of ``tcp_T_cam`` (synthetic study: 3-4x larger rotation error than with the
model below). With ``robot_sigma_mm``/``robot_sigma_deg`` set (default 0.1 mm, 0.01 deg per
axis, the spec's default robot pose error) each view also gets a TCP pose correction ``E_i``
(6 unknowns, TCP frame) with a Gaussian prior of those sigmas: the maximum-likelihood model of
a noisy robot. Pixel residuals are whitened by the corner noise ``pixel_sigma_px``, estimated
from the per-view PnP residuals (which robot errors cannot reach) unless given, and priors by
the robot sigmas; the robust loss applies to both, so a view whose image and robot pose
disagree grows a large correction instead of bending ``tcp_T_cam``.

The configured robot sigmas are only a starting point (``estimate_robot_sigma``, default on):
a robot that is really 10x less accurate than configured would have its errors pressed into
``tcp_T_cam`` (and genuine views dropped as outliers, and a 1-sigma far too small). After each
solve the rotation and translation sigmas are re-estimated from the corrections, a robust
variance-component estimate (Foerstner): per view, the squared whitened corrections over their
redundancy ``1 - h`` (``h`` the diagonal of the hat matrix), median over views, made consistent
for chi-square with 3 degrees of freedom; the solve is repeated until they change by less than
10%. The pixel noise needs no such step: it comes from the per-view PnP fits. The Jacobian is sparse
(a view's corners depend on the 12 shared unknowns and its own 6), with exact trust-region
steps up to 31 views and LSMR steps beyond. With the robot sigmas set to None the model is
the plain 12-unknown one.

Intrinsics. Held fixed (default), their own uncertainty (``intrinsics_cov``: the full covariance
of :mod:`brave6d.calibration.intrinsics_covariance`, or ``intrinsics_std``: 1-sigmas taken as
independent) is propagated to first order. With ``refine_intrinsics`` (parameter names, e.g.
``("fx", "fy", "cx", "cy", "k1", "k2", "k3")``) they are unknowns of the same solve instead: the
robot's motions then constrain them too (how far the board moved is known in metres, which pins
the focal length), and the uncertainty they add is the difference between the covariance of
``tcp_T_cam`` with them free and with them held (the real 16-view eye-to-hand set of the tests:
1-sigma 2.4 mm held and propagated, 0.9 mm refined jointly, of which 0.6 mm with the intrinsics
held; ``benchmarks/handeye_folder.py``).

Uncertainty (:class:`~brave6d.calibration.handeye_result.Uncertainty`): the per-view corrections are
eliminated exactly (Schur complement of the normal matrix); reported are the Gauss-Newton
covariance scaled by the residual variance, a sandwich covariance clustered by view (both with
the intrinsics as they are), and the contribution of the intrinsics' uncertainty.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import sparse
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.transforms import invert, make_transform, rotation_distance
from brave6d.calibration.closed_form import motion_pairs
from brave6d.calibration.handeye_result import Residuals, Uncertainty
from brave6d.calibration.intrinsics_covariance import INTRINSIC_NAMES, IntrinsicsCovariance

__all__ = [
    "CornerData",
    "RefineSettings",
    "Refinement",
    "axxb_residuals",
    "evaluate",
    "fit_board",
    "initial_board",
    "loss_weights",
    "pixel_noise_from_pnp",
    "refine_handeye",
    "reprojection_errors",
    "solution_uncertainty",
]

Array = NDArray[np.float64]
_FD_STEP = 1e-7  # forward-difference step (rad, m)
_DENSE_MAX_UNKNOWNS = 200  # up to 31 views with the robot model: exact steps; more views: LSMR
_NOISE_ITERATIONS = 8  # most solves of the robot noise estimate (it converges in 2-4)
_NOISE_TOLERANCE = 1.1  # stop when both sigmas change by less than this factor
_NOISE_RANGE = 100.0  # the estimate stays within this factor of the configured sigmas
_CHI2_3_MEDIAN = 2.365973884375338 / 3.0  # median of chi-square(3) / 3


@dataclass(frozen=True)
class CornerData:
    """Stacked corners of the used views: robot poses ``G`` (V, 4, 4, as reported), PnP board
    poses ``C`` (V, 4, 4), board points ``obj`` (M, 3), pixels ``img`` (M, 2), and the view of
    each corner ``view_of`` (M,)."""

    G: Array
    C: Array
    obj: Array
    img: Array
    view_of: NDArray[np.int64]

    @property
    def n_views(self) -> int:
        return len(self.G)

    def subset(self, views: Sequence[int]) -> CornerData:
        """The data of the views ``views`` (indices into this data), renumbered 0..len-1."""
        idx = np.asarray(list(views), dtype=np.int64)
        remap = np.full(self.n_views, -1, np.int64)
        remap[idx] = np.arange(len(idx))
        keep = remap[self.view_of] >= 0
        return CornerData(self.G[idx], self.C[idx], self.obj[keep], self.img[keep], remap[self.view_of[keep]])


# ----------------------------------------------------------------------------- geometry
def _inv_batch(T: Array) -> Array:
    R = np.swapaxes(T[:, :3, :3], 1, 2)
    out = np.zeros_like(T)
    out[:, :3, :3] = R
    out[:, :3, 3] = -np.einsum("vab,vb->va", R, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def _perturb(T0: Array, p: Array) -> Array:
    """``[exp([p[:3]]x) R0, t0 + p[3:6]]``."""
    T = T0.copy()
    T[:3, :3] = Rotation.from_rotvec(p[:3]).as_matrix() @ T0[:3, :3]
    T[:3, 3] = T0[:3, 3] + p[3:6]
    return T


def _corrections(D: Array) -> Array:
    """(V, 6) rotation vector + translation -> (V, 4, 4) TCP-frame corrections."""
    E = np.zeros((len(D), 4, 4))
    E[:, :3, :3] = Rotation.from_rotvec(D[:, :3]).as_matrix()
    E[:, :3, 3] = D[:, 3:]
    E[:, 3, 3] = 1.0
    return E


def _camera_points(X: Array, W: Array, G_inv: Array, data: CornerData) -> Array:
    C = invert(X)[None] @ G_inv @ W[None]
    return np.einsum("mab,mb->ma", C[data.view_of, :3, :3], data.obj) + C[data.view_of, :3, 3]


def _project(P: Array, K: Array, dist: Array) -> Array:
    P = P.copy()
    P[:, 2] = np.maximum(P[:, 2], 1e-6)  # points behind the camera stay finite (never at a solution)
    if dist.size == 0 or not np.any(dist):
        uvw = P @ K.T
        return uvw[:, :2] / uvw[:, 2:3]
    proj, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    return proj.reshape(-1, 2)


def reprojection_errors(
    tcp_T_cam: Array, base_T_board: Array, data: CornerData, K: Array, dist: Array, G: Array | None = None
) -> tuple[Array, Array]:
    """Per-corner ``(error px (M,), depth m (M,))``; ``G`` overrides the robot poses."""
    P = _camera_points(tcp_T_cam, base_T_board, _inv_batch(data.G if G is None else G), data)
    return np.linalg.norm(_project(P, K, dist) - data.img, axis=1), P[:, 2]


def loss_weights(r: Array, loss: str, f_scale: float) -> Array:
    """IRLS weights ``rho'(z)``, ``z = (r / f_scale)^2``, of scipy's robust losses."""
    z = (np.asarray(r, dtype=np.float64) / f_scale) ** 2
    if loss == "linear":
        return np.ones_like(z)
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))
    if loss == "cauchy":
        return 1.0 / (1.0 + z)
    if loss == "arctan":
        return 1.0 / (1.0 + z**2)
    raise ValueError(f"unknown loss {loss!r} (linear, soft_l1, huber, cauchy, arctan)")


def initial_board(tcp_T_cam: Array, data: CornerData) -> Array:
    """Mean of the board poses implied by each view, ``base_T_tcp_i X cam_T_board_i``."""
    W = data.G @ tcp_T_cam[None] @ data.C
    return make_transform(Rotation.from_matrix(W[:, :3, :3]).mean().as_matrix(), W[:, :3, 3].mean(axis=0))


def fit_board(
    tcp_T_cam: Array, W0: Array, data: CornerData, K: Array, dist: Array,
    loss: str = "soft_l1", f_scale_px: float = 1.0, max_nfev: int = 100,
) -> Array:
    """The ``base_T_board`` that best explains the corners for a fixed ``tcp_T_cam`` (robust)."""
    G_inv = _inv_batch(data.G)

    def fun(p: Array) -> Array:
        return (_project(_camera_points(tcp_T_cam, _perturb(W0, p), G_inv, data), K, dist) - data.img).ravel()

    sol = least_squares(fun, np.zeros(6), loss=loss, f_scale=f_scale_px, x_scale="jac", max_nfev=max_nfev)
    return _perturb(W0, sol.x)


def axxb_residuals(base_T_tcp: ArrayLike, cam_T_board: ArrayLike, tcp_T_cam: ArrayLike) -> tuple[Array, Array]:
    """Per view pair ``i < j``: ``(rotation deg, translation mm)`` of ``inv(A X) X B``."""
    A, B = motion_pairs(base_T_tcp, cam_T_board, "all", max_rotation_deg=180.0)
    if not len(A):
        return np.zeros(0), np.zeros(0)
    X = np.asarray(tcp_T_cam, dtype=np.float64)
    E = _inv_batch(A @ X[None]) @ X[None] @ B
    return np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude()), 1000.0 * np.linalg.norm(E[:, :3, 3], axis=1)


def _rms(x: Array) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else 0.0


def evaluate(tcp_T_cam: Array, base_T_board: Array, data: CornerData, K: Array, dist: Array) -> Residuals:
    """:class:`Residuals` of a solution, with the robot poses as reported."""
    err, depth = reprojection_errors(tcp_T_cam, base_T_board, data, K, dist)
    f = 0.5 * (K[0, 0] + K[1, 1])
    rot, trans = axxb_residuals(data.G, data.C, tcp_T_cam)
    implied = data.G @ tcp_T_cam[None] @ data.C
    board_rot = np.array([math.degrees(rotation_distance(T, base_T_board)) for T in implied])
    board_trans = 1000.0 * np.linalg.norm(implied[:, :3, 3] - base_T_board[:3, 3], axis=1)
    return Residuals(
        reprojection_rms_px=_rms(err), reprojection_median_px=float(np.median(err)),
        reprojection_max_px=float(err.max()), reprojection_rms_mm=_rms(1000.0 * err * np.maximum(depth, 0.0) / f),
        axxb_rotation_rms_deg=_rms(rot), axxb_translation_rms_mm=_rms(trans),
        axxb_rotation_max_deg=float(rot.max()) if len(rot) else 0.0,
        axxb_translation_max_mm=float(trans.max()) if len(trans) else 0.0,
        board_rotation_rms_deg=_rms(board_rot), board_translation_rms_mm=_rms(board_trans),
        n_views=data.n_views, n_corners=len(data.obj),
    )


# ----------------------------------------------------------------------------- joint refinement
@dataclass(frozen=True)
class RefineSettings:
    """Settings of :func:`refine_handeye` (see the module docstring).

    ``f_scale_px``: scale of the robust loss in pixels. ``pixel_sigma_px``: corner noise;
    None = estimated from the per-view PnP residuals (which no robot error can reach).
    ``robot_sigma_mm``/``robot_sigma_deg``: robot pose error per axis (None = exact poses).
    ``intrinsics_std``: 1-sigma of the intrinsics (``fx, fy, cx, cy, k1, ...`` as in
    :attr:`~brave6d.calibration.intrinsics.IntrinsicsResult.std`), taken as independent;
    ``intrinsics_cov``: their full covariance (wins over ``intrinsics_std``); the effect of either is
    added to the uncertainty of ``tcp_T_cam`` (a principal point error of 1 px turns the camera by
    1/f rad). ``refine_intrinsics``: intrinsic parameters solved jointly instead (see the module
    docstring); their effect on the uncertainty then comes from the joint solve.
    ``estimate_robot_sigma``: the robot sigmas are starting values, re-estimated from the
    corrections (see the module docstring); False keeps them fixed.
    """

    loss: str = "soft_l1"
    f_scale_px: float = 1.0
    robot_sigma_mm: float | None = 0.1
    robot_sigma_deg: float | None = 0.01
    pixel_sigma_px: float | None = None
    max_nfev: int = 100
    intrinsics_std: Mapping[str, float] | None = None
    estimate_robot_sigma: bool = True
    intrinsics_cov: IntrinsicsCovariance | None = None
    refine_intrinsics: tuple[str, ...] = ()

    @property
    def models_robot(self) -> bool:
        return bool(self.robot_sigma_mm and self.robot_sigma_deg)


@dataclass(frozen=True)
class Refinement:
    """Output of :func:`refine_handeye`. ``corrections``: (V, 6) estimated TCP pose corrections
    (rotation vector rad, translation m, TCP frame; zeros without the robot model);
    ``fit_errors_px`` (M,) and ``weights`` (M,) per corner, with those corrections applied;
    ``robot_sigma_mm``/``robot_sigma_deg``: the robot error model of the final solve (estimated
    when ``estimate_robot_sigma``; None without the robot model); ``K``, ``dist``: the intrinsics
    of the solution (refined with ``refine_intrinsics``, else as given) and ``intrinsics_std`` the
    1-sigma of the refined ones from the joint solve (None when they were held)."""

    tcp_T_cam: Array
    base_T_board: Array
    corrections: Array
    fit_errors_px: Array
    weights: Array
    pixel_sigma_px: float
    uncertainty: Uncertainty
    nfev: int
    robot_sigma_mm: float | None = None
    robot_sigma_deg: float | None = None
    K: Array | None = None
    dist: Array | None = None
    intrinsics_std: dict[str, float] | None = None


#: Floor of the estimated pixel noise (noise-free synthetic data would otherwise give 0).
MIN_PIXEL_SIGMA_PX = 0.01


def pixel_noise_from_pnp(data: CornerData, K: Array, dist: Array) -> float:
    """Corner noise (px, per coordinate) from the per-view PnP fits: their residual sum of
    squares over ``2M - 6V`` degrees of freedom. Robot pose errors do not enter (each view has
    its own pose), so this separates pixel noise from robot error."""
    P = np.einsum("mab,mb->ma", data.C[data.view_of, :3, :3], data.obj) + data.C[data.view_of, :3, 3]
    r = _project(P, K, dist) - data.img
    dof = max(2 * len(data.obj) - 6 * data.n_views, 1)
    return max(float(np.sqrt(np.sum(r * r) / dof)), MIN_PIXEL_SIGMA_PX)


class _Problem:
    """Whitened residuals of the unknowns ``p = [tcp_T_cam (6), base_T_board (6), intrinsics (I),
    corrections (6 V)]`` (``I`` = number of ``refine_intrinsics``; the first ``12 + I`` are shared).

    Rows: pixel residuals / ``sigma`` (2 per corner), then with the robot model the priors
    ``correction / robot_sigma`` (6 per view). The corrections are TCP-frame poses ``E_v``
    (``base_T_tcp_v @ E_v`` is the true TCP pose). The Jacobian is sparse: a view's pixels
    depend on the shared unknowns and on its own 6 corrections only.
    """

    def __init__(self, X0: Array, W0: Array, data: CornerData, K: Array, dist: Array,
                 settings: RefineSettings, sigma_px: float) -> None:
        self.X0, self.W0, self.data, self.K, self.dist = X0, W0, data, K, dist
        self.sigma = sigma_px
        self.robot = settings.models_robot
        self.V, self.M = data.n_views, len(data.obj)
        self.intrinsics = tuple(settings.refine_intrinsics)
        for name in self.intrinsics:
            if name not in INTRINSIC_NAMES[: 4 + len(dist)]:
                raise ValueError(f"refine_intrinsics: {name!r} is not a parameter of this camera model "
                                 f"({', '.join(INTRINSIC_NAMES[: 4 + len(dist)])})")
        self.ns = 12 + len(self.intrinsics)
        self.theta0 = _intrinsic_values(K, dist, self.intrinsics)
        # Forward-difference steps: 1e-6 of a focal length in px, 1e-6 for distortion coefficients.
        self.theta_step = np.array([1e-6 * max(abs(float(K[0, 0])), 1.0) if n in ("fx", "fy", "cx", "cy") else 1e-6
                                    for n in self.intrinsics])
        self.n = self.ns + (6 * self.V if self.robot else 0)
        self.m = 2 * self.M + (6 * self.V if self.robot else 0)
        self.G_inv = _inv_batch(data.G)
        self.row_view = np.repeat(data.view_of, 2)
        if self.robot:
            assert settings.robot_sigma_deg is not None and settings.robot_sigma_mm is not None
            self.prior_scale = np.tile(np.r_[[1.0 / math.radians(settings.robot_sigma_deg)] * 3,
                                             [1.0 / (settings.robot_sigma_mm * 1e-3)] * 3], self.V)

    def unpack(self, p: Array) -> tuple[Array, Array, Array]:
        D = p[self.ns:].reshape(self.V, 6) if self.robot else np.zeros((self.V, 6))
        return _perturb(self.X0, p[:6]), _perturb(self.W0, p[6:12]), D

    def camera(self, p: Array) -> tuple[Array, Array]:
        """``(K, dist)`` at ``p`` (the given ones unless intrinsics are refined)."""
        if not self.intrinsics:
            return self.K, self.dist
        return _with_intrinsics(self.K, self.dist, self.intrinsics, self.theta0 + p[12:self.ns])

    def pixel_residuals(self, p: Array) -> Array:
        X, W, D = self.unpack(p)
        K, dist = self.camera(p)
        G_inv = _inv_batch(_corrections(D)) @ self.G_inv if self.robot else self.G_inv
        return (_project(_camera_points(X, W, G_inv, self.data), K, dist) - self.data.img).ravel()

    def residuals(self, p: Array) -> Array:
        r = self.pixel_residuals(p) / self.sigma
        return np.concatenate([r, p[self.ns:] * self.prior_scale]) if self.robot else r

    def jacobian(self, p: Array) -> sparse.csr_matrix:
        """Forward differences, 12 + I + 6 evaluations (views do not interact)."""
        r0 = self.pixel_residuals(p) / self.sigma
        px_rows = np.arange(2 * self.M)
        rows, cols, vals = [], [], []
        for k in range(self.ns):
            step = _FD_STEP if k < 12 else float(self.theta_step[k - 12])
            q = p.copy()
            q[k] += step
            rows.append(px_rows)
            cols.append(np.full(2 * self.M, k))
            vals.append((self.pixel_residuals(q) / self.sigma - r0) / step)
        if self.robot:
            for k in range(6):
                q = p.copy()
                q[self.ns + k::6] += _FD_STEP
                rows.append(px_rows)
                cols.append(self.ns + 6 * self.row_view + k)
                vals.append((self.pixel_residuals(q) / self.sigma - r0) / _FD_STEP)
            rows.append(2 * self.M + np.arange(6 * self.V))
            cols.append(self.ns + np.arange(6 * self.V))
            vals.append(self.prior_scale)
        return sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(self.m, self.n)
        )

    def residuals_with(self, p: Array, K: Array, dist: Array) -> Array:
        """:meth:`residuals` with other intrinsics (for their sensitivity)."""
        saved = self.K, self.dist
        self.K, self.dist = K, dist
        try:
            return self.residuals(p)
        finally:
            self.K, self.dist = saved

    def cluster_of_rows(self) -> NDArray[np.int64]:
        """The view each residual row belongs to."""
        return np.concatenate([self.row_view, np.repeat(np.arange(self.V), 6)]) if self.robot else self.row_view


def _schur_complement(H: Array, ns: int, problem: _Problem) -> tuple[Array, Array | None, Array | None]:
    """``(S, BD, D^-1)`` of a normal matrix ``H`` whose first ``ns`` unknowns are shared: the Schur
    complement ``S`` for them, eliminating the per-view corrections (block-diagonal ``D``, 6 x 6 per
    view) exactly, with ``BD = B D^-1`` per view ((V, ns, 6); None without the robot model)."""
    A = H[:ns, :ns]
    if not problem.robot:
        return A, None, None
    V = problem.V
    idx = ns + np.arange(6 * V).reshape(V, 6)
    D_inv = np.linalg.inv(H[idx[:, :, None], idx[:, None, :]])  # (V, 6, 6)
    B = H[:ns, ns:].reshape(ns, V, 6).transpose(1, 0, 2)  # (V, ns, 6)
    BD = np.einsum("vij,vjk->vik", B, D_inv)
    return A - np.einsum("vik,vlk->il", BD, B), BD, D_inv


def _schur(J: sparse.csr_matrix, w: Array, problem: _Problem) -> tuple[Array, Array | None, Array | None]:
    """``(S^-1, BD, D^-1)`` of ``H = J^T W J`` for the shared unknowns (:func:`_schur_complement`);
    raises when ``(tcp_T_cam, base_T_board)`` is undetermined, or the refined intrinsics with them."""
    H = (J.T @ sparse.diags(w) @ J).toarray()
    S, BD, D_inv = _schur_complement(H, problem.ns, problem)
    # Judge the rank of the hand-eye unknowns in (deg, mm) units: rad and m differ by 1e3 in size.
    scale = np.tile(np.r_[[math.radians(1.0)] * 3, [1e-3] * 3], 2)
    _check_rank(S[:12, :12] * np.outer(scale, scale), "tcp_T_cam and the board pose together (rotations about a "
                                                      "single axis?); add poses rotated about different axes")
    if not problem.intrinsics:
        return np.linalg.inv(S * np.outer(scale, scale)) * np.outer(scale, scale), BD, D_inv
    # With intrinsics (px and unitless distortion, strongly correlated): judge and invert the
    # correlation matrix, which no choice of units changes.
    d = 1.0 / np.sqrt(np.maximum(np.diag(S), 1e-300))
    Sn = S * np.outer(d, d)
    _check_rank(Sn, "the intrinsics refined with the hand-eye transform; hold them fixed")
    return np.linalg.inv(Sn) * np.outer(d, d), BD, D_inv


def _check_rank(S: Array, what: str) -> None:
    ev = np.linalg.eigvalsh(0.5 * (S + S.T))
    if not np.all(np.isfinite(ev)) or ev[0] <= 1e-10 * max(ev[-1], 1e-300):
        raise DegenerateGeometryError(f"hand-eye refinement is rank deficient: the views do not determine {what}")


def _inverse_rows(J: sparse.csr_matrix, w: Array, problem: _Problem) -> tuple[Array, Array]:
    """``(S^-1, R)``: the inverse of the Schur complement (:func:`_schur`) and the first ``ns`` rows
    ``R`` of ``H^-1``."""
    S_inv, BD, _ = _schur(J, w, problem)
    if BD is None:
        return S_inv, S_inv
    R = np.concatenate([S_inv, -np.einsum("ij,vjk->ivk", S_inv, BD).reshape(problem.ns, -1)], axis=1)
    return S_inv, R


def _robot_variance_factors(problem: _Problem, p: Array, s: RefineSettings) -> tuple[float, float]:
    """Robust variance factors ``(rotation, translation)`` of the robot pose priors at ``p``: how
    much larger (> 1) or smaller the robot's real noise variance is than the one modelled.

    Per view and group (3 rotation or 3 translation priors): squared whitened correction over
    its redundancy ``1 - h`` (``h`` the hat-matrix diagonal, ``w s^2 (H^-1)_kk`` for a prior row
    ``s x_k``), then the median over views divided by the median of chi-square(3) / 3.
    """
    J = problem.jacobian(p)
    r = problem.residuals(p)
    w = loss_weights(r, s.loss, s.f_scale_px / problem.sigma)
    S_inv, BD, D_inv = _schur(J, w, problem)
    assert BD is not None and D_inv is not None
    h_inv = np.einsum("vkk->vk", D_inv) + np.einsum("vik,il,vlk->vk", BD, S_inv, BD)  # diag of H^-1, corrections
    V = problem.V
    scale2 = problem.prior_scale.reshape(V, 6) ** 2
    prior_w = w[2 * problem.M:].reshape(V, 6)
    redundancy = np.clip(1.0 - prior_w * scale2 * h_inv, 1e-3, 1.0)
    r2 = r[2 * problem.M:].reshape(V, 6) ** 2
    factors = []
    for group in (slice(0, 3), slice(3, 6)):
        ratio = r2[:, group].sum(axis=1) / redundancy[:, group].sum(axis=1)
        factors.append(float(np.median(ratio)) / _CHI2_3_MEDIAN)
    return factors[0], factors[1]


def _rescaled_robot_sigmas(s: RefineSettings, factors: tuple[float, float], configured: RefineSettings
                           ) -> RefineSettings:
    """``s`` with its robot sigmas multiplied by ``sqrt(factors)``, kept within ``_NOISE_RANGE``
    of the configured ones."""
    assert s.robot_sigma_deg and s.robot_sigma_mm and configured.robot_sigma_deg and configured.robot_sigma_mm

    def rescale(sigma: float, factor: float, start: float) -> float:
        return float(np.clip(sigma * math.sqrt(max(factor, 0.0)), start / _NOISE_RANGE, start * _NOISE_RANGE))

    return replace(s, robot_sigma_deg=rescale(s.robot_sigma_deg, factors[0], configured.robot_sigma_deg),
                   robot_sigma_mm=rescale(s.robot_sigma_mm, factors[1], configured.robot_sigma_mm))




def _intrinsic_values(K: Array, dist: Array, names: Sequence[str]) -> Array:
    """The values of the named intrinsic parameters (:data:`INTRINSIC_NAMES`)."""
    flat = np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist]
    return np.array([flat[INTRINSIC_NAMES.index(n)] for n in names], dtype=np.float64)


def _with_intrinsics(K: Array, dist: Array, names: Sequence[str], values: Array) -> tuple[Array, Array]:
    """``(K, dist)`` with the named parameters set to ``values``."""
    K2, d2 = K.copy(), dist.copy()
    for name, v in zip(names, values, strict=True):
        i = INTRINSIC_NAMES.index(name)
        if i < 4:
            K2[((0, 0), (1, 1), (0, 2), (1, 2))[i]] = v
        else:
            d2[i - 4] = v
    return K2, d2


def _propagated_intrinsics(problem: _Problem, s: RefineSettings) -> IntrinsicsCovariance | None:
    """The intrinsics' covariance to propagate: the full one, else the 1-sigmas as independent,
    restricted to parameters of this camera model."""
    cov = s.intrinsics_cov if s.intrinsics_cov is not None else (
        IntrinsicsCovariance.from_std(dict(s.intrinsics_std)) if s.intrinsics_std else None)
    if cov is None:
        return None
    keep = [i for i, n in enumerate(cov.names) if INTRINSIC_NAMES.index(n) < 4 + len(problem.dist)]
    if not keep:
        return None
    return IntrinsicsCovariance(tuple(cov.names[i] for i in keep), cov.matrix[np.ix_(keep, keep)])


def _intrinsics_covariance(problem: _Problem, p: Array, J: sparse.csr_matrix, w: Array, R6: Array,
                           cov: IntrinsicsCovariance) -> Array:
    """6x6 covariance of ``tcp_T_cam`` caused by the intrinsics' own uncertainty ``cov`` (held
    intrinsics), by first-order propagation ``dp/dtheta = -H^-1 J^T W J_theta``."""
    theta = _intrinsic_values(problem.K, problem.dist, cov.names)
    cols = []
    for k, name in enumerate(cov.names):
        step = 1e-3 if INTRINSIC_NAMES.index(name) < 4 else 1e-6
        out = []
        for sign in (1.0, -1.0):
            shifted = theta.copy()
            shifted[k] += sign * step
            out.append(problem.residuals_with(p, *_with_intrinsics(problem.K, problem.dist, cov.names, shifted)))
        cols.append((out[0] - out[1]) / (2.0 * step))
    J_theta = np.stack(cols, axis=1)
    dp = -R6 @ (J.T @ (w[:, None] * J_theta))
    return dp @ cov.matrix @ dp.T


def _held_rows(J: sparse.csr_matrix, w: Array, problem: _Problem) -> tuple[Array, Array, sparse.csr_matrix]:
    """``(S^-1, R, J)`` of the problem with the refined intrinsics held at ``p``: their columns
    dropped, the first 12 rows ``R`` of that problem's ``H^-1``."""
    keep = np.r_[np.arange(12), np.arange(problem.ns, problem.n)]
    J_held = J[:, keep].tocsr()
    H = (J_held.T @ sparse.diags(w) @ J_held).toarray()
    S, BD, _ = _schur_complement(H, 12, problem)
    S_inv = np.linalg.inv(S)
    R = S_inv if BD is None else np.concatenate([S_inv, -np.einsum("ij,vjk->ivk", S_inv, BD).reshape(12, -1)], axis=1)
    return S_inv, R, J_held


def _uncertainty(problem: _Problem, p: Array, s: RefineSettings) -> tuple[Uncertainty, Array, dict[str, float] | None]:
    """Uncertainty of ``tcp_T_cam`` at ``p``, the mean robust weight of each corner and, with
    refined intrinsics, their 1-sigma from the joint solve."""
    J = problem.jacobian(p)
    r = problem.residuals(p)
    w = loss_weights(r, s.loss, s.f_scale_px / problem.sigma)
    S_inv, R = _inverse_rows(J, w, problem)
    s2 = float(np.sum(w * r * r)) / max(len(r) - problem.n, 1)
    intrinsics_std = None
    if problem.intrinsics:  # model and sandwich with the intrinsics held; their share from the joint solve
        S_inv_held, R_held, J_held = _held_rows(J, w, problem)
        cov_joint = s2 * S_inv[:6, :6]
        cov_model = s2 * S_inv_held[:6, :6]
        cov_intr = cov_joint - cov_model
        R6, J_sandwich = R_held[:6], J_held
        var = np.maximum(s2 * np.diag(S_inv)[12:problem.ns], 0.0)
        intrinsics_std = {n: float(np.sqrt(v)) for n, v in zip(problem.intrinsics, var, strict=True)}
    else:
        R6, J_sandwich = R[:6], J
        cov_model = s2 * S_inv[:6, :6]
        held = _propagated_intrinsics(problem, s)
        cov_intr = _intrinsics_covariance(problem, p, J, w, R6, held) if held is not None else None
    # Sandwich clustered by view: sum over views of (R g_v)(R g_v)^T, g_v = J_v^T W_v r_v.
    cluster = problem.cluster_of_rows()
    indicator = sparse.csr_matrix((np.ones(len(r)), (cluster, np.arange(len(r)))), shape=(problem.V, len(r)))
    G = (indicator @ J_sandwich.multiply((w * r)[:, None]).tocsr()).toarray()  # (V, n)
    RG = R6 @ G.T
    cov_cluster = RG @ RG.T * (problem.V / max(problem.V - 1, 1))
    unc = Uncertainty.from_covariances(cov_model, cov_cluster, cov_intr)
    return unc, w[: 2 * problem.M].reshape(-1, 2).mean(axis=1), intrinsics_std


def _solve(problem: _Problem, p0: Array, s: RefineSettings) -> tuple[Array, int]:
    """``least_squares`` from ``p0``: ``(solution, function evaluations)``."""
    f_scale = s.f_scale_px / problem.sigma
    if problem.n <= _DENSE_MAX_UNKNOWNS:  # exact trust-region steps: converges in few iterations
        def jac(q: Array) -> Array:
            return problem.jacobian(q).toarray()

        sol = least_squares(problem.residuals, p0, jac=jac, loss=s.loss, f_scale=f_scale, x_scale="jac",
                            max_nfev=s.max_nfev, method="trf", tr_solver="exact")
    else:  # many views: sparse steps (LSMR)
        sol = least_squares(problem.residuals, p0, jac=problem.jacobian, loss=s.loss, f_scale=f_scale, x_scale="jac",
                            max_nfev=s.max_nfev, method="trf", tr_solver="lsmr")
    return sol.x, int(sol.nfev)


def _settle_robot_noise(problem: _Problem, p: Array, configured: RefineSettings
                        ) -> tuple[_Problem, Array, RefineSettings, int]:
    """Re-estimate the robot sigmas from the corrections of the solution ``p`` and solve again
    (warm start: the unknowns keep their meaning) until they change by less than 10%:
    ``(problem, solution, settings with the final sigmas, extra function evaluations)``."""
    current, nfev = configured, 0
    for _ in range(_NOISE_ITERATIONS - 1):
        nxt = _rescaled_robot_sigmas(current, _robot_variance_factors(problem, p, current), configured)
        assert nxt.robot_sigma_mm and nxt.robot_sigma_deg and current.robot_sigma_mm and current.robot_sigma_deg
        change = max(nxt.robot_sigma_mm / current.robot_sigma_mm, current.robot_sigma_mm / nxt.robot_sigma_mm,
                     nxt.robot_sigma_deg / current.robot_sigma_deg, current.robot_sigma_deg / nxt.robot_sigma_deg)
        if change < _NOISE_TOLERANCE:
            break
        current = nxt
        problem = _Problem(problem.X0, problem.W0, problem.data, problem.K, problem.dist, current, problem.sigma)
        p, more = _solve(problem, p, current)
        nfev += more
    return problem, p, current, nfev


def refine_handeye(
    tcp_T_cam0: Array, base_T_board0: Array, data: CornerData, K: Array, dist: Array,
    settings: RefineSettings | None = None,
) -> Refinement:
    """Joint robust refinement of ``tcp_T_cam`` and ``base_T_board`` (see the module docstring),
    with the robot sigmas re-estimated from the corrections when ``settings.estimate_robot_sigma``.

    Raises :class:`DegenerateGeometryError` when the problem is rank deficient at the solution.
    """
    s = settings or RefineSettings()
    loss_weights(np.zeros(1), s.loss, 1.0)  # validates the loss name
    sigma = max(float(s.pixel_sigma_px), MIN_PIXEL_SIGMA_PX) if s.pixel_sigma_px else pixel_noise_from_pnp(data, K, dist)
    problem = _Problem(tcp_T_cam0, base_T_board0, data, K, dist, s, sigma)
    p, nfev = _solve(problem, np.zeros(problem.n), s)
    if problem.robot and s.estimate_robot_sigma:
        problem, p, s, more = _settle_robot_noise(problem, p, s)
        nfev += more
    X, W, D = problem.unpack(p)
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(W))):
        raise DegenerateGeometryError("hand-eye refinement diverged (non-finite result)")
    K_fit, dist_fit = problem.camera(p)
    if not (np.all(np.isfinite(K_fit)) and np.all(np.isfinite(dist_fit))):
        raise DegenerateGeometryError("hand-eye refinement diverged (non-finite intrinsics)")
    unc, weights, intrinsics_std = _uncertainty(problem, p, s)
    fit = problem.pixel_residuals(p).reshape(-1, 2)
    return Refinement(
        tcp_T_cam=X, base_T_board=W, corrections=D, fit_errors_px=np.linalg.norm(fit, axis=1), weights=weights,
        pixel_sigma_px=sigma, uncertainty=unc, nfev=nfev,
        robot_sigma_mm=s.robot_sigma_mm if problem.robot else None,
        robot_sigma_deg=s.robot_sigma_deg if problem.robot else None,
        K=K_fit, dist=dist_fit, intrinsics_std=intrinsics_std,
    )


def solution_uncertainty(
    tcp_T_cam: Array, base_T_board: Array, data: CornerData, K: Array, dist: Array,
    settings: RefineSettings | None = None,
) -> tuple[Uncertainty, Array]:
    """Uncertainty of a given solution (no refinement) and the mean robust weight of each corner;
    used to rate a closed-form answer returned without refinement."""
    s = settings or RefineSettings()
    sigma = max(float(s.pixel_sigma_px), MIN_PIXEL_SIGMA_PX) if s.pixel_sigma_px else pixel_noise_from_pnp(data, K, dist)
    problem = _Problem(tcp_T_cam, base_T_board, data, K, dist, replace(s, refine_intrinsics=()), sigma)
    unc, weights, _ = _uncertainty(problem, np.zeros(problem.n), s)
    return unc, weights

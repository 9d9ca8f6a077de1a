"""Closed-form eye-in-hand solvers for ``A X = X B`` (X = ``tcp_T_cam``), in NumPy.

Inputs are the robot poses ``base_T_tcp`` and the board poses ``cam_T_board`` (solvePnP) of
the same views, the convention of ``cv2.calibrateHandEye`` (gripper2base, target2cam ->
cam2gripper). For views ``i, j``: ``A = inv(base_T_tcp_j) base_T_tcp_i`` (TCP motion),
``B = cam_T_board_j inv(cam_T_board_i)`` (camera motion); the board is fixed in the base frame,
so ``A X = X B``. Like OpenCV 4.x, the default uses all pairs ``i < j`` (``pairs="consecutive"``
uses only neighbouring views, e.g. for very long sequences).

* ``tsai``: Tsai & Lenz (1989): rotation from the Gibbs-vector form of ``R_A R_X = R_X R_B``
  (linear least squares), then translation by least squares. The Gibbs vector is singular
  when ``R_X`` turns 180 deg (a camera mounted "upside down" on the flange), so the rotation
  is also solved in camera frames turned by 180 deg about x, y, z (an exact change of
  variables; in one of the four frames ``R_X`` is within 120 deg of identity). The plain
  frame's answer is kept when it is within 120 deg and fits as well as the best; otherwise
  the best-fitting well-conditioned one (smallest ``|R_A R_X - R_X R_B|``).
* ``park``: Park & Martin (1994): the log-map axes satisfy ``alpha = R_X beta``; ``R_X`` is
  their orthogonal Procrustes fit (SVD), translation by least squares.
* ``daniilidis``: Daniilidis (1999): rotation and translation together from the null space of
  the stacked dual-quaternion equations ``a x = x b``.

Motion pairs rotating by more than ``max_rotation_deg`` (default 170) are left out: near 180
deg the quaternion sign of a motion is ambiguous under noise.

Degenerate inputs are refused before any solver runs: :func:`handeye_motions` (used by
:func:`solve_closed_form` and :func:`~brave6d.calibration.handeye.calibrate_handeye`) runs
:func:`~brave6d.calibration.conditioning.check_handeye_conditioning` on the poses, which raises
:class:`DegenerateGeometryError` naming the cause (too few or duplicated poses, pure
translations, small rotation span, a single rotation axis, robot and camera motions that
disagree) or :class:`NonRigidTransformError` naming the view (NaN/inf, scaled matrices). The
per-method solvers (``solve_tsai`` ...) take motions and assume they passed that check.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.transforms import invert, make_transform
from brave6d.calibration.conditioning import ConditioningReport, ConditioningThresholds, check_handeye_conditioning

__all__ = [
    "CLOSED_FORM_METHODS",
    "handeye_motions",
    "motion_pairs",
    "solve_closed_form",
    "solve_daniilidis",
    "solve_park",
    "solve_translation",
    "solve_tsai",
]

PairMode = Literal["all", "consecutive"]
Array = NDArray[np.float64]


def _skew(v: Array) -> Array:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [np.stack([z, -v[..., 2], v[..., 1]], -1), np.stack([v[..., 2], z, -v[..., 0]], -1),
         np.stack([-v[..., 1], v[..., 0], z], -1)], -2,
    )


def motion_pairs(
    base_T_tcp: Sequence[ArrayLike],
    cam_T_board: Sequence[ArrayLike],
    pairs: PairMode = "all",
    max_rotation_deg: float = 170.0,
) -> tuple[Array, Array]:
    """Stacked motions ``(A, B)``, each (P, 4, 4), for ``A X = X B`` (see the module docstring)."""
    G = np.asarray(base_T_tcp, dtype=np.float64).reshape(-1, 4, 4)
    C = np.asarray(cam_T_board, dtype=np.float64).reshape(-1, 4, 4)
    if len(G) != len(C):
        raise DegenerateGeometryError(f"{len(G)} robot poses but {len(C)} board poses")
    if pairs == "all":
        i, j = np.triu_indices(len(G), k=1)
    elif pairs == "consecutive":
        i, j = np.arange(len(G) - 1), np.arange(1, len(G))
    else:
        raise ValueError(f"pairs must be 'all' or 'consecutive', got {pairs!r}")
    G_inv = np.stack([invert(g) for g in G])
    C_inv = np.stack([invert(c) for c in C])
    A = G_inv[j] @ G[i]
    B = C[j] @ C_inv[i]
    angle = np.degrees(Rotation.from_matrix(A[:, :3, :3]).magnitude()) if len(A) else np.zeros(0)
    keep = angle <= max_rotation_deg
    return A[keep], B[keep]


def handeye_motions(
    base_T_tcp: Sequence[ArrayLike],
    cam_T_board: Sequence[ArrayLike],
    pairs: PairMode = "all",
    thresholds: ConditioningThresholds | None = None,
    names: Sequence[str] | None = None,
    setup: str = "eye-in-hand",
) -> tuple[Array, Array, ConditioningReport]:
    """``(A, B, report)``: the motions of :func:`motion_pairs` for poses that pass
    :func:`~brave6d.calibration.conditioning.check_handeye_conditioning`, which raises naming the cause
    otherwise. The one gate between poses and every closed-form solver."""
    report = check_handeye_conditioning(base_T_tcp, cam_T_board, thresholds, names, setup)
    A, B = motion_pairs(base_T_tcp, cam_T_board, pairs)
    return A, B, report


def _check_count(A: Array, name: str) -> None:
    if len(A) < 2:
        raise DegenerateGeometryError(f"{name}: {len(A)} motion(s); at least 2 with non-parallel axes are needed")


def solve_translation(A: Array, B: Array, R_X: Array) -> Array:
    """Least-squares ``t_X`` from ``(R_A - I) t_X = R_X t_B - t_A`` over all motions."""
    M = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (np.einsum("ab,pb->pa", R_X, B[:, :3, 3]) - A[:, :3, 3]).reshape(-1)
    sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    return sol


def _tsai_rotation(A: Array, B: Array) -> Array:
    # Modified Rodrigues vectors P = 2 sin(theta/2) k; Cayley: P_A - P_B = g x (P_A + P_B),
    # i.e. skew(P_A + P_B) g = P_B - P_A with g the Gibbs vector tan(theta_X / 2) k_X.
    ra = Rotation.from_matrix(A[:, :3, :3]).as_rotvec()
    rb = Rotation.from_matrix(B[:, :3, :3]).as_rotvec()

    def modified(r: Array) -> Array:
        th = np.linalg.norm(r, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(th > 1e-12, 2.0 * np.sin(th / 2.0) / np.maximum(th, 1e-300), 1.0)
        return r * scale

    pa, pb = modified(ra), modified(rb)
    M = _skew(pa + pb).reshape(-1, 3)
    g, *_ = np.linalg.lstsq(M, (pb - pa).reshape(-1), rcond=None)
    norm = float(np.linalg.norm(g))
    if norm < 1e-15:
        return np.eye(3)
    return Rotation.from_rotvec(2.0 * np.arctan(norm) * g / norm).as_matrix()


_KLEIN = [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]


def _rotation_residual(A: Array, B: Array, R_X: Array) -> float:
    return float(np.sum((A[:, :3, :3] @ R_X - R_X @ B[:, :3, :3]) ** 2))


def solve_tsai(A: Array, B: Array) -> Array:
    """Tsai-Lenz: ``tcp_T_cam`` from stacked motions (see the module docstring)."""
    _check_count(A, "Tsai-Lenz")
    candidates = []  # (residual, angle of X' in deg, R_X) per camera frame
    for C in _KLEIN:
        # X' = X C^T solves A X' = X' B' with B' = C B C^T; one of the four is within 120 deg of I.
        B_rot = B.copy()
        B_rot[:, :3, :3] = C @ B[:, :3, :3] @ C.T
        R_prime = _tsai_rotation(A, B_rot)
        R_X = R_prime @ C
        candidates.append((_rotation_residual(A, B, R_X), float(np.degrees(Rotation.from_matrix(R_prime).magnitude())), R_X))
    best = min(c[0] for c in candidates)
    # The plain frame (as in the paper and OpenCV) unless its Gibbs vector is near its singularity.
    plain = candidates[0]
    if plain[1] <= 120.0 and plain[0] <= 1.5 * best + 1e-15:
        R_X = plain[2]
    else:
        usable = [c for c in candidates if c[1] <= 120.0] or candidates
        R_X = min(usable, key=lambda c: c[0])[2]
    return make_transform(R_X, solve_translation(A, B, R_X))


def solve_park(A: Array, B: Array) -> Array:
    """Park-Martin: ``tcp_T_cam`` from stacked motions (see the module docstring)."""
    _check_count(A, "Park-Martin")
    alpha = Rotation.from_matrix(A[:, :3, :3]).as_rotvec()
    beta = Rotation.from_matrix(B[:, :3, :3]).as_rotvec()
    H = beta.T @ alpha  # sum beta alpha^T; R_X maximises tr(R_X H)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R_X = Vt.T @ D @ U.T
    return make_transform(R_X, solve_translation(A, B, R_X))


def _qmul(p: Array, q: Array) -> Array:
    """Hamilton product of (..., 4) quaternions in (w, x, y, z) order."""
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - np.sum(pv * qv, axis=-1, keepdims=True)
    v = pw * qv + qw * pv + np.cross(pv, qv)
    return np.concatenate([w, v], axis=-1)


def _dual_quaternions(T: Array) -> tuple[Array, Array]:
    """(real, dual) parts (P, 4) in (w, x, y, z) order with w >= 0; dual = 0.5 (0, t) real."""
    real = Rotation.from_matrix(T[:, :3, :3]).as_quat(canonical=True)[:, [3, 0, 1, 2]]
    t = np.concatenate([np.zeros((len(T), 1)), T[:, :3, 3]], axis=1)
    return real, 0.5 * _qmul(t, real)


def solve_daniilidis(A: Array, B: Array) -> Array:
    """Daniilidis dual-quaternion solver: ``tcp_T_cam`` from stacked motions."""
    _check_count(A, "Daniilidis")
    qa, qa_d = _dual_quaternions(A)
    qb, qb_d = _dual_quaternions(B)
    a, ad, b, bd = qa[:, 1:], qa_d[:, 1:], qb[:, 1:], qb_d[:, 1:]
    P = len(A)
    S = np.zeros((P, 6, 8))
    S[:, :3, 0] = a - b
    S[:, :3, 1:4] = _skew(a + b)
    S[:, 3:, 0] = ad - bd
    S[:, 3:, 1:4] = _skew(ad + bd)
    S[:, 3:, 4] = a - b
    S[:, 3:, 5:8] = _skew(a + b)
    _, _, Vt = np.linalg.svd(S.reshape(-1, 8), full_matrices=False)
    v1, v2 = Vt[-2], Vt[-1]
    u1, w1, u2, w2 = v1[:4], v1[4:], v2[:4], v2[4:]
    # x = l1 v1 + l2 v2 with |real(x)| = 1 and real(x) . dual(x) = 0 (a quadratic form in l).
    Q = np.array([[u1 @ w1, 0.5 * (u1 @ w2 + u2 @ w1)], [0.5 * (u1 @ w2 + u2 @ w1), u2 @ w2]])
    N = np.array([[u1 @ u1, u1 @ u2], [u1 @ u2, u2 @ u2]])
    ev, evec = np.linalg.eigh(Q)
    if ev[0] < 0.0 < ev[1]:
        candidates = [
            np.sqrt(ev[1]) * evec[:, 0] + s * np.sqrt(-ev[0]) * evec[:, 1] for s in (1.0, -1.0)
        ]
    else:  # noise made the form definite: take its most nearly null direction
        candidates = [evec[:, int(np.argmin(np.abs(ev)))]]
    lam = max(candidates, key=lambda c: float(c @ N @ c) / max(float(c @ c), 1e-300))
    x = lam[0] * v1 + lam[1] * v2
    real, dual = x[:4], x[4:]
    norm = float(np.linalg.norm(real))
    if not np.isfinite(norm) or norm < 1e-12:
        raise DegenerateGeometryError("Daniilidis: the dual-quaternion system has no usable solution")
    real, dual = real / norm, dual / norm
    dual = dual - (real @ dual) * real
    R_X = Rotation.from_quat(real[[1, 2, 3, 0]]).as_matrix()
    conj = real * np.array([1.0, -1.0, -1.0, -1.0])
    t_X = 2.0 * _qmul(dual, conj)[1:]
    return make_transform(R_X, t_X)


CLOSED_FORM_METHODS: dict[str, Callable[[Array, Array], Array]] = {
    "tsai": solve_tsai,
    "park": solve_park,
    "daniilidis": solve_daniilidis,
}


def solve_closed_form(
    base_T_tcp: Sequence[ArrayLike],
    cam_T_board: Sequence[ArrayLike],
    method: str = "park",
    pairs: PairMode = "all",
    thresholds: ConditioningThresholds | None = None,
) -> Array:
    """``tcp_T_cam`` by one closed-form method (``"tsai"``, ``"park"`` or ``"daniilidis"``).

    Raises :class:`DegenerateGeometryError` naming the cause when the poses cannot determine
    ``tcp_T_cam`` (the checks of :func:`~brave6d.calibration.conditioning.check_handeye_conditioning`
    with ``thresholds``, the same as :func:`~brave6d.calibration.handeye.calibrate_handeye`), and
    :class:`NonRigidTransformError` naming the view for a NaN or non-rigid pose.
    """
    if method not in CLOSED_FORM_METHODS:
        raise ValueError(f"unknown hand-eye method {method!r}; choose from {sorted(CLOSED_FORM_METHODS)}")
    A, B, _ = handeye_motions(base_T_tcp, cam_T_board, pairs, thresholds)
    X = CLOSED_FORM_METHODS[method](A, B)
    if not np.all(np.isfinite(X)):
        raise DegenerateGeometryError(f"{method}: the closed-form solution is not finite (degenerate motions)")
    return X

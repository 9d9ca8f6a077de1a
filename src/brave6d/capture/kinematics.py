"""UR3e/UR5e/UR10e/UR16e kinematics: forward kinematics from the official DH parameters and the
analytic (closed-form) inverse kinematics with all up-to-8 solutions.

Conventions: standard DH, ``T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` with
``alpha = [pi/2, 0, 0, pi/2, -pi/2, 0]``; ``fk`` gives ``base_T_tcp = base_T_flange @ flange_T_tcp``
(the TCP is the flange unless a tool offset is given). Radians, metres, 4x4 float64.

The inverse kinematics follows the classic decomposition (Hawkins' derivation, re-derived here):
q1 from the wrist-centre position (two shoulder branches), q5/q6 and q2+q3+q4 from the
orientation seen in frame 1 (``R_16 = Rz(q234) Ry(-q5) Rz(q6)``, two wrist branches), then a
planar two-link problem for q2/q3 (two elbow branches). Each branch is labelled by
``(shoulder, elbow, wrist)`` signs so that a planner can keep one arm configuration (no flips).
Arguments of asin/acos are clamped only within ``clamp_tol``; beyond it the pose is unreachable
and the result says why. At the wrist singularity (sin q5 ~ 0) only q2+q3+q4 +- q6 is determined:
q6 is taken from ``q_near`` (or 0) unless that leaves the wrist centre out of the elbow's reach,
in which case the closest feasible split is used, so the answer is finite and deterministic.
Every solution is checked by forward kinematics; one that misses the pose by 1e-12 to 1e-5
(ill-conditioned near singularities) is polished by a few Gauss-Newton steps on the geometric
Jacobian, and kept only if it then reproduces the pose within ``verify_tol``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scipy.spatial.transform import Rotation

from brave6d.core.transforms import check_rigid, invert

TWO_PI = 2.0 * math.pi
ALPHA = (math.pi / 2.0, 0.0, 0.0, math.pi / 2.0, -math.pi / 2.0, 0.0)


@dataclass(frozen=True)
class DHParams:
    """The non-zero DH lengths of a UR e-series arm (metres; a2, a3 are negative by UR's convention)."""

    d1: float
    a2: float
    a3: float
    d4: float
    d5: float
    d6: float

    @property
    def a(self) -> tuple[float, ...]:
        return (0.0, self.a2, self.a3, 0.0, 0.0, 0.0)

    @property
    def d(self) -> tuple[float, ...]:
        return (self.d1, 0.0, 0.0, self.d4, self.d5, self.d6)

    @property
    def reach(self) -> float:
        """Upper bound of the distance from the shoulder to the flange (m)."""
        return abs(self.a2) + abs(self.a3) + math.hypot(self.d4, self.d5) + self.d6


#: Official UR DH parameters (Universal Robots' published tables).
UR_DH: dict[str, DHParams] = {
    "ur3e": DHParams(0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
    "ur5e": DHParams(0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    "ur10e": DHParams(0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
    "ur16e": DHParams(0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
}

#: Default joint limits of every UR e-series joint: +-2 pi (rows: joints, columns: lo, hi).
DEFAULT_JOINT_LIMITS: NDArray[np.float64] = np.tile(np.array([-TWO_PI, TWO_PI]), (6, 1))


# ----------------------------------------------------------------------------- joint-space helpers
def wrap_to_pi(angles: ArrayLike) -> NDArray[np.float64]:
    """Angles mapped into (-pi, pi]."""
    a = np.asarray(angles, dtype=np.float64)
    w = np.mod(a + math.pi, TWO_PI) - math.pi
    return np.where(w <= -math.pi, w + TWO_PI, w)


def joint_distance(
    q_a: ArrayLike, q_b: ArrayLike, weights: ArrayLike | None = None, wrapped: bool = False
) -> float:
    """Weighted Euclidean distance between two joint vectors (radians; no Jacobian needed).

    With ``wrapped`` each difference is taken modulo 2 pi (shortest way round), which is the
    distance between the closest representatives rather than between the given numbers.
    """
    diff = np.asarray(q_a, dtype=np.float64) - np.asarray(q_b, dtype=np.float64)
    if wrapped:
        diff = wrap_to_pi(diff)
    if weights is not None:
        diff = diff * np.asarray(weights, dtype=np.float64)
    return float(np.linalg.norm(diff))


def max_joint_step(q_a: ArrayLike, q_b: ArrayLike) -> float:
    """Largest absolute per-joint difference (radians): what the slowest joint must travel."""
    return float(np.max(np.abs(np.asarray(q_a, dtype=np.float64) - np.asarray(q_b, dtype=np.float64))))


def nearest_representative(
    q: ArrayLike, q_near: ArrayLike | None, limits: ArrayLike = DEFAULT_JOINT_LIMITS
) -> NDArray[np.float64] | None:
    """Per joint, the angle equal to ``q`` modulo 2 pi that lies within ``limits`` and is closest
    to ``q_near`` (to 0 when ``q_near`` is None); None when some joint has no such angle."""
    qa = wrap_to_pi(q)
    lim = np.asarray(limits, dtype=np.float64)
    ref = np.zeros_like(qa) if q_near is None else np.asarray(q_near, dtype=np.float64)
    # the candidate closest to ref, then its neighbours one turn away (whichever fits the limits)
    base = qa + TWO_PI * np.round((ref - qa) / TWO_PI)
    cands = base[None, :] + TWO_PI * np.array([0.0, -1.0, 1.0, -2.0, 2.0])[:, None]
    ok = (cands >= lim[:, 0] - 1e-12) & (cands <= lim[:, 1] + 1e-12)
    cost = np.where(ok, np.abs(cands - ref), np.inf)
    idx = np.argmin(cost, axis=0)
    if not np.all(np.isfinite(cost[idx, np.arange(6)])):
        return None
    return np.clip(cands[idx, np.arange(6)], lim[:, 0], lim[:, 1])


def closest_solution(
    solutions: ArrayLike,
    q_prev: ArrayLike,
    weights: ArrayLike | None = None,
    max_step: float | None = None,
) -> int | None:
    """Index of the IK branch closest to the previous joints (weighted Euclidean), or None.

    With ``max_step`` (radians) branches that need a larger move of any single joint are refused:
    this is what keeps a sequence of moves free of wrist (or shoulder/elbow) flips.
    """
    sols = np.asarray(solutions, dtype=np.float64).reshape(-1, 6)
    if len(sols) == 0:
        return None
    prev = np.asarray(q_prev, dtype=np.float64).reshape(6)
    diff = sols - prev
    w = np.ones(6) if weights is None else np.asarray(weights, dtype=np.float64)
    cost = np.linalg.norm(diff * w, axis=1)
    if max_step is not None:
        cost = np.where(np.max(np.abs(diff), axis=1) <= max_step, cost, np.inf)
    i = int(np.argmin(cost))
    return i if np.isfinite(cost[i]) else None


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True)
class IKResult:
    """All IK solutions of one pose (rows, closest to ``q_near`` first) or why there is none.

    ``branches[i]`` is ``(shoulder, elbow, wrist)`` of solution i, each +1 or -1.
    """

    solutions: NDArray[np.float64]
    branches: NDArray[np.int8]
    reason: str = ""
    singular: tuple[str, ...] = field(default=())

    @property
    def reachable(self) -> bool:
        return len(self.solutions) > 0

    def __len__(self) -> int:
        return len(self.solutions)

    def of_branch(self, branch: Sequence[int]) -> NDArray[np.float64] | None:
        """The solution with the given ``(shoulder, elbow, wrist)`` signs, or None."""
        for sol, br in zip(self.solutions, self.branches):
            if tuple(int(b) for b in br) == tuple(int(b) for b in branch):
                return sol
        return None


def _empty(reason: str, singular: tuple[str, ...] = ()) -> IKResult:
    return IKResult(np.zeros((0, 6)), np.zeros((0, 3), dtype=np.int8), reason, singular)


# ----------------------------------------------------------------------------- elementary matrices
# cos/sin of ALPHA, exact (cos(pi/2) would be 6e-17 instead of 0)
_COS_ALPHA = (0.0, 1.0, 1.0, 0.0, 0.0, 1.0)
_SIN_ALPHA = (1.0, 0.0, 0.0, 1.0, -1.0, 0.0)


def _dh(theta: float, d: float, a: float, ca: float, sa: float) -> NDArray[np.float64]:
    ct, st = math.cos(theta), math.sin(theta)
    return np.array(
        [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]
    )


def _rz(t: float) -> NDArray[np.float64]:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(t: float) -> NDArray[np.float64]:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


_RX_HALF_PI = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


# ----------------------------------------------------------------------------- the arm
class URKinematics:
    """Forward and inverse kinematics of one UR e-series arm with an optional tool offset.

    ``joint_limits``: (6, 2) array of [lo, hi] per joint (default +-2 pi).
    ``clamp_tol``: how far beyond [-1, 1] the shoulder's asin argument may be and still count as
    the boundary (reachable, singular); further out the pose is unreachable.
    ``elbow_tol``: the same for the elbow's acos argument (looser: near a wrist singularity the
    wrist centre is known less precisely; a clamped solution must still pass the FK check).
    ``wrist_tol``: |sin q5| below which the wrist counts as singular (q6 taken from ``q_near``).
    ``verify_tol``: largest accepted FK error of a solution (metres and radians).
    """

    def __init__(
        self,
        model: str = "ur5e",
        flange_T_tcp: ArrayLike | None = None,
        joint_limits: ArrayLike | None = None,
        clamp_tol: float = 1e-9,
        elbow_tol: float = 1e-6,
        wrist_tol: float = 1e-10,
        verify_tol: float = 1e-10,
    ) -> None:
        if model not in UR_DH:
            raise ValueError(f"unknown UR model {model!r}; expected one of {sorted(UR_DH)}")
        self.model = model
        self.dh = UR_DH[model]
        self.flange_T_tcp = np.eye(4) if flange_T_tcp is None else check_rigid(flange_T_tcp, "flange_T_tcp")
        self.tcp_T_flange = invert(self.flange_T_tcp)
        lim = DEFAULT_JOINT_LIMITS.copy() if joint_limits is None else np.asarray(joint_limits, dtype=np.float64)
        if lim.shape != (6, 2) or not np.all(lim[:, 0] < lim[:, 1]):
            raise ValueError(f"joint_limits must be (6, 2) with lo < hi per joint, got {lim.tolist()}")
        self.joint_limits = lim
        self.clamp_tol = clamp_tol
        self.elbow_tol = elbow_tol
        self.wrist_tol = wrist_tol
        self.verify_tol = verify_tol

    # ------------------------------------------------------------------ forward
    def link_frames(self, q: ArrayLike) -> NDArray[np.float64]:
        """``base_T_frame_i`` for i = 0..6 as a (7, 4, 4) array (frame 0 = base, 6 = flange)."""
        qq = self._joints(q)
        frames = np.empty((7, 4, 4))
        frames[0] = np.eye(4)
        a, d = self.dh.a, self.dh.d
        for i in range(6):
            frames[i + 1] = frames[i] @ _dh(float(qq[i]), d[i], a[i], _COS_ALPHA[i], _SIN_ALPHA[i])
        return frames

    def fk_flange(self, q: ArrayLike) -> NDArray[np.float64]:
        """``base_T_flange`` for joint angles ``q`` (radians)."""
        return self.link_frames(q)[6]

    def fk(self, q: ArrayLike) -> NDArray[np.float64]:
        """``base_T_tcp`` for joint angles ``q`` (radians)."""
        return self.fk_flange(q) @ self.flange_T_tcp

    def within_limits(self, q: ArrayLike) -> bool:
        """True when every joint lies within its limits."""
        qq = self._joints(q)
        return bool(np.all(qq >= self.joint_limits[:, 0]) and np.all(qq <= self.joint_limits[:, 1]))

    @staticmethod
    def _joints(q: ArrayLike) -> NDArray[np.float64]:
        qq = np.asarray(q, dtype=np.float64).reshape(-1)
        if qq.shape != (6,) or not np.all(np.isfinite(qq)):
            raise ValueError(f"expected 6 finite joint angles, got {np.asarray(q).tolist()}")
        return qq

    # ------------------------------------------------------------------ inverse
    def ik(self, base_T_tcp: ArrayLike, q_near: ArrayLike | None = None) -> IKResult:
        """All solutions (up to 8) reaching ``base_T_tcp`` within the joint limits.

        Each solution's angles are the representatives modulo 2 pi closest to ``q_near`` (to 0
        without it); rows are sorted by distance to ``q_near``. An empty result carries a reason.
        """
        T = check_rigid(base_T_tcp, "IK target base_T_tcp") @ self.tcp_T_flange
        near = None if q_near is None else self._joints(q_near)
        raw, branches, reason, singular = self._ik_raw(T, near)
        if not raw:
            return _empty(reason or "out of reach of the arm", singular)
        sols: list[NDArray[np.float64]] = []
        kept: list[tuple[int, int, int]] = []
        out_of_limits = 0
        for q, br in zip(raw, branches):
            q, err = self._polish(q, T)
            if err >= self.verify_tol:
                continue  # a clamped branch that does not actually reach: not a solution
            rep = nearest_representative(q, near, self.joint_limits)
            if rep is None:
                out_of_limits += 1
                continue
            if any(np.max(np.abs(wrap_to_pi(rep - s))) < 1e-9 for s in sols):
                continue  # coincident branches at a singularity
            sols.append(rep)
            kept.append(br)
        if not sols:
            if out_of_limits:
                return _empty(f"all {out_of_limits} IK solutions lie outside the joint limits", singular)
            return _empty(reason or "no IK solution reproduces the pose (numerically out of reach)", singular)
        arr = np.array(sols)
        brs = np.array(kept, dtype=np.int8)
        ref = np.zeros(6) if near is None else near
        order = np.argsort(np.linalg.norm(arr - ref, axis=1), kind="stable")
        return IKResult(arr[order], brs[order], "", singular)

    def ik_closest(
        self,
        base_T_tcp: ArrayLike,
        q_near: ArrayLike,
        max_step: float | None = None,
        branch: Sequence[int] | None = None,
    ) -> NDArray[np.float64] | None:
        """The solution closest to ``q_near`` (optionally of one ``branch`` and with no joint moving
        more than ``max_step``), or None."""
        res = self.ik(base_T_tcp, q_near)
        sols = res.solutions
        if branch is not None:
            mask = np.all(res.branches == np.asarray(branch, dtype=np.int8), axis=1)
            sols = sols[mask]
        i = closest_solution(sols, q_near, max_step=max_step)
        return None if i is None else sols[i].copy()

    def branch_of(self, q: ArrayLike) -> tuple[int, int, int]:
        """The ``(shoulder, elbow, wrist)`` signs of a joint vector (as the IK labels them)."""
        res = self.ik(self.fk(q), q)
        if not res.reachable:
            raise ValueError(f"joints {np.asarray(q).tolist()} are outside the joint limits")
        return tuple(int(b) for b in res.branches[0])  # type: ignore[return-value]

    def _pose_error(self, q: NDArray[np.float64], T: NDArray[np.float64]) -> float:
        """FK error of the flange at ``q``: max(translation in m, rotation angle in rad)."""
        F = self.fk_flange(q)
        dp = float(np.linalg.norm(T[:3, 3] - F[:3, 3]))
        # ||R1 - R2||_F = 2 sqrt(2) sin(angle / 2): exact angle, cheap (no scipy call)
        s = min(1.0, float(np.linalg.norm(T[:3, :3] - F[:3, :3])) / (2.0 * math.sqrt(2.0)))
        return max(dp, 2.0 * math.asin(s))

    def _error_vector(self, q: NDArray[np.float64], T: NDArray[np.float64]) -> NDArray[np.float64]:
        F = self.fk_flange(q)
        dr = Rotation.from_matrix(T[:3, :3] @ F[:3, :3].T).as_rotvec()
        return np.concatenate([T[:3, 3] - F[:3, 3], dr])

    def _polish(self, q: NDArray[np.float64], T: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
        """Gauss-Newton steps on the geometric Jacobian while the FK error exceeds 1e-12; only for
        near-solutions (error below 1e-5): a far-off branch is not turned into another one."""
        err = self._pose_error(q, T)
        for _ in range(8):
            if err < 1e-12 or err > 1e-5:
                break
            e = self._error_vector(q, T)
            frames = self.link_frames(q)
            p_end = frames[6, :3, 3]
            J = np.empty((6, 6))
            for i in range(6):
                z, o = frames[i, :3, 2], frames[i, :3, 3]
                J[:3, i] = np.cross(z, p_end - o)
                J[3:, i] = z
            dq = np.linalg.lstsq(J, e, rcond=1e-10)[0]
            q_new = q + dq
            err_new = self._pose_error(q_new, T)
            if err_new >= err:
                break
            q, err = q_new, err_new
        return wrap_to_pi(q), err

    def _singular_q234(
        self, phi0: float, planar_centre: NDArray[np.float64]
    ) -> float:
        """At the wrist singularity q234 is free on a circle: the value closest to ``phi0`` that
        keeps the frame-4 origin ``P - d5 (sin phi, -cos phi)`` within the elbow's reach."""
        dh = self.dh
        P = float(np.hypot(planar_centre[0], planar_centre[1]))
        if P < 1e-12:
            return phi0
        psi = math.atan2(planar_centre[1], planar_centre[0])
        r_max = abs(dh.a2) + abs(dh.a3)
        r_min = abs(abs(dh.a2) - abs(dh.a3))
        # rho^2 = P^2 + d5^2 - 2 d5 P sin(phi - psi) must lie in [r_min^2, r_max^2]
        lo = (P * P + dh.d5**2 - r_max**2) / (2.0 * dh.d5 * P)
        hi = (P * P + dh.d5**2 - r_min**2) / (2.0 * dh.d5 * P)
        lo, hi = max(lo, -1.0), min(hi, 1.0)
        if lo > hi:
            return phi0  # no split reaches: the caller reports the elbow failure
        s0 = math.sin(phi0 - psi)
        if lo <= s0 <= hi:
            return phi0
        b = lo if s0 < lo else hi
        cands = [psi + math.asin(b), psi + math.pi - math.asin(b)]
        return min(cands, key=lambda c: abs(float(wrap_to_pi(c - phi0))))

    def _ik_raw(
        self, T: NDArray[np.float64], near: NDArray[np.float64] | None
    ) -> tuple[list[NDArray[np.float64]], list[tuple[int, int, int]], str, tuple[str, ...]]:
        dh = self.dh
        tol = self.clamp_tol
        R = T[:3, :3]
        p = T[:3, 3]
        singular: list[str] = []
        # q1: frame-5 origin (wrist centre) must lie d4 off the base z axis along z1
        p05 = p - dh.d6 * R[:, 2]
        r = math.hypot(p05[0], p05[1])
        if r <= dh.d4 * (1.0 - tol) or r == 0.0:
            return [], [], (
                f"wrist centre is {r:.4f} m from the base z axis, less than the shoulder "
                f"offset d4 = {dh.d4} m"), ("shoulder",)
        ratio = min(dh.d4 / r, 1.0)
        if ratio > 1.0 - 1e-7:
            singular.append("shoulder")
        phi = math.atan2(p05[1], p05[0])
        alpha1 = math.asin(ratio)
        q1_options = ((1, phi + alpha1), (-1, phi + math.pi - alpha1))

        sols: list[NDArray[np.float64]] = []
        labels: list[tuple[int, int, int]] = []
        worst_c3 = 0.0
        for s_sign, q1 in q1_options:
            R01 = _rz(q1) @ _RX_HALF_PI
            R16 = R01.T @ R
            p16 = R01.T @ (p - np.array([0.0, 0.0, dh.d1]))
            c5 = R16[2, 2]
            s5_abs = math.hypot(R16[0, 2], R16[1, 2])
            wrist_singular = s5_abs < self.wrist_tol
            if wrist_singular and "wrist" not in singular:
                singular.append("wrist")
            for w_sign in (1, -1):
                q5 = math.atan2(w_sign * s5_abs, c5)
                if wrist_singular:
                    q6 = 0.0 if near is None else float(near[5])
                else:
                    q6 = math.atan2(-R16[2, 1] * w_sign, R16[2, 0] * w_sign)
                M = R16 @ _rz(q6).T @ _ry(-q5).T
                q234 = math.atan2(M[1, 0], M[0, 0])
                p15 = p16 - dh.d6 * R16[:, 2]
                if wrist_singular:
                    q234_fit = self._singular_q234(q234, p15[:2])
                    if q234_fit != q234:
                        q234 = q234_fit
                        N = _ry(-q5).T @ _rz(q234).T @ R16
                        q6 = math.atan2(N[1, 0], N[0, 0])
                p14 = p15 - dh.d5 * np.array([math.sin(q234), -math.cos(q234), 0.0])
                x, y = float(p14[0]), float(p14[1])
                c3 = (x * x + y * y - dh.a2**2 - dh.a3**2) / (2.0 * dh.a2 * dh.a3)
                if abs(c3) > 1.0:  # beyond the stretched (or folded) arm: clamp only within elbow_tol
                    worst_c3 = c3 if abs(c3) > abs(worst_c3) else worst_c3
                    if abs(c3) > 1.0 + self.elbow_tol:
                        continue
                c3 = max(-1.0, min(1.0, c3))
                if abs(c3) > 1.0 - 1e-10 and "elbow" not in singular:
                    singular.append("elbow")
                s3_abs = math.sqrt(max(0.0, 1.0 - c3 * c3))
                for e_sign in (1, -1):
                    q3 = math.atan2(e_sign * s3_abs, c3)
                    q2 = math.atan2(y, x) - math.atan2(dh.a3 * math.sin(q3), dh.a2 + dh.a3 * math.cos(q3))
                    q4 = q234 - q2 - q3
                    sols.append(wrap_to_pi(np.array([q1, q2, q3, q4, q5, q6])))
                    labels.append((s_sign, e_sign, w_sign))
        # the reason is also what the caller reports when clamped solutions fail the FK check
        why = "" if worst_c3 == 0.0 else (
            f"out of reach of the arm (the elbow would need cos q3 = {worst_c3:.9g}, outside [-1, 1])")
        return sols, labels, why, tuple(singular)

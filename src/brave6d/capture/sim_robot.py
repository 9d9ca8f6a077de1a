"""A simulated UR arm on a virtual clock (the Robot protocol without hardware).

Moves take the time a UR controller would need (trapezoidal velocity profile on the leading
joint, the others synchronised; moveL: trapezoid on the Cartesian path), but nothing sleeps:
the virtual clock jumps, and the whole trajectory is kept so that the simulated camera can ask
for the true TCP pose at any image time (:meth:`SimRobot.true_base_T_tcp`).

Effects (from the scene spec; an unlisted effect draws no random number and changes nothing):

- ``robot_pose_error``: per move, a random rigid perturbation ``E`` (tool frame, Gaussian
  translation and rotation vector) separates the ACTUAL pose (``commanded @ E``, what the camera
  sees) from the reported one (the commanded pose, as a real robot reports its encoders). During
  a move the perturbation blends from the previous one to the new one.
- ``time_offset``: :meth:`tcp_pose` and :meth:`joints` report the state at ``now - offset_s``
  (a stale pose; it matters only while the arm moves).
"""

from __future__ import annotations

import bisect
import math
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from brave6d.core.spec import EffectsSpec, RobotSpec, SceneSpec
from brave6d.core.transforms import check_rigid, make_transform, matrix_to_ur_pose
from brave6d.capture.kinematics import URKinematics
from brave6d.capture.protocols import RobotError

# ----------------------------------------------------------------------------- motion-time model
#: Moves shorter than this (radians or metres) are null moves: no time, no effect draws.
NULL_MOVE = 1e-12


def trapezoid_time(distance: ArrayLike, v_max: float, a_max: float) -> NDArray[np.float64] | float:
    """Duration of a rest-to-rest move over ``distance`` with speed/acceleration limits.

    Triangular profile when the distance is too short to reach ``v_max``. Distances up to
    ``NULL_MOVE`` are null moves that take no time. Vectorised.
    """
    d = np.abs(np.asarray(distance, dtype=np.float64))
    if v_max <= 0 or a_max <= 0:
        raise ValueError(f"speed and acceleration must be positive, got {v_max}, {a_max}")
    d_acc = v_max * v_max / a_max  # distance spent accelerating + decelerating at full speed
    t = np.where(d <= d_acc, 2.0 * np.sqrt(d / a_max), d / v_max + v_max / a_max)
    t = np.where(d <= NULL_MOVE, 0.0, t)
    return float(t) if t.ndim == 0 else t


def trapezoid_fraction(t: float, distance: float, v_max: float, a_max: float) -> float:
    """Fraction in [0, 1] of ``distance`` covered ``t`` seconds after the start of the move."""
    D = abs(distance)
    if D <= NULL_MOVE:
        return 1.0
    T = float(trapezoid_time(D, v_max, a_max))
    if t >= T:
        return 1.0
    if t <= 0.0:
        return 0.0
    if D <= v_max * v_max / a_max:
        tp = T / 2.0
        s = 0.5 * a_max * t * t if t < tp else D - 0.5 * a_max * (T - t) ** 2
    else:
        ta = v_max / a_max
        if t < ta:
            s = 0.5 * a_max * t * t
        elif t < T - ta:
            s = 0.5 * a_max * ta * ta + v_max * (t - ta)
        else:
            s = D - 0.5 * a_max * (T - t) ** 2
    return min(1.0, max(0.0, s / D))


def joint_move_time(q_from: ArrayLike, q_to: ArrayLike, speed: float, acceleration: float) -> float:
    """Duration of a synchronised joint move (moveJ: the limits apply to the leading joint)."""
    delta = np.max(np.abs(np.asarray(q_to, dtype=np.float64) - np.asarray(q_from, dtype=np.float64)))
    return float(trapezoid_time(delta, speed, acceleration))


def joint_move_times(q_from: ArrayLike, q_to: ArrayLike, speed: float, acceleration: float) -> NDArray[np.float64]:
    """Vectorised :func:`joint_move_time` over leading axes of shape (..., 6)."""
    delta = np.max(np.abs(np.asarray(q_to, dtype=np.float64) - np.asarray(q_from, dtype=np.float64)), axis=-1)
    return np.asarray(trapezoid_time(delta, speed, acceleration), dtype=np.float64)


def format_pose(T: ArrayLike) -> str:
    """A pose as UR writes it, ``[x, y, z, rx, ry, rz]`` (m, rad), for error messages."""
    try:
        return "[" + ", ".join(f"{v:.4f}" for v in matrix_to_ur_pose(T)) + "]"
    except Exception:  # noqa: BLE001 - the message must not fail on a bad matrix
        return repr(np.asarray(T).tolist())


# ----------------------------------------------------------------------------- trajectory
@dataclass(frozen=True)
class _Segment:
    """One move: commanded joints/pose and actual perturbation at both ends, and its profile."""

    t0: float
    duration: float
    distance: float
    v_max: float
    a_max: float
    q0: NDArray[np.float64]
    q1: NDArray[np.float64]
    T0: NDArray[np.float64]
    T1: NDArray[np.float64]
    E0: NDArray[np.float64]
    E1: NDArray[np.float64]
    linear: bool
    path_s: NDArray[np.float64] | None = None  # linear moves: path samples (s) and joints there
    path_q: NDArray[np.float64] | None = None

    @property
    def t1(self) -> float:
        return self.t0 + self.duration

    def fraction(self, t: float) -> float:
        if self.duration <= 0.0:
            return 1.0
        return trapezoid_fraction(t - self.t0, self.distance, self.v_max, self.a_max)


def interpolate_pose(T0: NDArray[np.float64], T1: NDArray[np.float64], s: float) -> NDArray[np.float64]:
    """The pose a fraction ``s`` of the way from ``T0`` to ``T1``: straight line in translation, slerp in
    rotation (the simulated robot's and the UR emulator's linear moves and pose-error blending)."""
    if s <= 0.0:
        return T0.copy()
    if s >= 1.0:
        return T1.copy()
    rots = Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]]))
    R = Slerp([0.0, 1.0], rots)([s]).as_matrix()[0]
    return make_transform(R, (1.0 - s) * T0[:3, 3] + s * T1[:3, 3])


# ----------------------------------------------------------------------------- the robot
class SimRobot:
    """Simulated UR arm implementing :class:`brave6d.capture.protocols.Robot` on a virtual clock.

    ``robot``: speeds, accelerations, model and home joints (the start state unless
    ``start_joints`` is given). ``effects``/``seed``: see the module docstring.
    """

    def __init__(
        self,
        robot: RobotSpec,
        *,
        effects: EffectsSpec | None = None,
        seed: int = 0,
        start_joints: ArrayLike | None = None,
        flange_T_tcp: ArrayLike | None = None,
        joint_limits: ArrayLike | None = None,
        start_time: float = 0.0,
    ) -> None:
        self.spec = robot
        self.kin = URKinematics(robot.model, flange_T_tcp=flange_T_tcp, joint_limits=joint_limits)
        self.effects = effects if effects is not None else EffectsSpec()
        self.seed = int(seed)
        q = np.deg2rad(np.asarray(robot.home_joints_deg, dtype=np.float64)) if start_joints is None \
            else np.asarray(start_joints, dtype=np.float64).reshape(6)
        if not self.kin.within_limits(q):
            raise RobotError(f"start joints {np.round(q, 4).tolist()} are outside the joint limits")
        self._clock = float(start_time)
        self._q = q.copy()
        self._T = self.kin.fk(q)
        self._E = np.eye(4)
        self._segments: list[_Segment] = []
        self._starts: list[float] = []
        self._closed = False
        self._fault: str | None = None
        # one independent stream per effect, created only when the effect is listed
        self._rng_pose = (
            np.random.default_rng([self.seed, zlib.crc32(b"robot_pose_error")])
            if self.effects.robot_pose_error is not None else None
        )
        #: number of random draws made so far (stays 0 when no robot effect is listed)
        self.random_draws = 0

    @classmethod
    def from_spec(cls, spec: SceneSpec, *, effects: EffectsSpec | None = None, **kwargs: object) -> SimRobot:
        """A SimRobot for a scene: robot spec, ``simulation.effects`` (or ``effects`` given here,
        e.g. other effects for a calibration capture) and ``simulation.seed``."""
        seed = spec.simulation.seed if spec.simulation is not None else 0
        if effects is None and spec.simulation is not None:
            effects = spec.simulation.effects
        return cls(spec.robot, effects=effects, seed=seed, **kwargs)  # type: ignore[arg-type]

    # ------------------------------------------------------------------ protocol: motion
    def move_joints(self, joints: NDArray[np.float64]) -> None:
        """Joint move (moveJ) to ``joints``; advances the virtual clock by the motion time."""
        self._check_usable()
        q1 = np.asarray(joints, dtype=np.float64).reshape(-1)
        if q1.shape != (6,) or not np.all(np.isfinite(q1)):
            raise RobotError(f"move_joints needs 6 finite joint angles, got {np.asarray(joints).tolist()}")
        if not self.kin.within_limits(q1):
            raise RobotError(f"joint target {np.round(q1, 4).tolist()} is outside the joint limits")
        delta = float(np.max(np.abs(q1 - self._q)))
        self._append(
            distance=delta, v_max=self.spec.joint_speed, a_max=self.spec.joint_acceleration,
            q1=q1, T1=self.kin.fk(q1), linear=False,
        )

    def move_to(self, base_T_tcp: NDArray[np.float64], *, linear: bool = False) -> None:
        """Move the TCP to ``base_T_tcp`` (IK branch closest to the current joints)."""
        self._check_usable()
        try:
            T1 = check_rigid(base_T_tcp, "target base_T_tcp")
        except ValueError as exc:
            raise RobotError(f"invalid target pose: {exc}") from None
        if not linear:
            res = self.kin.ik(T1, self._q)
            if not res.reachable:
                raise RobotError(f"target pose {format_pose(T1)} is unreachable: {res.reason}")
            self.move_joints(res.solutions[0])
            return
        path_s, path_q = self._linear_path(self._T, T1)
        trans = float(np.linalg.norm(T1[:3, 3] - self._T[:3, 3]))
        angle = float(Rotation.from_matrix(self._T[:3, :3].T @ T1[:3, :3]).magnitude())
        t_trans = float(trapezoid_time(trans, self.spec.linear_speed, self.spec.linear_acceleration))
        t_rot = float(trapezoid_time(angle, self.spec.joint_speed, self.spec.joint_acceleration))
        if t_trans >= t_rot:
            dist, v, a = trans, self.spec.linear_speed, self.spec.linear_acceleration
        else:
            dist, v, a = angle, self.spec.joint_speed, self.spec.joint_acceleration
        self._append(distance=dist, v_max=v, a_max=a, q1=path_q[-1], T1=T1, linear=True,
                     path_s=path_s, path_q=path_q)

    def _linear_path(
        self, T0: NDArray[np.float64], T1: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Joints along a straight Cartesian path, following one IK branch; RobotError if it breaks."""
        trans = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        angle = float(Rotation.from_matrix(T0[:3, :3].T @ T1[:3, :3]).magnitude())
        n = max(10, math.ceil(trans / 0.005) + math.ceil(angle / math.radians(2.0)))
        s_values = np.linspace(0.0, 1.0, n + 1)
        qs = [self._q.copy()]
        for s in s_values[1:]:
            T = interpolate_pose(T0, T1, float(s))
            q = self.kin.ik_closest(T, qs[-1], max_step=math.radians(30.0))
            if q is None:
                res = self.kin.ik(T, qs[-1])
                why = res.reason or "the arm would have to flip its configuration"
                raise RobotError(
                    f"linear move to {format_pose(T1)} refused: the straight path leaves the reachable "
                    f"set at {100 * s:.0f}% ({format_pose(T)}): {why}"
                )
            qs.append(q)
        return s_values, np.array(qs)

    def _append(
        self, *, distance: float, v_max: float, a_max: float, q1: NDArray[np.float64], T1: NDArray[np.float64],
        linear: bool, path_s: NDArray[np.float64] | None = None, path_q: NDArray[np.float64] | None = None,
    ) -> None:
        if distance <= NULL_MOVE and float(np.max(np.abs(T1 - self._T))) <= NULL_MOVE:
            return  # null move: nothing happens, nothing is drawn
        E1 = self._draw_pose_error()
        duration = float(trapezoid_time(distance, v_max, a_max))
        seg = _Segment(self._clock, duration, distance, v_max, a_max, self._q.copy(), q1.copy(),
                       self._T.copy(), T1.copy(), self._E.copy(), E1, linear, path_s, path_q)
        self._segments.append(seg)
        self._starts.append(seg.t0)
        self._clock = seg.t1
        self._q, self._T, self._E = q1.copy(), T1.copy(), E1

    def _draw_pose_error(self) -> NDArray[np.float64]:
        cfg = self.effects.robot_pose_error
        if cfg is None or self._rng_pose is None:
            return np.eye(4)
        draw = self._rng_pose.normal(size=6)
        self.random_draws += 6
        t = draw[:3] * cfg.translation_sigma_m
        rv = draw[3:] * math.radians(cfg.rotation_sigma_deg)
        return make_transform(Rotation.from_rotvec(rv).as_matrix(), t)

    def wait_until_steady(self, settle_time_s: float) -> None:
        """Advance the virtual clock past the end of the motion plus ``settle_time_s``."""
        self._check_open()
        end = self._segments[-1].t1 if self._segments else self._clock
        self._clock = max(self._clock, end) + max(0.0, float(settle_time_s))

    def advance(self, dt: float) -> None:
        """Advance the virtual clock by ``dt`` seconds (e.g. camera exposure and transfer)."""
        if dt < 0:
            raise ValueError(f"cannot move the clock backwards (dt = {dt})")
        self._clock += float(dt)

    def stop(self) -> None:
        """Moves are blocking in the simulation, so nothing is ever in motion: a no-op."""

    def close(self) -> None:
        """Mark the robot closed (later moves raise RobotError)."""
        self._closed = True

    def inject_fault(self, message: str = "protective stop") -> None:
        """Make every later move raise RobotError(message) until :meth:`clear_fault` (for tests)."""
        self._fault = message

    def clear_fault(self) -> None:
        self._fault = None

    def _check_open(self) -> None:
        if self._closed:
            raise RobotError("the simulated robot is closed")

    def _check_usable(self) -> None:
        self._check_open()
        if self._fault is not None:
            raise RobotError(f"simulated robot fault: {self._fault}")

    # ------------------------------------------------------------------ protocol: state
    def now(self) -> float:
        """The virtual clock (seconds)."""
        return self._clock

    def tcp_pose(self) -> NDArray[np.float64]:
        """The reported (commanded) TCP pose, stale by ``time_offset`` when that effect is listed."""
        return self.commanded_base_T_tcp(self._report_time())

    def joints(self) -> NDArray[np.float64]:
        """The reported joints, stale by ``time_offset`` when that effect is listed."""
        return self.joints_at(self._report_time())

    def _report_time(self) -> float:
        off = self.effects.time_offset
        return self._clock if off is None else self._clock - off.offset_s

    def inverse_kinematics(
        self, base_T_tcp: NDArray[np.float64], q_near: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64] | None:
        """IK solution closest to ``q_near`` (default: the current joints), or None."""
        try:
            res = self.kin.ik(base_T_tcp, self._q if q_near is None else q_near)
        except ValueError:
            return None
        return res.solutions[0].copy() if res.reachable else None

    # ------------------------------------------------------------------ trajectory queries
    def _segment_at(self, t: float) -> _Segment | None:
        i = bisect.bisect_right(self._starts, t) - 1
        return self._segments[i] if i >= 0 else None

    def _state_at(self, t: float) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(joints, commanded pose, perturbation) at virtual time ``t``."""
        seg = self._segment_at(t)
        if seg is None:
            first = self._segments[0] if self._segments else None
            if first is None:
                return self._q.copy(), self._T.copy(), self._E.copy()
            return first.q0.copy(), first.T0.copy(), first.E0.copy()
        s = seg.fraction(t)
        if s >= 1.0:
            return seg.q1.copy(), seg.T1.copy(), seg.E1.copy()
        E = seg.E0.copy() if np.array_equal(seg.E0, seg.E1) else interpolate_pose(seg.E0, seg.E1, s)
        if seg.linear:
            T = interpolate_pose(seg.T0, seg.T1, s)
            assert seg.path_s is not None and seg.path_q is not None
            q = np.array([np.interp(s, seg.path_s, seg.path_q[:, j]) for j in range(6)])
        else:
            q = seg.q0 + s * (seg.q1 - seg.q0)
            T = self.kin.fk(q)
        return q, T, E

    def joints_at(self, t: float) -> NDArray[np.float64]:
        """Commanded joints at virtual time ``t``."""
        return self._state_at(t)[0]

    def commanded_base_T_tcp(self, t: float | None = None) -> NDArray[np.float64]:
        """The commanded (= reported, without time offset) TCP pose at ``t`` (default: now)."""
        return self._state_at(self._clock if t is None else t)[1]

    def true_base_T_tcp(self, t: float | None = None) -> NDArray[np.float64]:
        """The ACTUAL TCP pose at virtual time ``t`` (default: now): what the camera sees."""
        _, T, E = self._state_at(self._clock if t is None else t)
        return T @ E

    def true_base_T_flange(self, t: float | None = None) -> NDArray[np.float64]:
        """The actual flange pose at ``t`` (equals the TCP pose unless a tool offset is set)."""
        return self.true_base_T_tcp(t) @ self.kin.tcp_T_flange

    def is_moving(self, t: float | None = None) -> bool:
        """True while a move is in progress at ``t`` (default: now)."""
        tt = self._clock if t is None else t
        seg = self._segment_at(tt)
        return seg is not None and tt < seg.t1

    def motion_time(self, q_from: ArrayLike, q_to: ArrayLike) -> float:
        """Duration of a joint move between two joint vectors with this robot's limits."""
        return joint_move_time(q_from, q_to, self.spec.joint_speed, self.spec.joint_acceleration)

    @property
    def move_count(self) -> int:
        return len(self._segments)

"""The emulated arm's motion on the controller's clock: moves that can be stopped part way.

A move is joint-interpolated (movej: the leading joint follows a trapezoidal speed profile, the
others are synchronised, as ``capture/sim_robot.py`` models it) or a straight TCP line (movel:
joints from the inverse kinematics along the path, one arm configuration throughout). A stop
(stopj/stopl, a protective stop, the program stopped) replaces the rest of the profile by a
constant deceleration from the speed the arm has at that moment, along the same path.

``robot_pose_error`` (when a scene lists it) perturbs the ACTUAL pose per move exactly as the
simulated robot does, with the same random stream: the controller reports the commanded pose
(its encoders), the camera sees ``commanded @ E``.
"""

from __future__ import annotations

import bisect
import math
import zlib
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.spec import RobotPoseError
from brave6d.core.transforms import make_transform
from brave6d.capture.kinematics import URKinematics
from brave6d.capture.sim_robot import interpolate_pose, trapezoid_fraction, trapezoid_time

Array = NDArray[np.float64]
#: Moves kept for questions about the past (the simulated camera asks for the pose at its image time).
HISTORY = 4096
#: A linear path is followed with joint samples at most this far apart (m, rad), no joint turning
#: more than MAX_PATH_STEP between samples (else the arm would flip configuration).
PATH_STEP_M = 0.005
PATH_STEP_RAD = math.radians(2.0)
MAX_PATH_STEP = math.radians(30.0)


class PathError(Exception):
    """A move the controller cannot execute (the program stops with this message)."""


@dataclass
class Move:
    """One move from ``t0``: geometry (joint line or sampled TCP line) and its speed profile."""

    t0: float
    distance: float
    v_max: float
    a_max: float
    q0: Array
    q1: Array
    E0: Array
    E1: Array
    linear: bool
    path_s: Array | None = None
    path_q: Array | None = None
    kind: str = "movej"
    #: set by :meth:`stop`: (time, fraction then, path speed then, deceleration) in path units
    braking: tuple[float, float, float, float] | None = field(default=None)

    @property
    def planned_duration(self) -> float:
        return float(trapezoid_time(self.distance, self.v_max, self.a_max))

    @property
    def t1(self) -> float:
        """When the arm comes to rest."""
        if self.braking is None:
            return self.t0 + self.planned_duration
        ts, _, v, a = self.braking
        return ts + (v / a if a > 0 else 0.0)

    def fraction(self, t: float) -> float:
        """Fraction of the path covered at ``t`` (0..1)."""
        if self.distance <= 0.0:
            return 1.0
        if self.braking is not None and t >= self.braking[0]:
            ts, s0, v, a = self.braking
            dt = min(t - ts, v / a if a > 0 else 0.0)
            return min(1.0, s0 + (v * dt - 0.5 * a * dt * dt) / self.distance)
        return float(trapezoid_fraction(t - self.t0, self.distance, self.v_max, self.a_max))

    def path_speed(self, t: float) -> float:
        """Speed along the path (path units per second) at ``t``."""
        h = 1e-4
        return max(0.0, (self.fraction(t + h) - self.fraction(t - h)) / (2 * h) * self.distance)

    def joints(self, s: float) -> Array:
        if self.linear and self.path_s is not None and self.path_q is not None:
            return np.array([np.interp(s, self.path_s, self.path_q[:, j]) for j in range(6)])
        return self.q0 + s * (self.q1 - self.q0)

    def error(self, s: float) -> Array:
        return self.E0.copy() if np.array_equal(self.E0, self.E1) else interpolate_pose(self.E0, self.E1, s)

    def stop(self, t: float, deceleration: float) -> None:
        """Decelerate from time ``t`` at ``deceleration`` (path units / s^2) along the same path."""
        if t >= self.t1:
            return
        s, v = self.fraction(t), self.path_speed(t)
        self.braking = (t, s, v, max(deceleration, 1e-9))


class Motion:
    """The arm's trajectory: current and past moves, queried at any controller time."""

    def __init__(self, kin: URKinematics, q_start: Array, *, pose_error: RobotPoseError | None = None,
                 seed: int = 0, rotation_speed: float = 1.05, rotation_acceleration: float = 1.4) -> None:
        self.kin = kin
        #: how fast movel turns the tool when the rotation, not the translation, leads (rad/s, rad/s^2)
        self.rotation_speed, self.rotation_acceleration = rotation_speed, rotation_acceleration
        self._q_start = np.asarray(q_start, dtype=np.float64).copy()
        self._moves: deque[Move] = deque(maxlen=HISTORY)
        self._starts: deque[float] = deque(maxlen=HISTORY)
        self._pose_error = pose_error
        # the same stream as SimRobot's robot_pose_error (created only when the effect is listed)
        self._rng = np.random.default_rng([int(seed), zlib.crc32(b"robot_pose_error")]) if pose_error else None
        self.count = 0

    # ------------------------------------------------------------------ queries
    def _move_at(self, t: float) -> Move | None:
        i = bisect.bisect_right(self._starts, t) - 1
        return self._moves[i] if i >= 0 else None

    def state(self, t: float) -> tuple[Array, Array, float]:
        """(commanded joints, actual-pose perturbation E, joint speed norm) at controller time ``t``."""
        move = self._move_at(t)
        if move is None:
            first = self._moves[0] if self._moves else None
            if first is None:
                return self._q_start.copy(), np.eye(4), 0.0
            return first.q0.copy(), first.E0.copy(), 0.0
        s = move.fraction(t)
        q = move.joints(s)
        speed = 0.0
        if t < move.t1:
            h = 1e-3
            step = move.joints(move.fraction(t + h)) - move.joints(move.fraction(t - h))
            speed = float(np.linalg.norm(step)) / (2 * h)
        return q, move.error(s), speed

    def current(self) -> Move | None:
        return self._moves[-1] if self._moves else None

    def moving(self, t: float) -> bool:
        move = self.current()
        return move is not None and t < move.t1

    # ------------------------------------------------------------------ commands
    def movej(self, t: float, q_target: Array, speed: float, acceleration: float, kind: str = "movej") -> Move:
        q0, E0, _ = self.state(t)
        q1 = np.asarray(q_target, dtype=np.float64).reshape(6)
        if not self.kin.within_limits(q1):
            raise PathError(f"{kind}: joint target {np.round(q1, 4).tolist()} outside the joint limits")
        distance = float(np.max(np.abs(q1 - q0)))
        return self._append(Move(t, distance, speed, acceleration, q0, q1, E0, self._draw(E0, distance), False,
                                 kind=kind))

    def movel(self, t: float, T_target: Array, speed: float, acceleration: float, kind: str = "movel") -> Move:
        q0, E0, _ = self.state(t)
        T0 = self.kin.fk(q0)
        T1 = np.asarray(T_target, dtype=np.float64)
        trans = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        angle = float(Rotation.from_matrix(T0[:3, :3].T @ T1[:3, :3]).magnitude())
        n = max(10, math.ceil(trans / PATH_STEP_M) + math.ceil(angle / PATH_STEP_RAD))
        s_values = np.linspace(0.0, 1.0, n + 1)
        qs = [q0.copy()]
        for s in s_values[1:]:
            q = self.kin.ik_closest(interpolate_pose(T0, T1, float(s)), qs[-1], max_step=MAX_PATH_STEP)
            if q is None:
                raise PathError(f"{kind}: inverse kinematics failed along the path at {100 * s:.0f}% "
                                "(out of reach or a configuration flip)")
            qs.append(q)
        # the path's duration: translation at the tool speed, or rotation at the joint limits, whichever is longer
        t_trans = float(trapezoid_time(trans, speed, acceleration))
        t_rot = float(trapezoid_time(angle, self.rotation_speed, self.rotation_acceleration))
        dist, v, a = (trans, speed, acceleration) if t_trans >= t_rot else \
            (angle, self.rotation_speed, self.rotation_acceleration)
        return self._append(Move(t, dist, v, a, q0, qs[-1], E0, self._draw(E0, dist), True, s_values,
                                 np.array(qs), kind=kind))

    def stop(self, t: float, deceleration: float) -> Move | None:
        """Brake the current move (if any is under way at ``t``); returns it."""
        move = self.current()
        if move is None or t >= move.t1:
            return None
        # a joint deceleration (rad/s^2) brakes the leading joint; a tool one (m/s^2) the TCP path
        move.stop(t, deceleration)
        return move

    def _append(self, move: Move) -> Move:
        current = self.current()
        if current is not None and move.t0 < current.t1:
            current.stop(move.t0, 1e9)  # a new command replaces the rest of the old move (no blending)
        self._moves.append(move)
        self._starts.append(move.t0)
        self.count += 1
        return move

    def _draw(self, E0: Array, distance: float) -> Array:
        cfg = self._pose_error
        if cfg is None or self._rng is None or distance <= 1e-12:
            return E0.copy()
        draw = self._rng.normal(size=6)
        rv = draw[3:] * math.radians(cfg.rotation_sigma_deg)
        return make_transform(Rotation.from_rotvec(rv).as_matrix(), draw[:3] * cfg.translation_sigma_m)

    # ------------------------------------------------------------------ regions
    def first_time_inside(self, move: Move, tcp_of: object, lo: Array, hi: Array, *, inside: bool = True,
                          samples: int = 400) -> float | None:
        """The first controller time at which the TCP position of ``move`` is inside (or, with
        ``inside=False``, outside) the box [lo, hi]; ``tcp_of(q)`` gives ``base_T_tcp``."""
        t0, t1 = move.t0, move.t1
        for t in np.linspace(t0, t1, samples + 1):
            p = tcp_of(move.joints(move.fraction(float(t))))[:3, 3]  # type: ignore[operator]
            within = bool(np.all(p >= lo) and np.all(p <= hi))
            if within == inside:
                return float(t)
        return None

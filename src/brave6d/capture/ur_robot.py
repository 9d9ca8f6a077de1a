"""The real UR arm behind the Robot protocol, on ur-rtde.

Everything that can go wrong at the lab robot becomes one :class:`RobotError` line: the
connection (retried: users report refused connections right after protective stops), a target
outside the safety limits (refused before moving), a protective stop or a lost connection
(checked before and after every move), a move the controller rejects. On any error, and on
Ctrl-C, the arm is stopped before the exception propagates.

ur-rtde is imported lazily (only when connecting with the default factory), so that planning
and simulation never need it. Tests inject ``interfaces_factory`` with in-process fakes.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.extras import require
from brave6d.core.spec import RobotSpec
from brave6d.core.transforms import check_rigid, matrix_to_ur_pose, ur_pose_to_matrix
from brave6d.capture.protocols import RobotError

log = logging.getLogger(__name__)

#: ``host -> (control, receive)``: objects with the ur-rtde RTDEControlInterface /
#: RTDEReceiveInterface methods this module uses.
InterfacesFactory = Callable[[str], tuple[Any, Any]]


def rtde_interfaces(host: str) -> tuple[Any, Any]:
    """Open ur-rtde's control and receive interfaces to ``host`` (imported here, lazily)."""
    rtde_control = require("rtde_control", "robot", "--robot ur:HOST")
    rtde_receive = require("rtde_receive", "robot", "--robot ur:HOST")
    receive = rtde_receive.RTDEReceiveInterface(host)
    try:
        control = rtde_control.RTDEControlInterface(host)
    except BaseException:
        _quietly(receive.disconnect)
        raise
    return control, receive


def _quietly(fn: Callable[..., Any], *args: Any) -> Any:
    """Call ``fn`` and swallow any exception (for clean-up paths that must not mask the cause)."""
    try:
        return fn(*args)
    except Exception:  # noqa: BLE001
        return None


def _fmt(pose: list[float]) -> str:
    return "[" + ", ".join(f"{v:.4f}" for v in pose) + "]"


class URRobot:
    """A UR e-series arm over RTDE, implementing :class:`brave6d.capture.protocols.Robot`.

    ``robot``: speeds/accelerations passed to moveJ/moveL. ``tcp_offset``: ``flange_T_tcp`` set on
    the controller at connect (default identity: the reported TCP is the flange, as the planner's
    kinematics assume); None leaves the controller's TCP as configured on the pendant.
    ``sleep``/``monotonic`` are injectable so that tests need no real waiting.
    """

    def __init__(
        self,
        host: str,
        robot: RobotSpec,
        *,
        interfaces_factory: InterfacesFactory | None = None,
        connect_tries: int = 3,
        retry_pause_s: float = 2.0,
        steady_timeout_s: float = 30.0,
        poll_interval_s: float = 0.02,
        tcp_offset: ArrayLike | None = np.eye(4),
        sleep: Callable[[float], None] = time.sleep,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        if connect_tries < 1:
            raise ValueError("connect_tries must be at least 1")
        self.host = host
        self.spec = robot
        self._factory = interfaces_factory or rtde_interfaces
        self.connect_tries = connect_tries
        self.retry_pause_s = retry_pause_s
        self.steady_timeout_s = steady_timeout_s
        self.poll_interval_s = poll_interval_s
        self._tcp_offset = None if tcp_offset is None else check_rigid(tcp_offset, "tcp_offset")
        self._sleep = sleep
        self._monotonic = monotonic
        self._control: Any = None
        self._receive: Any = None
        self._last_linear = False
        self._closed = False
        self._connect()

    # ------------------------------------------------------------------ connection
    def _connect(self) -> None:
        last: BaseException | None = None
        for attempt in range(1, self.connect_tries + 1):
            try:
                self._control, self._receive = self._factory(self.host)
                break
            except Exception as exc:  # noqa: BLE001 - ur-rtde raises RuntimeError; fakes may differ
                last = exc
                log.warning("UR connect to %s failed (try %d/%d): %s", self.host, attempt, self.connect_tries, exc)
                if attempt < self.connect_tries:
                    self._sleep(self.retry_pause_s)
        else:
            raise RobotError(
                f"Could not connect to UR robot at {self.host} after {self.connect_tries} tries: {last}"
            )
        self._closed = False
        if self._tcp_offset is not None:
            offset = matrix_to_ur_pose(self._tcp_offset)
            if not self._call("setTcp", offset):
                raise RobotError(f"UR robot at {self.host} refused the TCP offset {_fmt(offset)}")

    def reconnect(self) -> None:
        """Re-open the RTDE connection (ur-rtde's reconnect, else fresh interfaces with retries)."""
        if self._control is not None and self._receive is not None:
            _quietly(self._control.reconnect)
            _quietly(self._receive.reconnect)
            if _quietly(self._control.isConnected) and _quietly(self._receive.isConnected):
                self._closed = False
                return
        self._drop_interfaces()
        self._connect()

    def _drop_interfaces(self) -> None:
        for iface in (self._control, self._receive):
            if iface is not None:
                _quietly(iface.disconnect)
        self._control = self._receive = None

    def close(self) -> None:
        """Stop the control script and disconnect (idempotent)."""
        if self._control is not None:
            _quietly(self._control.stopScript)
        self._drop_interfaces()
        self._closed = True

    def __enter__(self) -> URRobot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ low-level guards
    def _call(self, name: str, *args: Any, receive: bool = False) -> Any:
        """Call an interface method; any library error becomes a RobotError naming the call."""
        if self._closed or self._control is None or self._receive is None:
            raise RobotError(f"UR robot at {self.host} is not connected (closed); call reconnect()")
        iface = self._receive if receive else self._control
        try:
            return getattr(iface, name)(*args)
        except RobotError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise RobotError(f"UR robot at {self.host}: {name} failed: {exc}") from None

    def check_health(self, when: str = "now") -> None:
        """Raise RobotError when the connection is lost or the arm is protectively stopped."""
        if not (self._call("isConnected", receive=True) and self._call("isConnected")):
            raise RobotError(f"lost the connection to UR robot at {self.host} ({when}); call reconnect()")
        if self._call("isProtectiveStopped", receive=True):
            raise RobotError(
                f"UR robot at {self.host} is in a protective stop ({when}); clear it on the teach pendant "
                "(or the dashboard's 'unlock protective stop') and check the workspace before continuing"
            )

    def _guarded_move(self, what: str, move: Callable[[], Any]) -> None:
        """Health check, move, health check; stop the arm on any error or Ctrl-C."""
        self.check_health(f"before {what}")
        try:
            ok = move()
            if ok is False:
                self.check_health(f"after {what} failed")
                raise RobotError(f"UR robot at {self.host} did not complete {what}")
            self.check_health(f"after {what}")
        except KeyboardInterrupt:
            self.stop()
            raise
        except RobotError:
            self.stop()
            raise
        except Exception as exc:  # noqa: BLE001
            self.stop()
            raise RobotError(f"UR robot at {self.host}: {what} failed: {exc}") from None

    def _check_safe(self, pose: list[float]) -> None:
        if not self._call("isPoseWithinSafetyLimits", pose):
            raise RobotError(f"target pose {_fmt(pose)} is outside the UR robot's safety limits; refused")

    # ------------------------------------------------------------------ protocol: motion
    def move_to(self, base_T_tcp: NDArray[np.float64], *, linear: bool = False) -> None:
        """moveL to the pose, or moveJ to the controller's IK solution closest to the current joints."""
        try:
            pose = matrix_to_ur_pose(base_T_tcp)
        except ValueError as exc:
            raise RobotError(f"invalid target pose: {exc}") from None
        self.check_health("before the move")
        self._check_safe(pose)
        self._last_linear = linear
        if linear:
            self._guarded_move(
                f"moveL to {_fmt(pose)}",
                lambda: self._control.moveL(pose, self.spec.linear_speed, self.spec.linear_acceleration),
            )
            return
        q = self._ik(pose, self.joints())
        if q is None:
            raise RobotError(f"target pose {_fmt(pose)} has no inverse-kinematics solution on the controller")
        self._guarded_move(
            f"moveJ to {_fmt(pose)}",
            lambda: self._control.moveJ(q.tolist(), self.spec.joint_speed, self.spec.joint_acceleration),
        )

    def move_joints(self, joints: NDArray[np.float64]) -> None:
        """moveJ to joint angles (radians)."""
        q = np.asarray(joints, dtype=np.float64).reshape(-1)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise RobotError(f"move_joints needs 6 finite joint angles, got {np.asarray(joints).tolist()}")
        self._last_linear = False
        self._guarded_move(
            f"moveJ to joints {_fmt(q.tolist())}",
            lambda: self._control.moveJ(q.tolist(), self.spec.joint_speed, self.spec.joint_acceleration),
        )

    def stop(self) -> None:
        """Decelerate to a stop (stopL after a linear move, else stopJ); never raises."""
        if self._control is None:
            return
        if self._last_linear:
            _quietly(self._control.stopL, 10.0 * self.spec.linear_acceleration)
        else:
            _quietly(self._control.stopJ, 2.0 * self.spec.joint_acceleration)

    def wait_until_steady(self, settle_time_s: float) -> None:
        """Poll isSteady (health-checked) until the arm is still, then wait ``settle_time_s``."""
        deadline = self._monotonic() + self.steady_timeout_s
        try:
            while True:
                self.check_health("while waiting for the arm to settle")
                if self._call("isSteady"):
                    break
                if self._monotonic() > deadline:
                    raise RobotError(
                        f"UR robot at {self.host} did not come to rest within {self.steady_timeout_s:.1f} s"
                    )
                self._sleep(self.poll_interval_s)
            if settle_time_s > 0:
                self._sleep(settle_time_s)
        except KeyboardInterrupt:
            self.stop()
            raise
        except RobotError:
            self.stop()
            raise

    # ------------------------------------------------------------------ protocol: state
    def tcp_pose(self) -> NDArray[np.float64]:
        """getActualTCPPose as ``base_T_tcp``."""
        pose = self._call("getActualTCPPose", receive=True)
        try:
            return ur_pose_to_matrix(pose)
        except ValueError as exc:
            raise RobotError(f"UR robot at {self.host} reported an invalid TCP pose: {exc}") from None

    def joints(self) -> NDArray[np.float64]:
        """getActualQ (radians)."""
        q = np.asarray(self._call("getActualQ", receive=True), dtype=np.float64).reshape(-1)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise RobotError(f"UR robot at {self.host} reported invalid joints {q.tolist()}")
        return q

    def now(self) -> float:
        """The controller's clock (getTimestamp, seconds since controller start)."""
        return float(self._call("getTimestamp", receive=True))

    def inverse_kinematics(
        self, base_T_tcp: NDArray[np.float64], q_near: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64] | None:
        """The controller's IK closest to ``q_near`` (default: current joints), None if unreachable
        or outside the safety limits."""
        try:
            pose = matrix_to_ur_pose(base_T_tcp)
        except ValueError:
            return None
        if not self._call("isPoseWithinSafetyLimits", pose):
            return None
        near = self.joints() if q_near is None else np.asarray(q_near, dtype=np.float64)
        return self._ik(pose, near)

    def _ik(self, pose: list[float], q_near: NDArray[np.float64]) -> NDArray[np.float64] | None:
        near = [float(v) for v in q_near]
        has = getattr(self._control, "getInverseKinematicsHasSolution", None)
        if has is not None and not self._call("getInverseKinematicsHasSolution", pose, near):
            return None
        try:
            q = np.asarray(self._call("getInverseKinematics", pose, near), dtype=np.float64).reshape(-1)
        except RobotError:
            return None
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            return None
        return q

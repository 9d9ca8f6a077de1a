"""The real UR arm behind the Robot protocol, on ur-rtde.

Everything that can go wrong at the lab robot becomes one :class:`RobotError` line: the
connection (retried: users report refused connections right after protective stops), a target
outside the safety limits (refused before moving), a protective stop, a stopped program or a lost
connection (checked before, during and after every move), a move the controller rejects, and a
crash or hang of ur-rtde itself. On any error, and on Ctrl-C, the arm is stopped before the
exception propagates.

ur-rtde runs in a child process (:mod:`brave6d.capture.ur_worker`): its reconnect segfault or a
wedged call ends that process, not the capture. Moves are sent asynchronously and followed by
polling the controller's async-operation register, so a stop (Ctrl-C, a fault) reaches the arm
while it moves; when ur-rtde can no longer send it, the dashboard's ``stop`` (a plain socket to
port 29999) stops the program instead. ``interfaces_factory`` may replace the child process
(``host -> (control, receive)``); the tests drive the real client against ``brave6d ur-emulator``.
"""

from __future__ import annotations

import importlib.util
import logging
import socket
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


#: Dashboard server port of every UR controller (its 'stop' needs no RTDE connection).
DASHBOARD_PORT = 29999
#: How far (m, and rotation-matrix entries) the state stream's TCP pose may be from the controller's own
#: forward kinematics at rest: encoder noise passes, the previous view's pose (centimetres away) does not.
FRESH_POSE_TOLERANCE = 5e-4
#: Bits of ur-rtde's async operation status (the control script's output_int_register_2).
_ASYNC_RUNNING = 0x8000


def rtde_interfaces(host: str) -> tuple[Any, Any]:
    """ur-rtde's control and receive interfaces to ``host``, in their own child process."""
    for module in ("rtde_control", "rtde_receive"):
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            require(module, "robot", "--robot ur:HOST")  # raises MissingExtra naming the extra
    from brave6d.capture.ur_worker import isolated_interfaces

    return isolated_interfaces(host)


def dashboard_command(host: str, command: str, timeout_s: float = 2.0) -> str | None:
    """Send one line to the controller's dashboard server and return its answer (None if unreachable)."""
    try:
        with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as sock:
            sock.settimeout(timeout_s)
            reader = sock.makefile("rb")
            reader.readline()  # the greeting
            sock.sendall(command.encode("ascii") + b"\n")
            return reader.readline(4096).decode("utf-8", "replace").strip()
    except OSError:
        return None


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
    ``move_timeout_s``: longest a single move may take before it counts as stuck.
    ``sleep``/``monotonic`` are injectable (tests record the retry pauses).
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
        move_timeout_s: float = 120.0,
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
        self.move_timeout_s = move_timeout_s
        self.poll_interval_s = poll_interval_s
        self._tcp_offset = None if tcp_offset is None else check_rigid(tcp_offset, "tcp_offset")
        self._sleep = sleep
        self._monotonic = monotonic
        self._control: Any = None
        self._receive: Any = None
        self._last_linear = False
        self._closed = False
        #: the state stream was seen to show the pose the controller held after the last move
        self._state_current = False
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
                + self._dashboard_hint()
            )
        self._closed = False
        if self._tcp_offset is not None:
            offset = matrix_to_ur_pose(self._tcp_offset)
            if not self._call("setTcp", offset):
                raise RobotError(f"UR robot at {self.host} refused the TCP offset {_fmt(offset)}")

    def _dashboard_hint(self) -> str:
        """Why a connection may have failed, as the dashboard tells (empty when it says nothing useful)."""
        status = dashboard_command(self.host, "safetystatus", timeout_s=1.0)
        if status and "NORMAL" not in status.upper() and "could not understand" not in status:
            return f" (the controller's {status}; unlock it on the teach pendant first)"
        return ""

    def reconnect(self) -> None:
        """Open fresh interfaces (a new ur-rtde process; never ur-rtde's own reconnect, which can crash)."""
        self._drop_interfaces()
        self._connect()

    def _drop_interfaces(self) -> None:
        release = getattr(self._control, "release_client", None)
        if callable(release):
            _quietly(release)  # the child disconnects both interfaces and ends
        else:
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
        """Raise RobotError when the connection is lost, the arm is protectively stopped or the
        control program no longer runs."""
        if not (self._call("isConnected", receive=True) and self._call("isConnected")):
            raise RobotError(f"lost the connection to UR robot at {self.host} ({when})")
        stopped = self._call("isProtectiveStopped", receive=True)
        if not stopped and not self._call("isProgramRunning"):
            # the state stream may not show the reason yet; the dashboard answers now
            stopped = "PROTECTIVE_STOP" in (dashboard_command(self.host, "safetystatus", timeout_s=1.0) or "")
            if not stopped:
                raise RobotError(f"the control program on UR robot at {self.host} is not running ({when}): "
                                 "stopped on the teach pendant, or a URScript error (see the pendant's log); "
                                 "reconnect to upload it again")
        if stopped:
            raise RobotError(
                f"UR robot at {self.host} is in a protective stop ({when}); clear it on the teach pendant "
                "(or the dashboard's 'unlock protective stop') and check the workspace before continuing"
            )

    def _async_status(self) -> int:
        status = self._call("getAsyncOperationProgressEx")
        value = status if isinstance(status, int) else int(status.value())
        return value & 0xFFFFFFFF

    def _guarded_move(self, what: str, move: Callable[[], Any]) -> None:
        """Health check, start the move (asynchronous), follow it to the end, health check; stop the
        arm on any error or Ctrl-C."""
        self.check_health(f"before {what}")
        self._state_current = False
        try:
            before = (self._async_status() >> 24) & 0x7F
            ok = move()
            if ok is False:
                self.check_health(f"after {what} failed")
                raise RobotError(f"UR robot at {self.host} did not complete {what}")
            self._follow(what, before)
            self.check_health(f"after {what}")
            self._await_fresh_state()
            self._state_current = True
        except KeyboardInterrupt:
            self.stop()
            raise
        except RobotError:
            self.stop()
            raise
        except Exception as exc:  # noqa: BLE001
            self.stop()
            raise RobotError(f"UR robot at {self.host}: {what} failed: {exc}") from None

    def _follow(self, what: str, op_before: int) -> None:
        """Poll until the asynchronous move started after ``op_before`` has finished (health-checked)."""
        deadline = self._monotonic() + self.move_timeout_s
        started = False
        while True:
            status = self._async_status()
            started = started or ((status >> 24) & 0x7F) != op_before
            if started and not status & _ASYNC_RUNNING:
                return
            self.check_health(f"during {what}")
            if self._monotonic() > deadline:
                raise RobotError(f"UR robot at {self.host} did not finish {what} within {self.move_timeout_s:.0f} s")
            self._sleep(self.poll_interval_s)

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
                lambda: self._control.moveL(pose, self.spec.linear_speed, self.spec.linear_acceleration, True),
            )
            return
        q = self._ik(pose, self.joints())
        if q is None:
            raise RobotError(f"target pose {_fmt(pose)} has no inverse-kinematics solution on the controller")
        self._guarded_move(
            f"moveJ to {_fmt(pose)}",
            lambda: self._control.moveJ(q.tolist(), self.spec.joint_speed, self.spec.joint_acceleration, True),
        )

    def move_joints(self, joints: NDArray[np.float64]) -> None:
        """moveJ to joint angles (radians)."""
        q = np.asarray(joints, dtype=np.float64).reshape(-1)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise RobotError(f"move_joints needs 6 finite joint angles, got {np.asarray(joints).tolist()}")
        self._last_linear = False
        self._guarded_move(
            f"moveJ to joints {_fmt(q.tolist())}",
            lambda: self._control.moveJ(q.tolist(), self.spec.joint_speed, self.spec.joint_acceleration, True),
        )

    def stop(self) -> None:
        """Decelerate to a stop (stopL after a linear move, else stopJ); when ur-rtde cannot send it
        (its process died, the connection dropped), stop the program through the dashboard. Never raises."""
        if self._control is None:
            return
        try:
            if self._last_linear:
                self._control.stopL(10.0 * self.spec.linear_acceleration, False)
            else:
                self._control.stopJ(2.0 * self.spec.joint_acceleration, False)
            # the stop reached the arm only through a connected, running control script
            if self._control.isConnected() and self._control.isProgramRunning():
                return
            if self._receive is not None and self._receive.isProtectiveStopped():
                return  # the safety system has stopped the arm already
        except Exception:  # noqa: BLE001 - any failure: the dashboard below
            pass
        answer = dashboard_command(self.host, "stop")
        log.info("UR robot at %s: ur-rtde could not stop the arm; the dashboard's stop answered %r",
                    self.host, answer)

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
            if not self._state_current:  # already checked when the last move ended
                self._await_fresh_state()
                self._state_current = True
            if settle_time_s > 0:
                self._sleep(settle_time_s)
        except KeyboardInterrupt:
            self.stop()
            raise
        except RobotError:
            self.stop()
            raise

    def _await_fresh_state(self) -> None:
        """Wait until the state stream (the receive interface, which tcp_pose and joints read) shows the
        pose the controller holds now. The two interfaces are separate connections: on a loaded PC the
        state stream can lag the command stream by a second, and a pose recorded from it would be the
        pose before the move."""
        try:
            fresh = ur_pose_to_matrix(self._call("getForwardKinematics"))  # answered by the controller, now
        except ValueError:
            raise RobotError(f"UR robot at {self.host} did not answer get_forward_kin() with a pose") from None
        deadline = self._monotonic() + self.steady_timeout_s
        while True:
            reported = self.tcp_pose()
            if float(np.max(np.abs(reported - fresh))) < FRESH_POSE_TOLERANCE:
                return
            if self._monotonic() > deadline:
                raise RobotError(f"UR robot at {self.host}: the state stream still reports "
                                 f"{_fmt(matrix_to_ur_pose(reported))} {self.steady_timeout_s:.0f} s after the arm "
                                 f"came to rest at {_fmt(matrix_to_ur_pose(fresh))} (is this PC overloaded?)")
            self._sleep(self.poll_interval_s)

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

"""The emulated UR controller: arm, safety system, program state and ur-rtde's control script loop.

What a real e-Series controller does for a ur-rtde client, in one object that the network servers
(:mod:`.servers`) drive:

* the **control script** ur-rtde uploads runs as the script's own main loop does: each cycle it
  reads ``input_int_register_0``; 0 means idle (``output_int_register_0 = 1``, ready), a new
  command is executed once and answered ``2`` (done) when it finishes; a synchronous move keeps
  the loop busy until the arm arrives, an asynchronous one runs beside it and reports through
  ``output_int_register_2`` (running bit, operation id, change count);
* the **arm**: moves in real time (scaled by ``time_scale``) with the UR kinematics of
  :mod:`brave6d.capture.kinematics`, the TCP offset, IK closest to ``qnear``; ``is_steady``;
* the **safety system**: ``is_within_safety_limits`` (reachable and the TCP inside the configured
  safety box); a move that would take the TCP out of the box, an injected fault or
  ``protective_stop()`` brakes the arm and pauses the program (``safety_status_bits`` bit 2); it
  can be unlocked from the dashboard no sooner than ``unlock_delay_s`` after it happened; a new
  program does not start while the arm is protectively stopped;
* **program state** (``runtime_state``: 1 stopped, 2 playing, 4 paused) and what the pendant
  does (stop, remote/local control).

Every command, stop and fault is written to the event log with the controller time. A URScript
runtime error (no IK solution for ``get_inverse_kin``, a path that cannot be followed, a command
this emulator does not execute) stops the program, as on a real controller, and names the cause.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.core.spec import RobotPoseError
from brave6d.core.transforms import invert, matrix_to_ur_pose, ur_pose_to_matrix
from brave6d.capture.kinematics import UR_DH, URKinematics
from brave6d.capture.ur_emulator import rtde_protocol as rtde
from brave6d.capture.ur_emulator.commands import (
    COMMANDS, DONE, NO_CMD, READY, REALTIME, STOP_SCRIPT, check_against_script, is_control_script)
from brave6d.capture.ur_emulator.faults import Fault, parse_fault
from brave6d.capture.ur_emulator.motion import Motion, Move, PathError

Array = NDArray[np.float64]

# runtime_state, robot_mode, safety_mode (UR's numbering)
STOPPED, PLAYING, PAUSED = 1, 2, 4
RUNTIME_NAMES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING"}
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 1, 3
SAFETY_NAMES = {1: "NORMAL", 3: "PROTECTIVE_STOP"}
JOINT_MODE_RUNNING = 253
#: Deceleration of a protective stop (rad/s^2 of the leading joint; stop category 1 brakes hard).
PSTOP_DECELERATION = 15.0
#: Deceleration when the program is stopped from the pendant or the dashboard.
PROGRAM_STOP_DECELERATION = 4.0
#: How long (wall-clock s) RTDE refuses connections after a 'drop' fault: a network outage, not a blip.
DROP_OUTAGE_S = 3.0
#: After the arm comes to rest, is_steady() waits this long (controller s) before answering True.
STEADY_AFTER_S = 0.008


@dataclass(frozen=True)
class ControllerConfig:
    """What the emulated controller is: model, start joints, safety box, versions, faults."""

    model: str = "ur5e"
    home_joints: tuple[float, ...] = tuple(np.deg2rad([0.0, -90.0, 90.0, -90.0, -90.0, 0.0]).tolist())
    #: controller seconds per wall-clock second (10: moves take a tenth of their real time)
    time_scale: float = 1.0
    #: the TCP must stay inside this box (base frame, metres): (lo, hi); None: reach only
    safety_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    controller_version: tuple[int, int, int, int] = (5, 11, 1, 108318)
    serial_number: str = "20235500001"
    pose_error: RobotPoseError | None = None
    #: the controller reports the state of this many seconds ago (the scene's time_offset effect)
    report_delay_s: float = 0.0
    seed: int = 0
    faults: tuple[Fault, ...] = ()
    unlock_delay_s: float = 5.0

    def __post_init__(self) -> None:
        if self.model not in UR_DH:
            raise BraveError(f"--model {self.model!r}: expected one of {', '.join(sorted(UR_DH))}")
        if not (0.01 <= self.time_scale <= 1000.0):
            raise BraveError(f"--time-scale {self.time_scale!r}: expected 0.01..1000")
        if len(self.home_joints) != 6 or not np.all(np.isfinite(self.home_joints)):
            raise BraveError("the start joints must be 6 finite angles")
        if not self.serial_number.isdigit():
            raise BraveError(f"serial number {self.serial_number!r}: a UR controller's is all digits")

    @property
    def polyscope_version(self) -> str:
        return ".".join(str(v) for v in self.controller_version)


@dataclass(frozen=True)
class Event:
    """One line of the event log: its running number, the controller time and what happened."""

    seq: int
    t: float
    text: str


@dataclass
class _Busy:
    """The script loop is blocked: in a synchronous move (``move``) or answering slowly (``until``)."""

    move: Move | None = None
    until_wall: float | None = None
    cmd: int = 0
    #: the synchronous move's target, to go on with after a pause (dashboard 'play')
    resume: Callable[[float], Move] | None = None


@dataclass
class _Hooks:
    """What the network side lets the controller do to it."""

    #: close every RTDE connection and refuse new ones for the given wall-clock seconds; returns how many closed
    drop_rtde: Callable[[float], int] = lambda seconds: 0


class Controller:
    """One emulated controller; every public method takes the lock (servers call from many threads)."""

    def __init__(self, config: ControllerConfig, *, wall: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self.lock = threading.RLock()
        self._wall = wall
        self._wall0 = wall()
        self.tcp_offset = np.eye(4)
        self.kin = URKinematics(config.model)
        self.motion = Motion(self.kin, np.asarray(config.home_joints), pose_error=config.pose_error,
                             seed=config.seed)
        self.events: deque[Event] = deque(maxlen=20000)
        self._seq = 0
        #: called with every new event (the command prints them); None: kept in :attr:`events` only
        self.on_event: Callable[[Event], None] | None = None
        self.hooks = _Hooks()
        self.runtime_state = STOPPED
        self.safety_mode = SAFETY_NORMAL
        self.pstop_time: float | None = None
        self.remote_control = not any(f.kind == "remote-off" for f in config.faults)
        self.slow_s = sum(f.seconds for f in config.faults if f.kind == "slow")
        self.refuse_left = sum(f.count for f in config.faults if f.kind == "refuse")
        self._pending: list[Fault] = [f for f in config.faults if f.kind in ("pstop", "drop", "program-stop")]
        self._scheduled: list[tuple[float, Fault]] = []
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self._executing = False
        self._busy: _Busy | None = None
        self._async_move: Move | None = None
        self._async_wr_count = 0
        self._async_op_id = 0
        self._stop_type = 0
        self._watchdog_hz: float | None = None
        self._last_cmd_input_wall = wall()
        self.script: str | None = None
        self.scripts_received = 0
        self.commands_executed = 0
        self.snapshot: dict[str, Any] = {}
        self._tcp_cache: tuple[Any, list[float]] = (None, [])
        self._update_snapshot(self.now())

    # ------------------------------------------------------------------ time and log
    def now(self) -> float:
        """Controller time (s since start), ``time_scale`` times the wall clock."""
        return (self._wall() - self._wall0) * self.config.time_scale

    def event(self, text: str) -> None:
        with self.lock:
            t = self.now()
            self._seq += 1
            item = Event(self._seq, t, text)
            self.events.append(item)
        if self.on_event is not None:
            self.on_event(item)

    def events_since(self, seq: int) -> list[Event]:
        """Log lines numbered above ``seq`` (the oldest may have been dropped: 20000 are kept)."""
        with self.lock:
            return [e for e in self.events if e.seq > seq]

    # ------------------------------------------------------------------ inputs from RTDE
    def write_inputs(self, values: dict[str, Any]) -> None:
        """Apply a client's data package (register values by name)."""
        with self.lock:
            for name, value in values.items():
                if name.startswith("input_int_register_"):
                    self.in_int[int(name.rsplit("_", 1)[1])] = int(value)
                    if name == "input_int_register_0":
                        self._last_cmd_input_wall = self._wall()
                elif name.startswith("input_double_register_"):
                    self.in_double[int(name.rsplit("_", 1)[1])] = float(value)

    # ------------------------------------------------------------------ the cycle
    def tick(self) -> dict[str, Any]:
        """One controller cycle: faults, safety, the script loop; returns the output snapshot."""
        with self.lock:
            t = self.now()
            self._fire_faults(t)
            if self.runtime_state == PLAYING and self.safety_mode == SAFETY_NORMAL:
                self._check_watchdog(t)
            if self.runtime_state == PLAYING and self.safety_mode == SAFETY_NORMAL:
                self._script_cycle(t)
            self._update_snapshot(t)
            return self.snapshot

    def _script_cycle(self, t: float) -> None:
        if self._async_move is not None and t >= self._async_move.t1:
            self._async_move = None
            self._write_async(-1)
        busy = self._busy
        if busy is not None:
            if busy.move is not None and t < busy.move.t1:
                return
            if busy.move is not None and self.slow_s > 0 and busy.until_wall is None:
                busy.move, busy.until_wall = None, self._wall() + self.slow_s
            if busy.until_wall is not None and self._wall() < busy.until_wall:
                return
            self._busy = None
            self._finish(busy.cmd)
            return
        cmd = self.in_int[0]
        if cmd in REALTIME:
            self._runtime_error(f"command {cmd} (a real-time command) is not emulated")
        elif cmd == NO_CMD:
            self._executing = False
            self.out_int[0] = READY
        elif not self._executing:
            self._executing = True
            self._process(cmd, t)

    def _finish(self, cmd: int) -> None:
        if cmd != STOP_SCRIPT and self.runtime_state == PLAYING:
            self.out_int[0] = DONE

    def _process(self, cmd: int, t: float) -> None:
        entry = COMMANDS.get(cmd)
        if entry is None:
            self._runtime_error(f"command {cmd} is not emulated (only {sorted(COMMANDS)})")
            return
        self.commands_executed += 1
        try:
            blocking = self._execute(cmd, t)
        except PathError as exc:
            self._runtime_error(str(exc))
            return
        if blocking is not None:
            self._busy = blocking
        elif self.slow_s > 0 and cmd != STOP_SCRIPT:
            self._busy = _Busy(until_wall=self._wall() + self.slow_s, cmd=cmd)
        else:
            self._finish(cmd)

    # ------------------------------------------------------------------ commands
    def _pose(self, first: int = 0) -> Array:
        return ur_pose_to_matrix(self.in_double[first:first + 6])

    def _q(self, first: int = 0) -> Array:
        return np.asarray(self.in_double[first:first + 6], dtype=np.float64)

    def _fmt(self, values: Sequence[float]) -> str:
        return "[" + ", ".join(f"{v:.4f}" for v in values) + "]"

    def _execute(self, cmd: int, t: float) -> _Busy | None:
        d, i = self.in_double, self.in_int
        name = COMMANDS[cmd].method
        if cmd in (1, 2, 3, 4):
            speed, acc, asynchronous = d[6], d[7], i[1] == 1
            if cmd in (1, 4):
                target = self._q()
                self.event(f"cmd {cmd} {name} q={self._fmt(target)} v={speed:.3f} a={acc:.3f} "
                           f"async={int(asynchronous)}")
            else:
                target_pose = self._pose()
                self.event(f"cmd {cmd} {name} pose={self._fmt(d[:6])} v={speed:.3f} a={acc:.3f} "
                           f"async={int(asynchronous)}")
            if cmd == 2:
                q_ik = self._ik(target_pose, self.current_q(t))
                if q_ik is None:
                    raise PathError(f"{name}: get_inverse_kin() found no solution for {self._fmt(d[:6])}")
                target = q_ik
            self._stop_async_move(t)

            def start(at: float) -> Move:
                if cmd in (1, 2):
                    move = self.motion.movej(at, target, speed, acc, kind="movej")
                else:
                    goal = target_pose if cmd == 3 else self.kin.fk(target)
                    move = self.motion.movel(at, goal, speed, acc, kind="movel")
                self._schedule_for(move)
                return move

            move = start(t)
            if asynchronous:
                self._async_move = move
                self._write_async(0)
                return None
            return _Busy(move=move, cmd=cmd, resume=start)
        if cmd == 29:
            pose = d[:6]
            self.tcp_offset = ur_pose_to_matrix(pose)
            self.kin = URKinematics(self.config.model, flange_T_tcp=self.tcp_offset)
            self.motion.kin = self.kin
            self.event(f"cmd 29 setTcp {self._fmt(pose)}")
        elif cmd in (30, 46):
            pose = self._pose()
            near = self._q(6) if cmd == 30 else self.current_q(t)
            q = self._ik(pose, near)
            self.event(f"cmd {cmd} {name} pose={self._fmt(d[:6])} -> {'none' if q is None else self._fmt(q)}")
            if q is None:
                raise PathError(f"get_inverse_kin(): no solution for {self._fmt(d[:6])}")
            self.out_double[0:6] = [float(v) for v in q]
        elif cmd in (60, 61):
            pose = self._pose()
            near = self._q(6) if cmd == 61 else self.current_q(t)
            ok = self._ik(pose, near) is not None
            self.out_int[1] = int(ok)
            self.event(f"cmd {cmd} {name} pose={self._fmt(d[:6])} -> {ok}")
        elif cmd == 36:
            ok = self.pose_within_safety_limits(self._pose())
            self.out_int[1] = int(ok)
            self.event(f"cmd 36 {name} pose={self._fmt(d[:6])} -> {ok}")
        elif cmd == 37:
            q = self._q()
            ok = self.kin.within_limits(q) and self._inside_box(self.kin.fk(q))
            self.out_int[1] = int(ok)
            self.event(f"cmd 37 {name} q={self._fmt(q)} -> {ok}")
        elif cmd == 40:
            self.out_double[0:6] = matrix_to_ur_pose(self.tcp_offset)
            self.event("cmd 40 getTCPOffset")
        elif cmd in (43, 44):
            if cmd == 43:
                T = self.kin.fk(self.current_q(t))
            else:
                T = URKinematics(self.config.model, flange_T_tcp=self._pose(6)).fk(self._q())
            self.out_double[0:6] = matrix_to_ur_pose(T)
            self.event(f"cmd {cmd} {name}")
        elif cmd == 47:
            steady = self.is_steady(t)
            self.out_int[1] = int(steady)
            self.event(f"cmd 47 isSteady -> {steady}")
        elif cmd in (33, 34):
            dec, asynchronous = d[0], i[1] == 1
            self.event(f"cmd {cmd} {name} a={dec:.3f} async={int(asynchronous)}")
            self._stop_async_move(t)
            # the script's quirk, kept: a synchronous stop uses stop_type, which only an async stop sets
            kind = "stopl" if (self._stop_type == 1) else "stopj"
            if asynchronous:
                self._stop_type = 1
            braking = self.motion.stop(t, max(dec, 1e-3))
            if braking is not None:
                self.event(f"arm braking ({kind}, a={dec:.3f}) until t={braking.t1:.3f}")
            if braking is not None and not asynchronous:
                return _Busy(move=braking, cmd=cmd)
        elif cmd == 31:
            self.event("cmd 31 triggerProtectiveStop")
            self.protective_stop("protective_stop() called by the program")
        elif cmd == 35:
            self._watchdog_hz = d[0] if d[0] > 0 else None
            self.event(f"cmd 35 setWatchdog min_frequency={d[0]:.3f} Hz")
        elif cmd == STOP_SCRIPT:
            self.event("cmd 255 stopScript: the control script ends")
            self._end_program(STOPPED, "stopScript")
        return None

    def _ik(self, pose: Array, near: Array) -> Array | None:
        try:
            res = self.kin.ik(pose, near)
        except ValueError:
            return None
        return res.solutions[0].copy() if res.reachable else None

    def _stop_async_move(self, t: float) -> None:
        if self._async_move is not None:
            if t < self._async_move.t1:
                self.event("async move thread killed")
            self._async_move = None
            self._write_async(-1)

    def _write_async(self, value: int) -> None:
        """The script's write_async_progress_register: change count, operation id, running bit, progress."""
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        reg = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.out_int[2] = reg

    # ------------------------------------------------------------------ state
    def current_q(self, t: float | None = None) -> Array:
        with self.lock:
            return self.motion.state(self.now() if t is None else t)[0]

    def is_steady(self, t: float) -> bool:
        move = self.motion.current()
        return move is None or t >= move.t1 + STEADY_AFTER_S

    def _inside_box(self, T: Array) -> bool:
        box = self.config.safety_box
        if box is None:
            return True
        p = T[:3, 3]
        return bool(np.all(p >= np.asarray(box[0])) and np.all(p <= np.asarray(box[1])))

    def pose_within_safety_limits(self, pose: Array) -> bool:
        """is_within_safety_limits(pose): reachable (an IK solution) and the TCP inside the safety box."""
        with self.lock:
            if not self._inside_box(pose):
                return False
            return self._ik(pose, self.current_q()) is not None

    def true_base_T_flange(self, t: float | None = None) -> Array:
        """Where the flange ACTUALLY is at controller time ``t`` (what a camera on it sees)."""
        with self.lock:
            tt = self.now() if t is None else float(t)
            q, E, _ = self.motion.state(tt)
            return self.kin.fk_flange(q) @ self.tcp_offset @ E @ invert(self.tcp_offset)

    # ------------------------------------------------------------------ program and safety
    def start_program(self, script: str) -> None:
        """A script arrived on port 30003: run it (ur-rtde's control script only)."""
        with self.lock:
            self.scripts_received += 1
            if not is_control_script(script):
                self.event(f"script of {len(script)} bytes ignored: only ur-rtde's control script is emulated")
                return
            self.script = script
            problems = check_against_script(script)
            if problems:
                self.event(f"script refused: its commands differ from the emulator's ({len(problems)}: "
                           f"{problems[0]}); this emulator follows ur-rtde 1.6.5")
                return
            if self.safety_mode != SAFETY_NORMAL:
                self.event("script refused: the arm is in a protective stop (unlock it first)")
                return
            if self.runtime_state != STOPPED:
                self._end_program(STOPPED, "a new program replaces the running one")
            t = self.now()
            self.runtime_state = PLAYING
            self._executing = False
            self._busy = None
            self._stop_type = 0
            self._async_move = None
            self._write_async(-1)  # reset_async_progress()
            self.out_int[0] = READY
            self._last_cmd_input_wall = self._wall()
            self.event(f"control script started ({len(script)} bytes)")
            self._update_snapshot(t)

    def _end_program(self, state: int, why: str, deceleration: float = PROGRAM_STOP_DECELERATION) -> None:
        t = self.now()
        braking = self.motion.stop(t, deceleration)
        if braking is not None:
            self.event(f"arm braking (program {RUNTIME_NAMES[state].lower()}, a={deceleration:g}) "
                       f"until t={braking.t1:.3f}")
        if state == STOPPED:
            self._busy = None
            self._async_move = None
            self._watchdog_hz = None
        self.runtime_state = state
        self.event(f"program {RUNTIME_NAMES[state]}: {why}")

    def _runtime_error(self, why: str) -> None:
        self.event(f"URScript runtime error, program stopped: {why}")
        self._end_program(STOPPED, why)

    def stop_program(self, why: str = "stopped from the teach pendant") -> bool:
        """The pendant's (or dashboard's) stop; False when no program was running."""
        with self.lock:
            if self.runtime_state == STOPPED:
                return False
            self._end_program(STOPPED, why)
            return True

    def play(self) -> str:
        """The dashboard's play: resume a paused program (refused during a protective stop)."""
        with self.lock:
            if self.safety_mode != SAFETY_NORMAL:
                return "Failed to execute: play"
            if self.runtime_state == PAUSED:
                t = self.now()
                self.runtime_state = PLAYING
                if self._busy is not None and self._busy.resume is not None:
                    self._busy.move = self._busy.resume(t)
                self.event("program resumed (play)")
                return "Starting program"
            if self.runtime_state == PLAYING:
                return "Starting program"
            return "Failed to execute: play"

    def protective_stop(self, why: str) -> None:
        with self.lock:
            if self.safety_mode == SAFETY_PROTECTIVE_STOP:
                return
            t = self.now()
            self.safety_mode = SAFETY_PROTECTIVE_STOP
            self.pstop_time = t
            self.event(f"PROTECTIVE STOP: {why}")
            braking = self.motion.stop(t, PSTOP_DECELERATION)
            if braking is not None:
                self.event(f"arm braking (protective stop) until t={braking.t1:.3f}")
            if self.runtime_state == PLAYING:
                self.runtime_state = PAUSED
                self.event("program PAUSED by the protective stop")

    def unlock_protective_stop(self) -> str:
        with self.lock:
            if self.safety_mode != SAFETY_PROTECTIVE_STOP:
                return "Protective stop releasing"
            waited = self.now() - (self.pstop_time or 0.0)
            if waited < self.config.unlock_delay_s:
                return ("Cannot unlock protective stop until 5s after occurrence. Always inspect cause of "
                        "protective stop before unlocking")
            self.safety_mode = SAFETY_NORMAL
            self.event("protective stop unlocked")
            return "Protective stop releasing"

    def _check_watchdog(self, t: float) -> None:
        if self._watchdog_hz and self._wall() - self._last_cmd_input_wall > 1.0 / self._watchdog_hz:
            self.event(f"RTDE watchdog: no input for more than {1.0 / self._watchdog_hz:.3f} s")
            self._end_program(STOPPED, "RTDE watchdog")

    # ------------------------------------------------------------------ faults
    def _schedule_for(self, move: Move) -> None:
        """Plan this move's faults: move-numbered ones half way, region ones where the path enters
        the region, and the safety box where the path would leave it."""
        n = self.motion.count
        for fault in list(self._pending):
            when = None
            if fault.at_move == n:
                when = move.t0 + 0.5 * (move.t1 - move.t0)
            elif fault.box is not None:
                when = self.motion.first_time_inside(move, self.kin.fk, np.asarray(fault.box[0]),
                                                     np.asarray(fault.box[1]))
            if when is not None:
                self._pending.remove(fault)
                self._scheduled.append((when, fault))
        box = self.config.safety_box
        if box is not None:
            leaves = self.motion.first_time_inside(move, self.kin.fk, np.asarray(box[0]), np.asarray(box[1]),
                                                   inside=False)
            if leaves is not None:
                self._scheduled.append((leaves, Fault("pstop", box=None, seconds=-1.0)))

    def _fire_faults(self, t: float) -> None:
        for fault in list(self._pending):
            if fault.at_time is not None and t >= fault.at_time:
                self._pending.remove(fault)
                self._scheduled.append((t, fault))
        for when, fault in sorted(self._scheduled, key=lambda x: x[0]):
            if t < when:
                continue
            self._scheduled.remove((when, fault))
            if fault.kind == "pstop" and fault.seconds < 0:
                self.protective_stop("safety limit: the TCP would leave the safety box")
            elif fault.kind == "pstop":
                self.protective_stop(f"injected fault {fault}")
            elif fault.kind == "program-stop":
                self.event(f"injected fault {fault}")
                self.stop_program("stopped from the teach pendant (injected fault)")
            elif fault.kind == "drop":
                dropped = self.hooks.drop_rtde(DROP_OUTAGE_S)
                self.event(f"injected fault {fault}: dropped {dropped} RTDE connection(s); RTDE refuses "
                           f"connections for {DROP_OUTAGE_S:g} s")

    def inject(self, text: str) -> None:
        """A fault while the emulator runs (the side channel's ``fault`` request): ``pstop``, ``drop`` or
        ``program-stop`` now, any ``--fault`` text (``pstop@move=N`` counts moves since the start), or
        ``remote-on`` / ``slow=0`` / ``refuse=0`` to undo a standing one."""
        with self.lock:
            if text in ("pstop", "drop", "program-stop"):
                self._scheduled.append((self.now(), Fault(text)))
            elif text == "remote-on":
                self.remote_control = True
            else:
                fault = parse_fault(text)
                if fault.kind == "remote-off":
                    self.remote_control = False
                elif fault.kind == "slow":
                    self.slow_s = fault.seconds
                elif fault.kind == "refuse":
                    self.refuse_left = fault.count
                else:
                    self._pending.append(fault)
            self.event(f"fault injected over the side channel: {text}")

    def take_refusal(self) -> bool:
        """True (and one fewer left) while the refuse=N fault still has connections to refuse."""
        with self.lock:
            if self.refuse_left > 0:
                self.refuse_left -= 1
                return True
            return False

    # ------------------------------------------------------------------ outputs
    def _update_snapshot(self, t: float) -> None:
        tr = max(0.0, t - self.config.report_delay_s)
        q, _, _ = self.motion.state(tr)
        moving = self.motion.moving(tr)
        if moving:
            q_prev, _, _ = self.motion.state(max(0.0, tr - 0.002))
            qd = (q - q_prev) / 0.002
        else:
            qd = np.zeros(6)
        key = (tuple(q.tolist()), id(self.kin))
        if key != self._tcp_cache[0]:  # forward kinematics only when the arm or the TCP changed
            self._tcp_cache = (key, matrix_to_ur_pose(self.kin.fk(q)))
        tcp = self._tcp_cache[1]
        pstop = self.safety_mode == SAFETY_PROTECTIVE_STOP
        snap: dict[str, Any] = {
            "timestamp": t, "actual_q": q.tolist(), "target_q": q.tolist(), "actual_qd": qd.tolist(),
            "target_qd": qd.tolist(), "actual_TCP_pose": tcp, "target_TCP_pose": tcp,
            "robot_mode": ROBOT_MODE_RUNNING, "joint_mode": [JOINT_MODE_RUNNING] * 6,
            "safety_mode": self.safety_mode, "safety_status": self.safety_mode,
            "runtime_state": self.runtime_state,
            "robot_status_bits": 1 | (2 if self.runtime_state == PLAYING else 0),
            "safety_status_bits": (1 << 2) if pstop else 1,
            "speed_scaling": 1.0, "target_speed_fraction": 1.0, "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0, "joint_temperatures": [30.0] * 6, "actual_execution_time": 0.2,
        }
        snap["output_int_register_"] = list(self.out_int)
        snap["output_double_register_"] = list(self.out_double)
        self.snapshot = snap

    @staticmethod
    def value_for(snapshot: dict[str, Any], name: str) -> Any:
        """A snapshot's value of ``name``, or the type's zero for variables the emulator does not model."""
        if name in snapshot:
            return snapshot[name]
        if name.startswith(("output_int_register_", "output_double_register_")):
            prefix, _, index = name.rpartition("_")
            return snapshot[prefix + "_"][int(index)]
        typ = rtde.OUTPUT_TYPES[name]
        count = int(rtde.TYPE_FORMATS[typ][:-1]) if len(rtde.TYPE_FORMATS[typ]) > 1 else 1
        zero: Any = 0.0 if typ in ("DOUBLE", "VECTOR3D", "VECTOR6D") else 0
        return zero if count == 1 else [zero] * count

    def status(self) -> dict[str, Any]:
        """A summary for the side channel and the tests."""
        with self.lock:
            t = self.now()
            return {"t": t, "model": self.config.model, "runtime_state": self.runtime_state,
                    "safety_mode": SAFETY_NAMES.get(self.safety_mode),
                    "q": self.current_q(t).tolist(), "moves": self.motion.count, "moving": self.motion.moving(t),
                    "scripts_received": self.scripts_received, "commands_executed": self.commands_executed,
                    "remote_control": self.remote_control, "tcp_offset": matrix_to_ur_pose(self.tcp_offset)}

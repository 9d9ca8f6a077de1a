"""The lab robot through its real client: ur-rtde (the installed wheel, unmodified, in its worker
process) drives ``brave6d ur-emulator`` processes on loopback addresses.

Covers connect and retry, moves, TCP offset, safety refusal, IK without a solution, a protective
stop in the middle of a ring (stop, unlock, resume: every view once), a dropped connection during a
move (one error line, exit 2, resumable), a crashed or wedged client, Ctrl-C during a move (the
emulator's log shows the stop), the program stopped from the pendant, remote control off, two
emulators side by side, hypothesis over poses near singularities and out of reach, and that the
emulator refuses malformed RTDE and that its command table matches the script the client uploads.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.spec import RobotSpec
from brave6d.core.transforms import make_transform, matrix_to_ur_pose, ur_pose_to_matrix
from brave6d.capture.kinematics import URKinematics
from brave6d.capture.protocols import RobotError
from brave6d.capture.ur_emulator import COMMANDS, check_against_script
from brave6d.capture.ur_emulator import rtde_protocol as rtde
from brave6d.capture.ur_emulator.commands import ScriptCommand
from brave6d.capture.ur_robot import URRobot, dashboard_command
from brave6d.capture.ur_worker import RobotClientError, RTDEWorker, isolated_interfaces

from capture_helpers import small_scene
from ur_emulator_helpers import Emulator, emulator, start_emulator

pytest.importorskip("rtde_control")
pytestmark = pytest.mark.slow

Q_A = np.array([0.2, -1.2, 1.5, -1.8, -1.5, 0.3])
Q_B = np.array([-0.4, -1.6, 1.1, -1.2, -1.7, -0.5])
KIN = URKinematics("ur5e")
#: the module emulator's safety box: the TCP must stay above z = 0.05 m
SAFETY_BOX = "-2,-2,0.05,2,2,2"


@pytest.fixture(autouse=True)
def _worker_logs_in_tmp_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The logs ur-rtde's failed processes leave (on purpose, for the user) stay in the test's folder."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))


@pytest.fixture(scope="module")
def emu(tmp_path_factory: pytest.TempPathFactory) -> Emulator:
    e = start_emulator(tmp_path_factory.mktemp("emulator"), f"--safety-box={SAFETY_BOX}")
    yield e
    e.stop()


@pytest.fixture(scope="module")
def robot(emu: Emulator) -> URRobot:
    r = URRobot(emu.address, RobotSpec())
    yield r
    r.close()


def _target(dx: float = 0.05) -> np.ndarray:
    T = KIN.fk(Q_A)
    T[:3, 3] += [dx, 0.02, -0.03]
    return T


# ============================================================================ moves, TCP, safety, IK
def test_connects_moves_and_reports_what_the_controller_holds(emu: Emulator, robot: URRobot) -> None:
    t0 = robot.now()
    robot.move_joints(Q_A)
    np.testing.assert_allclose(robot.joints(), Q_A, atol=1e-12)
    np.testing.assert_allclose(emu.link.status()["q"], Q_A, atol=1e-12)
    T = _target()
    robot.move_to(T, linear=True)
    np.testing.assert_allclose(robot.tcp_pose(), T, atol=1e-9)
    T2 = T.copy()
    T2[:3, 3] += [0.0, 0.04, 0.0]
    robot.move_to(T2)
    np.testing.assert_allclose(robot.tcp_pose(), T2, atol=1e-9)
    robot.wait_until_steady(0.0)
    assert robot.now() > t0
    q = robot.inverse_kinematics(T, Q_A)
    assert q is not None and np.allclose(KIN.fk(q), T, atol=1e-9)
    events = emu.events()
    assert any(e.startswith("cmd 29 setTcp [0.0000, 0.0000, 0.0000") for e in events)  # TCP = flange at connect
    # every move goes out asynchronously (so that a stop can reach the arm) with the spec's speeds
    moves = [e for e in events if e.startswith(("cmd 1 moveJ", "cmd 3 moveL"))]
    assert moves[-3].startswith("cmd 1 moveJ") and "v=1.050 a=1.400 async=1" in moves[-3]
    assert moves[-2].startswith("cmd 3 moveL") and "v=0.250 a=1.200 async=1" in moves[-2]
    assert moves[-1].startswith("cmd 1 moveJ")
    assert any(e.startswith("cmd 47 isSteady -> True") for e in events)


def test_tcp_offset_is_set_on_the_controller(emu: Emulator, robot: URRobot) -> None:
    robot.close()  # one control client at a time: a second one would find the input registers in use
    offset = make_transform(np.eye(3), [0.0, 0.01, 0.12])
    try:
        with URRobot(emu.address, RobotSpec(), tcp_offset=offset) as r:
            assert emu.link.status()["tcp_offset"] == pytest.approx(matrix_to_ur_pose(offset), abs=1e-12)
            r.move_joints(Q_B)
            np.testing.assert_allclose(r.tcp_pose(), KIN.fk_flange(Q_B) @ offset, atol=1e-9)
            T = r.tcp_pose()
            T[:3, 3] += [0.02, 0.0, 0.0]
            r.move_to(T, linear=True)  # a linear move of the TCP, not of the flange
            np.testing.assert_allclose(r.tcp_pose(), T, atol=1e-9)
    finally:
        robot.reconnect()  # the next connection sets the flange again
    np.testing.assert_allclose(robot.tcp_pose(), KIN.fk(robot.joints()), atol=1e-9)


def test_target_outside_the_safety_box_is_refused_before_moving(emu: Emulator, robot: URRobot) -> None:
    robot.move_joints(Q_A)
    moves_before = emu.link.status()["moves"]
    T = _target()
    T[2, 3] = 0.03  # below the box's floor (z = 0.05)
    with pytest.raises(RobotError, match=r"target pose \[.*0\.0300.*outside the UR robot's safety limits"):
        robot.move_to(T)
    with pytest.raises(RobotError, match="safety limits"):
        robot.move_to(T, linear=True)
    assert robot.inverse_kinematics(T) is None
    assert emu.link.status()["moves"] == moves_before
    np.testing.assert_allclose(robot.joints(), Q_A, atol=1e-12)
    T[2, 3] = 0.08
    assert robot.inverse_kinematics(T) is not None


def test_unreachable_pose_has_no_solution_and_the_program_keeps_running(emu: Emulator, robot: URRobot) -> None:
    T = _target()
    T[:3, 3] = [1.6, 0.2, 0.4]  # beyond a UR5e's 0.85 m reach
    assert robot.inverse_kinematics(T) is None
    with pytest.raises(RobotError, match="safety limits"):  # is_within_safety_limits includes reachability
        robot.move_to(T)
    robot.move_joints(Q_B)  # nothing above stopped the control program
    np.testing.assert_allclose(robot.joints(), Q_B, atol=1e-12)
    assert emu.link.status()["runtime_state"] == 2


def test_a_linear_move_follows_a_line_and_a_joint_move_does_not(emu: Emulator, robot: URRobot) -> None:
    """moveL and moveJ end at the same pose; only their paths tell them apart (a swapped command
    table would pass every end-pose test)."""
    T_end = KIN.fk(Q_B)
    deviation = {}
    for linear in (True, False):
        robot.move_joints(Q_A)
        since = emu.link.events()[-1][0]
        robot.move_to(T_end, linear=linear)
        start = next(t for _, t, text in emu.link.events(since) if text.startswith(("cmd 1 moveJ", "cmd 3 moveL")))
        end = emu.link.now()
        p0, p1 = KIN.fk(Q_A)[:3, 3], T_end[:3, 3]
        ts = np.linspace(start, start + min(end - start, 3.0), 60)
        points = np.array([emu.link.true_base_T_flange(float(t))[:3, 3] for t in ts])
        along = (points - p0) @ (p1 - p0) / np.dot(p1 - p0, p1 - p0)
        off = points - (p0 + along[:, None] * (p1 - p0))
        deviation[linear] = float(np.max(np.linalg.norm(off, axis=1)))
    assert deviation[True] < 1e-4
    assert deviation[False] > 5e-3


@settings(max_examples=25, deadline=None)
@given(q=st.lists(st.floats(-math.pi, math.pi), min_size=6, max_size=6),
       kind=st.sampled_from(["plain", "wrist", "elbow", "shoulder", "out_of_reach", "flip"]),
       eps=st.floats(-1e-6, 1e-6))
def test_ik_answers_near_singularities_and_out_of_reach(robot: URRobot, q: list[float], kind: str,
                                                        eps: float) -> None:
    """The controller's IK (through the real client) against the kinematics: a solution reproduces
    the pose, an unreachable pose has none, nothing is NaN, the program never stops."""
    qq = np.array(q)
    if kind == "wrist":
        qq[4] = eps  # sin(q5) ~ 0: q4 and q6 turn about one axis
    elif kind == "elbow":
        qq[2] = eps  # arm stretched
    T = KIN.fk(qq)
    if kind == "shoulder":
        T[:2, 3] = 0.0  # TCP on the base axis
    elif kind == "out_of_reach":
        T[:3, 3] *= 3.0 / max(np.linalg.norm(T[:3, 3]), 1e-3)
    near = qq.copy()
    if kind == "flip":
        near[3:] += np.pi  # a seed in the other wrist configuration
        near = (near + np.pi) % (2 * np.pi) - np.pi
    answer = robot.inverse_kinematics(T, near)
    T = ur_pose_to_matrix(matrix_to_ur_pose(T))  # what the controller receives: [x, y, z, rotation vector]
    local = KIN.ik(T, near)
    in_box = T[2, 3] >= 0.05 and np.all(np.abs(T[:3, 3]) <= 2.0)
    if not (local.reachable and in_box):
        assert answer is None
    else:
        assert answer is not None and np.all(np.isfinite(answer))
        np.testing.assert_allclose(KIN.fk(answer), T, atol=1e-8)
        np.testing.assert_allclose(answer, local.solutions[0], atol=1e-9)  # the one closest to the seed
    robot.check_health("after the IK questions")  # connected, no protective stop, the program runs


# ============================================================================ the protocol itself
def test_command_table_matches_the_script_the_client_uploads(emu: Emulator, robot: URRobot) -> None:
    script = emu.link.script()
    assert script is not None and "def rtde_control():" in script and len(script) > 30000
    assert check_against_script(script) == []
    swapped = dict(COMMANDS)
    swapped[1] = ScriptCommand(1, "moveJ", COMMANDS[3].script_marker)  # moveJ answered with movel
    swapped[3] = ScriptCommand(3, "moveL", COMMANDS[1].script_marker)
    problems = check_against_script(script, swapped)
    assert len(problems) == 2 and problems[0].startswith("command 1 (moveJ)")
    assert "movel(pose" in problems[0] and 'textmsg("movej")' in problems[0]
    renumbered = {47 + 1: ScriptCommand(48, "isSteady", COMMANDS[47].script_marker)}
    assert "command 48 (isSteady)" in check_against_script(script, renumbered)[0]


class RawRTDE:
    """A minimal RTDE client of the test's own, to send what ur-rtde never would."""

    def __init__(self, address: str) -> None:
        self.sock = socket.create_connection((address, 30004), timeout=5)

    def send(self, msg_type: int, payload: bytes = b"") -> None:
        self.sock.sendall(rtde.frame(msg_type, payload))

    def recv(self) -> tuple[int, bytes]:
        size, msg_type = rtde.parse_header(self._exact(3))
        return msg_type, self._exact(size)

    def _exact(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise EOFError
            data += chunk
        return data

    def handshake(self) -> None:
        self.send(rtde.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))
        assert self.recv() == (rtde.REQUEST_PROTOCOL_VERSION, b"\x01")

    def closed_after_text(self) -> str:
        """The refusal: a text message, then the connection closes."""
        msg_type, payload = self.recv()
        assert msg_type == rtde.TEXT_MESSAGE
        text = payload[1:1 + payload[0]].decode()
        with pytest.raises((EOFError, ConnectionError)):
            while True:
                self.recv()
        return text


def test_malformed_recipes_and_packages_are_refused(emu: Emulator) -> None:
    c = RawRTDE(emu.address)
    c.handshake()
    # registers ur-rtde's control interface does not hold (it may be connected: its inputs are IN_USE)
    c.send(rtde.SETUP_INPUTS, b"input_int_register_30,no_such_variable,")
    msg_type, payload = c.recv()
    assert msg_type == rtde.SETUP_INPUTS and payload[0] == 0 and payload[1:] == b"INT32,NOT_FOUND"
    c.send(rtde.SETUP_INPUTS, b"input_int_register_30,input_double_register_30")
    assert c.recv() == (rtde.SETUP_INPUTS, b"\x01INT32,DOUBLE")
    c.send(rtde.START)
    assert c.recv() == (rtde.START, b"\x01")
    c.send(rtde.DATA_PACKAGE, b"\x01" + struct.pack(">i", 0))  # 4 bytes where the recipe needs 12
    assert "recipe 1 has 4 bytes" in c.closed_after_text()

    c = RawRTDE(emu.address)
    c.handshake()
    c.send(rtde.SETUP_INPUTS, b"input_int_register_31")
    assert c.recv()[1][0] == 1
    c.send(rtde.START)
    c.recv()
    c.send(rtde.DATA_PACKAGE, b"\x07" + struct.pack(">i", 0))
    assert "input recipe 7, which was never set up" in c.closed_after_text()

    for payload, expected in ((struct.pack(">d", 0.0) + b"timestamp", "frequency 0.0 Hz"),
                              (struct.pack(">d", 1000.0) + b"timestamp", "frequency 1000.0 Hz"),
                              (struct.pack(">d", 125.0) + "tïmestamp".encode(), "not ASCII"),
                              (struct.pack(">d", 125.0) + b",".join([b"timestamp"] * 300), "300 names")):
        c = RawRTDE(emu.address)
        c.handshake()
        c.send(rtde.SETUP_OUTPUTS, payload)
        assert expected in c.closed_after_text()
    c = RawRTDE(emu.address)  # nothing but the version request before the version is agreed
    c.send(rtde.SETUP_INPUTS, b"input_int_register_31")
    assert "before protocol version 2" in c.closed_after_text()
    refusals = [e for e in emu.events() if ": refused: " in e]
    assert len(refusals) >= 7


def test_a_second_controller_client_finds_the_inputs_in_use(emu: Emulator, robot: URRobot) -> None:
    with pytest.raises(RobotError, match="input registers are already in use"):
        URRobot(emu.address, RobotSpec(), connect_tries=1)
    robot.move_joints(Q_A)  # the first client is untouched


# ============================================================================ connection faults
@pytest.fixture(scope="module")
def faults(tmp_path_factory: pytest.TempPathFactory) -> Emulator:
    """One emulator for the fault tests: each injects its faults over the side channel and undoes them."""
    e = start_emulator(tmp_path_factory.mktemp("faults"))
    yield e
    e.stop()


def _next_move(e: Emulator, k: int = 1) -> int:
    """The number the emulator will give the k-th move from now."""
    return int(e.link.status()["moves"]) + k


def test_refused_connections_are_retried_then_given_up(faults: Emulator) -> None:
    faults.link.inject("refuse=4")
    pauses: list[float] = []
    with pytest.raises(RobotError) as err:
        URRobot(faults.address, RobotSpec(), connect_tries=3, retry_pause_s=0.05, sleep=pauses.append)
    assert str(err.value).startswith(f"Could not connect to UR robot at {faults.address} after 3 tries: ")
    assert pauses == [0.05, 0.05]
    pauses.clear()
    with URRobot(faults.address, RobotSpec(), connect_tries=3, retry_pause_s=0.05, sleep=pauses.append) as r:
        assert pauses == [0.05]  # the 4th refusal, then connected
        r.move_joints(Q_A)
    assert sum("refused (refuse fault" in x for x in faults.events()) == 4


def test_remote_control_off_is_one_clear_error(faults: Emulator) -> None:
    faults.link.inject("remote-off")
    try:
        with pytest.raises(RobotError, match="Please enable remote control on the robot") as err:
            URRobot(faults.address, RobotSpec(), connect_tries=1)
        assert "\n" not in str(err.value)
    finally:
        faults.link.inject("remote-on")


def test_program_stopped_from_the_pendant_during_a_move(faults: Emulator) -> None:
    with URRobot(faults.address, RobotSpec()) as r:
        r.move_joints(Q_A)
        faults.link.inject(f"program-stop@move={_next_move(faults)}")
        with pytest.raises(RobotError, match="control program on UR robot at .* is not running"):
            r.move_joints(Q_B)
        assert not np.allclose(r.joints(), Q_B, atol=1e-3)  # braked on the way
        r.reconnect()  # a new client uploads the program again
        r.move_joints(Q_B)
        np.testing.assert_allclose(r.joints(), Q_B, atol=1e-12)


def test_a_wedged_client_call_is_one_error(faults: Emulator) -> None:
    faults.link.inject("slow=6")
    try:
        t0 = time.monotonic()
        with pytest.raises(RobotError, match=r"ur-rtde did not answer control\.setTcp within the time allowed"):
            URRobot(faults.address, RobotSpec(), connect_tries=1,
                    interfaces_factory=lambda host: isolated_interfaces(host, call_timeout_s=1.0))
        assert time.monotonic() - t0 < 5.0
    finally:
        faults.link.inject("slow=0")
        # the program is still in that command; ur-rtde would wait for it (as on a real controller):
        # stop it, as a user would on the pendant
        assert dashboard_command(faults.address, "stop") == "Stopped"


def test_a_crashing_client_is_one_error_and_the_arm_is_stopped(faults: Emulator) -> None:
    """ur-rtde's process killed by SIGSEGV in the middle of a move (as its reconnect does)."""
    r = URRobot(faults.address, RobotSpec(joint_speed=0.02))  # 0.8 rad: 40 controller s, 2 s at 20x
    try:
        since = faults.link.events()[-1][0]
        threading.Timer(0.5, os.kill, (r._control.worker.pid, signal.SIGSEGV)).start()
        with pytest.raises(RobotError, match=r"ur-rtde's process was killed by SIGSEGV during "):
            r.move_joints(faults.link.status()["q"] + np.array([0.8, 0, 0, 0, 0, 0]))
        texts = [x for _, _, x in faults.link.events(since)]
        assert "dashboard: 'stop'" in texts and any(x.startswith("program STOPPED") for x in texts)
        time.sleep(0.3)
        assert not faults.link.status()["moving"]
        r.reconnect()
        r.move_joints(Q_A)
    finally:
        r.close()


def test_ctrl_c_during_a_move_stops_the_arm(faults: Emulator) -> None:
    script = textwrap.dedent(f"""
        import numpy as np, sys
        from brave6d.core.spec import RobotSpec
        from brave6d.capture.ur_robot import URRobot
        r = URRobot({faults.address!r}, RobotSpec(joint_speed=0.01, linear_speed=0.002))
        r.move_joints(np.array({Q_A.tolist()}))
        print("moving", flush=True)
        try:
            r.move_joints(np.array({(Q_A + 1.2).tolist()}))  # 120 controller s, 6 s at 20x
        except KeyboardInterrupt:
            print("interrupted", flush=True)
        T = r.tcp_pose()
        T[2, 3] += 0.15  # 75 controller s at 2 mm/s
        print("moving linearly", flush=True)
        try:
            r.move_to(T, linear=True)
        except KeyboardInterrupt:
            print("interrupted", flush=True)
            r.close()
            sys.exit(130)
    """)
    events = faults.link.events()
    since = events[-1][0] if events else 0  # the test run alone: the emulator has logged nothing yet
    # SIGINT at its default, as in a terminal: a test run started in the background of a non-interactive
    # shell (as CI may be) has it ignored, and a child inherits that, so Python would install no handler
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                            start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert proc.stdout is not None
    for expected in ("moving", "interrupted", "moving linearly"):
        if expected == "interrupted":
            time.sleep(1.0)
            os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does to the capture's process group
        assert proc.stdout.readline().strip() == expected
    time.sleep(1.0)
    os.killpg(proc.pid, signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in out
    texts = [x for _, _, x in faults.link.events(since)]
    movej = max(i for i, x in enumerate(texts) if x.startswith("cmd 1 moveJ"))
    stopj = next(i for i, x in enumerate(texts) if x.startswith("cmd 34 stopJ"))
    movel = max(i for i, x in enumerate(texts) if x.startswith("cmd 3 moveL"))
    stopl = next(i for i, x in enumerate(texts) if x.startswith("cmd 33 stopL"))
    assert movej < stopj < movel < stopl and "async=0" in texts[stopj] and "async=0" in texts[stopl]
    assert any(x.startswith("arm braking") for x in texts[stopj:movel])  # it was moving: it braked
    assert any(x.startswith("arm braking") for x in texts[stopl:])


def test_two_emulators_side_by_side(tmp_path: Path, emu: Emulator, robot: URRobot) -> None:
    with emulator(tmp_path, "--model", "ur10e") as e10, URRobot(e10.address, RobotSpec(model="ur10e")) as r10:
        moves5 = emu.link.status()["moves"]
        robot.move_joints(Q_B)
        robot.move_joints(Q_A)
        r10.move_joints(Q_A)
        np.testing.assert_allclose(robot.tcp_pose(), URKinematics("ur5e").fk(Q_A), atol=1e-9)
        np.testing.assert_allclose(r10.tcp_pose(), URKinematics("ur10e").fk(Q_A), atol=1e-9)
        assert emu.link.status()["moves"] == moves5 + 2 and e10.link.status()["moves"] == 1
        assert emu.link.status()["model"] == "ur5e" and e10.link.status()["model"] == "ur10e"


# ============================================================================ captures
def test_protective_stop_mid_ring_then_unlock_and_resume(tmp_path: Path, demo_spec_path: Path,
                                                         faults: Emulator) -> None:
    from brave6d.capture.backends import open_rig
    from brave6d.capture.cli import make_plan
    from brave6d.capture.runner import CaptureOptions, run_capture

    scene = small_scene(tmp_path, demo_spec_path, views=6, distances=(0.3,))
    spec = scene.load_spec()
    plan = make_plan(scene)
    n = len(plan.views)
    assert n == 5
    faults.link.inject(f"pstop@move={_next_move(faults, 4)}")
    with open_rig(spec, f"ur:{faults.address}", "sim") as rig, pytest.raises(RobotError) as err:
        run_capture(scene.capture, plan.views, rig.robot, rig.camera)
    message = str(err.value)
    assert "\n" not in message and "protective stop" in message
    assert f"3 of {n} frames kept" in message and "--resume" in message
    assert len(scene.frames()) == 3
    assert dashboard_command(faults.address, "unlock protective stop") == "Protective stop releasing"
    with open_rig(spec, f"ur:{faults.address}", "sim") as rig:
        summary = run_capture(scene.capture, plan.views, rig.robot, rig.camera, CaptureOptions(resume=True))
    assert (summary.resumed_from, summary.written, summary.total) == (3, n - 3, n)
    records = scene.frames()
    assert [r.index for r in records] == list(range(n))
    assert sorted(r.view_id for r in records) == sorted(str(v.view_id) for v in plan.views)
    texts = faults.events()
    assert sum(x.startswith("PROTECTIVE STOP: injected fault pstop@move=") for x in texts) == 1
    assert "protective stop unlocked" in texts
    # the camera saw where the emulator held the arm; the frames record what ur-rtde reported (no pose error here)
    flange_T_cam = spec.simulation.true_tcp_T_camera.matrix()
    for i in (0, 4):
        truth = np.asarray(json.loads(scene.capture.sim_pose_path(i).read_text())["world_T_cam_true"])
        np.testing.assert_allclose(np.asarray(records[i].base_T_tcp) @ flange_T_cam, truth, atol=1e-9)


def test_resume_before_unlocking_is_refused_naming_the_protective_stop(faults: Emulator) -> None:
    with URRobot(faults.address, RobotSpec()) as r:
        r.move_joints(Q_A)
        faults.link.inject("pstop")
        time.sleep(0.2)
        with pytest.raises(RobotError, match="protective stop"):
            r.move_joints(Q_B)
    try:
        with pytest.raises(RobotError, match=r"Failed to start control script.*PROTECTIVE_STOP"):
            URRobot(faults.address, RobotSpec(), connect_tries=1)
    finally:
        assert dashboard_command(faults.address, "unlock protective stop") == "Protective stop releasing"


def _capture_cli(scene: Path, address: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "brave6d.cli", "capture", "run", str(scene), "--robot",
                           f"ur:{address}", "--camera", "sim", *extra], capture_output=True, text=True, timeout=300)


def test_dropped_connection_during_a_move_is_one_line_exit_2_and_resumable(tmp_path: Path, demo_spec_path: Path,
                                                                           faults: Emulator) -> None:
    scene = small_scene(tmp_path, demo_spec_path, views=6, distances=(0.3,))
    faults.link.inject(f"drop@move={_next_move(faults, 3)}")
    out = _capture_cli(scene.root, faults.address)
    lines = [x for x in out.stderr.splitlines() if x.strip() and not re.search(r"\| *\d+/\d+ \[", x)]  # no bars
    assert out.returncode == 2, out.stderr[-2000:]
    assert len(lines) == 1, lines
    assert lines[0].startswith("brave6d capture: error: ") and "lost the connection" in lines[0]
    assert "2 of 5 frames kept" in lines[0] and "--resume" in lines[0]
    assert any("dropped 2 RTDE connection(s)" in x for x in faults.events())
    time.sleep(3.0)  # the emulator's network outage
    out = _capture_cli(scene.root, faults.address, "--resume")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "captured 3 frames (2 kept from before, 5 in all)" in out.stdout
    records = scene.frames()
    assert [r.index for r in records] == [0, 1, 2, 3, 4] and len({r.view_id for r in records}) == 5


def test_ur_rtde_reconnect_after_a_drop_crashes_only_its_own_process(faults: Emulator) -> None:
    """The sharp edge behind the isolation: ur-rtde 1.6.5's own reconnect after a dropped socket."""
    worker = RTDEWorker(faults.address)
    try:
        faults.link.inject(f"drop@move={_next_move(faults)}")
        assert worker.call("control", "moveJ", (Q_A + 0.5).tolist(), 0.05, 1.4, True) is True
        deadline = time.monotonic() + 40
        crashed_or_wedged = (r"ur-rtde's process was killed by SIGSEGV during control\.reconnect|"
                             r"ur-rtde did not answer control\.reconnect within the time allowed")
        with pytest.raises(RobotClientError, match=crashed_or_wedged):
            while time.monotonic() < deadline:  # segfaults or wedges (seen both), never within its own process
                try:
                    worker.call("control", "reconnect", timeout=5.0)
                except RuntimeError:
                    pass  # an ordinary error (e.g. refused during the outage): try again
                time.sleep(0.05)
        assert not worker.alive
    finally:
        worker.close()
        time.sleep(3.0)  # the outage, for whoever connects next

"""The UR emulator's parts without a network: RTDE packing, fault texts, loopback-only addresses, the
motion model's stops, the controller's script loop answering as ur-rtde's script does."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.errors import BraveError
from brave6d.core.transforms import matrix_to_ur_pose
from brave6d.capture.kinematics import URKinematics
from brave6d.capture.sim_robot import trapezoid_time
from brave6d.capture.ur_emulator import Controller, ControllerConfig, FaultSpecError, check_loopback, parse_fault
from brave6d.capture.ur_emulator import rtde_protocol as rtde
from brave6d.capture.ur_emulator.commands import COMMANDS, DONE, READY, REALTIME
from brave6d.capture.ur_emulator.motion import Motion

Q_A = np.array([0.2, -1.2, 1.5, -1.8, -1.5, 0.3])


# ----------------------------------------------------------------------------- RTDE packing
@settings(max_examples=60)
@given(ints=st.lists(st.integers(-2**31, 2**31 - 1), min_size=1, max_size=4),
       doubles=st.lists(st.floats(allow_nan=False), min_size=0, max_size=6),
       vec=st.lists(st.floats(allow_nan=False), min_size=6, max_size=6))
def test_a_recipe_packs_and_unpacks_exactly(ints: list[int], doubles: list[float], vec: list[float]) -> None:
    names = [f"input_int_register_{i}" for i in range(len(ints))] + \
            [f"input_double_register_{i}" for i in range(len(doubles))] + ["external_force_torque"]
    recipe = rtde.Recipe(3, tuple(names), tuple(rtde.resolve(names, rtde.INPUT_TYPES)))
    values = dict(zip(names, [*ints, *doubles, vec]))
    payload = recipe.pack(values)
    assert payload[0] == 3 and len(payload) == 1 + recipe.size == 1 + 4 * len(ints) + 8 * len(doubles) + 48
    assert recipe.unpack(payload[1:]) == values
    with pytest.raises(rtde.ProtocolError, match=f"recipe 3 has {recipe.size - 1} bytes"):
        recipe.unpack(payload[1:-1])


def test_names_are_resolved_as_a_controller_answers() -> None:
    assert rtde.resolve(["timestamp", "actual_q", "nope", "actual_q;drop"], rtde.OUTPUT_TYPES) == \
        ["DOUBLE", "VECTOR6D", "NOT_FOUND", "NOT_FOUND"]
    assert rtde.resolve(["input_int_register_0", "input_int_register_1"], rtde.INPUT_TYPES,
                        in_use={"input_int_register_1"}) == ["INT32", "IN_USE"]
    assert rtde.split_names(b"a,b,") == ["a", "b"]
    for bad, why in ((b"", "no variable names"), (b",".join([b"x"] * 300), "300 names"), ("é".encode(), "ASCII")):
        with pytest.raises(rtde.ProtocolError, match=why):
            rtde.split_names(bad)
    with pytest.raises(rtde.ProtocolError, match="less than the header"):
        rtde.parse_header(struct.pack(">HB", 2, rtde.DATA_PACKAGE))
    for freq in (0.0, -1.0, 501.0, float("nan"), float("inf")):
        with pytest.raises(rtde.ProtocolError, match="frequency"):
            rtde.output_setup_request(struct.pack(">d", freq) + b"timestamp")


# ----------------------------------------------------------------------------- faults and addresses
@pytest.mark.parametrize("text, shown", [
    ("pstop@t=3", "pstop@t=3"), ("pstop@move=12", "pstop@move=12"), ("drop@move=1", "drop@move=1"),
    ("pstop@box=0.3,-0.1,0,0.5,0.1,0.2", "pstop@box=0.3,-0.1,0,0.5,0.1,0.2"), ("program-stop@t=0.5", "program-stop@t=0.5"),
    ("refuse=2", "refuse=2"), ("remote-off", "remote-off"), ("slow=0.25", "slow=0.25"),
])
def test_fault_texts_parse(text: str, shown: str) -> None:
    assert str(parse_fault(text)) == shown


@pytest.mark.parametrize("text, why", [
    ("pstop", "expected one of"), ("pstop@t", "needs a value"), ("pstop@t=-1", ">= 0"), ("pstop@t=nan", "finite"),
    ("pstop@move=0", "whole number >= 1"), ("pstop@move=1.5", "whole number"), ("drop@box=0,0,0,1,1,1", "unknown trigger"),
    ("pstop@box=1,1,1,0,0,0", "below its maximum"), ("pstop@box=1,2", "six numbers"), ("refuse=1.5", "whole number"),
    ("slow=9999", "at most 600"), ("explode@t=1", "expected one of"), ("x" * 300, "longer than 200"),
])
def test_bad_fault_texts_are_one_line_errors(text: str, why: str) -> None:
    with pytest.raises(FaultSpecError, match=why) as err:
        parse_fault(text)
    assert "\n" not in str(err.value)


@given(st.text(max_size=60))
def test_any_fault_text_parses_or_is_refused_cleanly(text: str) -> None:
    try:
        parse_fault(text)
    except FaultSpecError as exc:
        assert "\n" not in str(exc)


@pytest.mark.parametrize("address", ["0.0.0.0", "10.0.0.7", "192.168.1.10", "::", "example.org", "127.0.0.1 "])
def test_only_loopback_addresses_are_served(address: str) -> None:
    with pytest.raises(BraveError, match="loopback"):
        check_loopback(address)
    assert check_loopback("127.0.0.2") == "127.0.0.2" and check_loopback("localhost") == "127.0.0.1"
    assert check_loopback("::1") == "::1"


def test_the_command_refuses_a_network_address(capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.cli import main

    assert main(["ur-emulator", "--address", "0.0.0.0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "loopback addresses only" in err


# ----------------------------------------------------------------------------- motion
def test_a_stop_brakes_part_way_along_the_same_path() -> None:
    kin = URKinematics("ur5e")
    motion = Motion(kin, Q_A)
    target = Q_A + np.array([1.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    move = motion.movej(0.0, target, 1.0, 2.0)
    planned = float(trapezoid_time(1.0, 1.0, 2.0))
    assert move.t1 == pytest.approx(planned)
    t_stop = 0.5 * planned  # at full speed (1 rad/s) half way
    v = move.path_speed(t_stop)
    s_stop = move.fraction(t_stop)
    motion.stop(t_stop, 4.0)
    assert move.t1 == pytest.approx(t_stop + v / 4.0)
    q_end, _, speed = motion.state(move.t1 + 1.0)
    s_end = (q_end[0] - Q_A[0]) / 1.0
    assert s_end == pytest.approx(s_stop + v * v / (2 * 4.0), abs=1e-9)  # braking distance v^2 / 2a
    np.testing.assert_allclose(q_end, Q_A + s_end * (target - Q_A), atol=1e-12)  # on the joint line
    assert speed == 0.0 and not motion.moving(move.t1 + 1e-6)


# ----------------------------------------------------------------------------- the script loop
def _script(commands: dict = COMMANDS) -> str:
    """A control script with the branches the emulator checks (the real one comes from ur-rtde: the
    network tests check the table against it)."""
    branches = "".join(f"        elif cmd == {c}:\n            {e.script_marker}\n" for c, e in sorted(commands.items()))
    realtime = " or ".join(f"cmd == {c}" for c in sorted(REALTIME))
    return (f"def rtde_control():\n    def process_cmd(cmd):\n        if cmd == 0:\n            pass\n{branches}"
            f"    end\n    signal_ready()\n    while True:\n        if {realtime}:\n            pass\n        end\n"
            "    end\nend\n")


def _controller(**kw: object) -> tuple[Controller, list[float]]:
    clock = [0.0]
    c = Controller(ControllerConfig(**kw), wall=lambda: clock[0])  # type: ignore[arg-type]
    c.start_program(_script())
    return c, clock


def test_a_script_whose_commands_differ_is_not_run() -> None:
    c = Controller(ControllerConfig())
    renumbered = {(48 if k == 47 else k): v for k, v in COMMANDS.items()}
    c.start_program(_script(renumbered))
    assert c.runtime_state == 1
    assert any("script refused: its commands differ" in e.text and "command 47 (isSteady)" in e.text
               for e in c.events)
    c.start_program(_script())
    assert c.runtime_state == 2


def _command(c: Controller, cmd: int, doubles: list[float] = (), async_flag: int = 0) -> None:
    c.write_inputs({"input_int_register_0": cmd, "input_int_register_1": async_flag,
                    **{f"input_double_register_{i}": v for i, v in enumerate(doubles)}})
    c.tick()


def test_the_script_loop_answers_ready_then_done_once_per_command() -> None:
    c, clock = _controller()
    assert c.tick()["output_int_register_"][0] == READY and c.runtime_state == 2
    _command(c, 47)  # isSteady
    assert c.out_int[0] == DONE and c.out_int[1] == 1 and c.commands_executed == 1
    c.tick()
    assert c.commands_executed == 1  # the same command in the register is not executed again
    _command(c, 0)
    assert c.out_int[0] == READY
    _command(c, 1, [*Q_A, 1.0, 2.0])  # synchronous moveJ: no 'done' until the arm arrives
    assert c.out_int[0] == READY and c.motion.moving(c.now())
    clock[0] += 10.0
    c.tick()
    assert c.out_int[0] == DONE
    np.testing.assert_allclose(c.current_q(), Q_A, atol=1e-12)


def test_an_async_move_reports_through_the_progress_register() -> None:
    c, clock = _controller()
    before = c.out_int[2]
    _command(c, 1, [*Q_A, 1.0, 2.0], async_flag=1)
    status = c.out_int[2]
    assert c.out_int[0] == DONE and status & 0x8000 and (status >> 24) & 0x7F == ((before >> 24) & 0x7F) + 1
    _command(c, 0)
    clock[0] += 10.0
    c.tick()
    assert not c.out_int[2] & 0x8000 and (c.out_int[2] >> 24) & 0x7F == (status >> 24) & 0x7F


def test_ik_without_a_solution_is_a_urscript_error_that_stops_the_program() -> None:
    c, _ = _controller()
    far = matrix_to_ur_pose(np.diag([1.0, -1.0, -1.0, 1.0]) @ np.eye(4))
    far[:3] = [2.0, 0.0, 0.3]
    _command(c, 61, [*far, *Q_A, 1e-10, 1e-10])  # has a solution? no: answered, the program runs on
    assert c.out_int[1] == 0 and c.runtime_state == 2
    _command(c, 0)
    _command(c, 30, [*far, *Q_A, 1e-10, 1e-10])  # get_inverse_kin() itself: a runtime error, as URScript's
    assert c.runtime_state == 1
    assert any("get_inverse_kin(): no solution" in e.text for e in c.events)


def test_a_command_that_is_not_emulated_stops_the_program_naming_it() -> None:
    c, _ = _controller()
    _command(c, 13)  # setStandardDigitalOut: not emulated, never silently 'done'
    assert c.runtime_state == 1 and c.out_int[0] != DONE
    assert any("command 13 is not emulated" in e.text for e in c.events)


def test_a_protective_stop_pauses_and_a_new_program_waits_for_the_unlock() -> None:
    c, clock = _controller(unlock_delay_s=5.0)
    _command(c, 1, [*(Q_A + 0.5), 1.0, 2.0], async_flag=1)
    clock[0] += 0.3
    c.protective_stop("test")
    assert c.runtime_state == 4 and c.tick()["safety_status_bits"] == 1 << 2
    c.start_program(_script())
    assert c.runtime_state == 4  # refused during the protective stop
    assert c.unlock_protective_stop().startswith("Cannot unlock protective stop until 5s")
    clock[0] += 5.0
    assert c.unlock_protective_stop() == "Protective stop releasing"
    c.start_program(_script())
    assert c.runtime_state == 2 and c.tick()["safety_status_bits"] == 1
    assert math.isfinite(c.current_q()[0]) and not np.allclose(c.current_q(), Q_A + 0.5)


def test_a_region_fault_stops_the_arm_where_its_path_enters_the_box() -> None:
    kin = URKinematics("ur5e")
    target = Q_A + np.array([0.6, 0.0, 0.0, 0.0, 0.0, 0.0])
    mid = kin.fk(Q_A + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0]))[:3, 3]  # the TCP half way along the move
    box = ",".join(f"{v:.4f}" for v in (*(mid - 0.01), *(mid + 0.01)))
    far = ",".join(f"{v:.4f}" for v in (*(mid + 0.5), *(mid + 0.6)))
    for spec, stops in ((f"pstop@box={box}", True), (f"pstop@box={far}", False)):
        c, clock = _controller(faults=(parse_fault(spec),))
        _command(c, 1, [*Q_A, 1.0, 2.0], async_flag=1)
        clock[0] += 10.0
        c.tick()
        _command(c, 0)
        _command(c, 1, [*target, 1.0, 2.0], async_flag=1)
        for _ in range(40):
            clock[0] += 0.05
            c.tick()
        assert (c.safety_mode == 3) is stops
        q = c.current_q()
        if stops:  # braked just past the box's edge, short of the target
            assert 0.2 < q[0] - Q_A[0] < 0.35
            assert any(e.text == f"PROTECTIVE STOP: injected fault {spec}" for e in c.events)
        else:
            np.testing.assert_allclose(q, target, atol=1e-12)


def test_a_move_that_would_leave_the_safety_box_ends_in_a_protective_stop() -> None:
    kin = URKinematics("ur5e")
    z = kin.fk(Q_A)[2, 3]
    c, clock = _controller(safety_box=((-2.0, -2.0, z - 0.05), (2.0, 2.0, 2.0)))
    _command(c, 1, [*Q_A, 1.0, 2.0], async_flag=1)
    clock[0] += 10.0
    c.tick()
    _command(c, 0)
    below = kin.fk(Q_A)
    below[2, 3] -= 0.2
    assert not c.pose_within_safety_limits(below)
    _command(c, 3, [*matrix_to_ur_pose(below), 0.25, 1.2], async_flag=1)  # moveL straight down through the floor
    for _ in range(40):
        clock[0] += 0.05
        c.tick()
    assert c.safety_mode == 3
    assert any(e.text.startswith("PROTECTIVE STOP: safety limit") for e in c.events)
    assert kin.fk(c.current_q())[2, 3] > z - 0.08  # stopped near the floor, not 0.2 m below


def test_a_timed_fault_fires_once_at_its_time() -> None:
    c, clock = _controller(faults=(parse_fault("program-stop@t=2"),))
    clock[0] += 1.9
    c.tick()
    assert c.runtime_state == 2
    clock[0] += 0.2
    c.tick()
    assert c.runtime_state == 1
    c.start_program(_script())
    clock[0] += 5.0
    c.tick()
    assert c.runtime_state == 2  # once

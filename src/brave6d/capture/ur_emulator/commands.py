"""The commands of ur-rtde's control script that the emulator executes, and a check of that table
against the script a client actually uploads.

ur-rtde (``RTDEControlInterface``) writes a command's type to ``input_int_register_0``, its
arguments to ``input_double_register_0..`` and an async flag to ``input_int_register_1``; the
control script it uploads to port 30003 dispatches on the type (``elif cmd == N:``). The ids below
are those of ur-rtde 1.6.5's script. :func:`check_against_script` reads an uploaded script and
reports every emulated command whose branch does not call what the emulator does, so a client
release that renumbers its commands (or a wrong entry here) is caught, not silently obeyed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass


@dataclass(frozen=True)
class ScriptCommand:
    """One command: its id, the ur-rtde method that sends it, and the text its script branch holds."""

    cmd: int
    method: str
    #: a piece of the script's ``elif cmd == N:`` branch that identifies what it does
    script_marker: str


#: Every command the emulator executes (id -> command); any other id stops the program with an error.
COMMANDS: dict[int, ScriptCommand] = {c.cmd: c for c in (
    ScriptCommand(1, "moveJ", "movej(q, a=acceleration, v=velocity)"),
    ScriptCommand(2, "moveJ_IK", "q = get_inverse_kin(pose)"),
    ScriptCommand(3, "moveL", "movel(pose, a=acceleration, v=velocity)"),
    ScriptCommand(4, "moveL_FK", "movel(q, a=acceleration, v=velocity)"),
    ScriptCommand(29, "setTcp", "set_tcp(pose)"),
    ScriptCommand(30, "getInverseKinematics", "get_inverse_kin(x, qnear, maxPositionError, maxOrientationError)"),
    ScriptCommand(31, "triggerProtectiveStop", "protective_stop()"),
    ScriptCommand(33, "stopL", 'exec_stopl_stopj(cmd, "stopl async=")'),
    ScriptCommand(34, "stopJ", 'exec_stopl_stopj(cmd, "stopj async=")'),
    ScriptCommand(35, "setWatchdog", "rtde_set_watchdog("),
    ScriptCommand(36, "isPoseWithinSafetyLimits", "is_within_safety_limits(pose)"),
    ScriptCommand(37, "isJointsWithinSafetyLimits", "is_within_safety_limits(q)"),
    ScriptCommand(40, "getTCPOffset", "get_tcp_offset()"),
    ScriptCommand(43, "getForwardKinematics", "get_forward_kin()"),
    ScriptCommand(44, "getForwardKinematics", "get_forward_kin(q, tcp_offset)"),
    ScriptCommand(46, "getInverseKinematics", "q = get_inverse_kin(x)"),
    ScriptCommand(47, "isSteady", "is_steady()"),
    ScriptCommand(60, "getInverseKinematicsHasSolution", "get_inverse_kin_has_solution(x)"),
    ScriptCommand(61, "getInverseKinematicsHasSolution",
                  "get_inverse_kin_has_solution(x, qnear, maxPositionError, maxOrientationError)"),
    ScriptCommand(255, "stopScript", 'textmsg("Received stop script!")'),
)}
#: Ids the script treats as real-time commands (processed every cycle, answered 'ready' at once).
REALTIME = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
NO_CMD = 0
STOP_SCRIPT = 255
#: output_int_register_0 values the script writes
READY, DONE = 1, 2

_BRANCH = re.compile(r"^\s*(?:el)?if cmd == (\d+):\s*$", re.MULTILINE)
_MAIN = "def rtde_control():"


def script_branches(script: str) -> dict[int, str]:
    """The text of each ``if/elif cmd == N:`` branch of a control script's ``process_cmd`` (first
    occurrence per id)."""
    marks = list(_BRANCH.finditer(script))
    out: dict[int, str] = {}
    for i, m in enumerate(marks):
        end = marks[i + 1].start() if i + 1 < len(marks) else len(script)
        out.setdefault(int(m.group(1)), script[m.end():end])
    return out


def is_control_script(script: str) -> bool:
    """True for ur-rtde's control script (the only program the emulator runs)."""
    return _MAIN in script and "def process_cmd(cmd):" in script and "signal_ready()" in script


def check_against_script(script: str, commands: dict[int, ScriptCommand] | None = None) -> list[str]:
    """Every disagreement between ``commands`` (default :data:`COMMANDS`) and the script's branches,
    one line each; empty when the table matches the script the client uploaded."""
    table = COMMANDS if commands is None else commands
    branches = script_branches(script)
    problems = []
    for cmd, entry in sorted(table.items()):
        body = branches.get(cmd)
        if body is None:
            problems.append(f"command {cmd} ({entry.method}): the script has no branch for it")
        elif entry.script_marker not in body:
            first = body.strip().splitlines()[0].strip() if body.strip() else "(empty)"
            problems.append(f"command {cmd} ({entry.method}): the script's branch does not contain "
                            f"{entry.script_marker!r} (it starts with {first!r})")
    realtime = re.search(r"if (cmd == \d+(?: or cmd == \d+)+):", script)  # the main loop's real-time test
    if realtime is not None:
        ids = {int(x) for x in re.findall(r"cmd == (\d+)", realtime.group(1))}
        if ids != REALTIME:
            problems.append(f"real-time commands differ: script {sorted(ids)}, emulator {sorted(REALTIME)}")
    return problems

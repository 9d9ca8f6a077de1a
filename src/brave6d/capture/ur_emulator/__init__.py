"""A UR e-Series controller emulator that the unmodified ur-rtde client drives (``brave6d ur-emulator``).

Public API: :class:`Controller` / :class:`ControllerConfig` (the emulated controller),
:class:`EmulatorServer` (its RTDE, dashboard, script and side-channel ports on a loopback
address), :class:`EmulatorLink` / :func:`probe` (the side channel's client), :func:`parse_fault`,
and :func:`check_against_script` (the command table against the script a client uploads).
"""

from brave6d.capture.ur_emulator.commands import COMMANDS, check_against_script
from brave6d.capture.ur_emulator.controller import Controller, ControllerConfig
from brave6d.capture.ur_emulator.faults import Fault, FaultSpecError, parse_fault
from brave6d.capture.ur_emulator.link import EmulatorLink, EmulatorLinkError, probe
from brave6d.capture.ur_emulator.servers import SIDE_PORT, EmulatorServer, check_loopback

__all__ = ["COMMANDS", "check_against_script", "Controller", "ControllerConfig", "Fault", "FaultSpecError",
           "parse_fault", "EmulatorLink", "EmulatorLinkError", "probe", "SIDE_PORT", "EmulatorServer",
           "check_loopback"]

"""``brave6d ur-emulator``: a UR e-Series controller on a loopback address that the real ur-rtde
client drives (RTDE 30004, dashboard 29999, script 30003), for rehearsing the lab workflow.

Typical rehearsal, in two terminals::

    brave6d ur-emulator --spec SCENE_DIR --address 127.0.0.2 --time-scale 10
    brave6d calibrate all SCENE_DIR --robot ur:127.0.0.2 --camera sim

The emulator prints every command, stop and fault with the controller time, and runs until
Ctrl-C (or SIGTERM).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

import numpy as np

from brave6d.core.errors import BraveError
from brave6d.capture.kinematics import UR_DH


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--address", default="127.0.0.2",
                        help="loopback address to listen on (default 127.0.0.2; each emulator needs its own, "
                             "since ur-rtde's ports are fixed)")
    parser.add_argument("--model", choices=sorted(UR_DH), default=None,
                        help="arm model (default: the spec's robot.model, else ur5e)")
    parser.add_argument("--spec", type=Path, default=None, metavar="PATH",
                        help="scene spec (YAML) or scene directory: robot model and home joints, and the "
                             "simulation's robot effects (robot_pose_error, time_offset) with its seed")
    parser.add_argument("--time-scale", type=float, default=1.0, metavar="X",
                        help="controller seconds per real second (10: moves take a tenth of a real arm's time)")
    parser.add_argument("--safety-box", default=None, metavar="X0,Y0,Z0,X1,Y1,Z1",
                        help="the TCP must stay in this box (base frame, m): is_within_safety_limits refuses "
                             "poses outside it and a move leaving it ends in a protective stop")
    parser.add_argument("--fault", action="append", default=[], metavar="FAULT",
                        help="inject a fault (repeatable): pstop@t=S, pstop@move=N, pstop@box=X0,Y0,Z0,X1,Y1,Z1, "
                             "drop@t=S, drop@move=N, program-stop@t=S|@move=N, refuse=N, remote-off, slow=S")
    parser.add_argument("--unlock-delay", type=float, default=5.0, metavar="S",
                        help="controller seconds after a protective stop before it can be unlocked (default 5)")
    parser.add_argument("--quiet", action="store_true", help="do not print the event log")


def _safety_box(text: str | None) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    if text is None:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise BraveError(f"--safety-box {text!r}: expected six numbers X0,Y0,Z0,X1,Y1,Z1") from None
    if len(v) != 6 or not np.all(np.isfinite(v)) or any(a >= b for a, b in zip(v[:3], v[3:])):
        raise BraveError(f"--safety-box {text!r}: expected six finite numbers, each minimum below its maximum")
    return tuple(v[:3]), tuple(v[3:])


def build_config(args: argparse.Namespace):  # noqa: ANN201 - ControllerConfig
    """The controller's configuration from the command line (and the spec, when given)."""
    from brave6d.core.spec import load_scene_spec
    from brave6d.capture.ur_emulator.controller import ControllerConfig
    from brave6d.capture.ur_emulator.faults import parse_fault

    kwargs: dict = {}
    if args.spec is not None:
        path = args.spec / "scene.yaml" if args.spec.is_dir() else args.spec
        spec = load_scene_spec(path, check_files=False)
        kwargs["model"] = spec.robot.model
        kwargs["home_joints"] = tuple(np.deg2rad(spec.robot.home_joints_deg).tolist())
        if spec.simulation is not None:
            effects = spec.simulation.effects
            kwargs["pose_error"] = effects.robot_pose_error
            kwargs["report_delay_s"] = effects.time_offset.offset_s if effects.time_offset is not None else 0.0
            kwargs["seed"] = spec.simulation.seed
    if args.model is not None:
        kwargs["model"] = args.model
    if not (np.isfinite(args.unlock_delay) and args.unlock_delay >= 0):
        raise BraveError(f"--unlock-delay {args.unlock_delay}: expected a number >= 0")
    return ControllerConfig(time_scale=float(args.time_scale), safety_box=_safety_box(args.safety_box),
                            faults=tuple(parse_fault(f) for f in args.fault), unlock_delay_s=args.unlock_delay,
                            **kwargs)


def run(args: argparse.Namespace) -> int:
    from brave6d.capture.ur_emulator.controller import Controller
    from brave6d.capture.ur_emulator.servers import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT, EmulatorServer

    config = build_config(args)
    controller = Controller(config)
    if not args.quiet:
        controller.on_event = lambda e: print(f"{e.t:10.3f}  {e.text}", flush=True)
    server = EmulatorServer(controller, args.address)
    server.start()
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    faults = ", ".join(str(f) for f in config.faults) or "none"
    print(f"ur-emulator: {config.model.upper()} controller (PolyScope {config.polyscope_version}) on "
          f"{server.address}: RTDE {RTDE_PORT}, dashboard {DASHBOARD_PORT}, script {SCRIPT_PORT}, side channel "
          f"{server.side_port}; time scale {config.time_scale:g}; faults: {faults}. Ctrl-C stops it.", flush=True)
    try:
        done.wait()
    finally:
        server.stop()
        print("ur-emulator: stopped", file=sys.stderr, flush=True)
    return 0

"""The ``brave6d`` command line: one sub-command per stage, dispatched lazily.

``brave6d --help`` lists the commands without importing any stage (torch, open3d, ... load only
when their command runs). Each command module provides ``configure(parser)`` and
``run(args) -> int``. A :class:`~brave6d.core.errors.BraveError` ends the program with one line on
stderr and exit status 2, never with a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from dataclasses import dataclass

from brave6d.core.errors import BraveError


@dataclass(frozen=True)
class Command:
    name: str
    module: str
    help: str
    #: a server: once it has stopped (Ctrl-C, SIGTERM) and closed what it had open, the process ends at
    #: once instead of tearing the interpreter down (about 1-2 s of torch, numba and Open3D on 2 cores)
    exits_fast: bool = False


#: Every command, in pipeline order. A stage adds its line here when it exists.
COMMANDS: tuple[Command, ...] = (
    Command("spec", "brave6d.spec_cli", "validate a scene spec (YAML) and print a summary"),
    Command("init", "brave6d.init_cli", "create a scene directory from a scene spec"),
    Command("calibrate", "brave6d.calibration.cli", "capture the ChArUco board, calibrate intrinsics and the hand-eye transform"),
    Command("capture", "brave6d.capture.cli", "plan capture views and capture them with a robot and a camera"),
    Command("ur-emulator", "brave6d.capture.ur_emulator.cli", "emulate a UR controller on a loopback address for ur-rtde (rehearse calibrate/capture with --robot ur:ADDRESS --camera sim)", exits_fast=True),
    Command("import", "brave6d.training.import_cli", "import a capture made elsewhere (COLMAP model or nerfstudio / instant-ngp transforms.json) into a scene directory"),
    Command("annotate", "brave6d.annotation.cli", "import 3D-DAT object poses and export BOP ground truth"),
    Command("train", "brave6d.training.cli", "train a 3D Gaussian Splatting scene and evaluate it on held-out views"),
    Command("synth", "brave6d.synth.cli", "render a synthetic training split (BOP train_pbr) of a dataset's or scene's objects"),
    Command("export", "brave6d.serve.export_cli", "write the scene bundle that the render server loads"),
    Command("serve", "brave6d.commands.serve", "serve a bundle to active-vision agents (HTTP + WebSocket, browser viewer)", exits_fast=True),
    Command("release", "brave6d.dataset.release.cli", "build a dataset release (BOP zips, bundles, checksums, card) or verify one"),
    Command("ros1", "brave6d.commands.ros1", "serve a bundle or release as a ROS 1 node (topics, tf, services; rospy)", exits_fast=True),
    Command("ros2", "brave6d.commands.ros2", "serve a bundle or release as a ROS 2 node (rclpy: services and topics; loopback by default)", exits_fast=True),
    Command("evaluate", "brave6d.evaluation.cli", "score agent episodes (BOP Average Recall, adjustments) and print a leaderboard"),
    Command("learn", "brave6d.evaluation.learned.cli", "train the learned baseline (detector + pose network) on a synthetic train_pbr, or score it on held-out images"),
    Command("estimate", "brave6d.evaluation.estimate_cli", "estimate an object's pose in any RGB-D frame (or over a BOP split: results CSV)"),
    Command("report", "brave6d.evaluation.report.cli", "write the accuracy-vs-time report from real measurements"),
    Command("dataset", "brave6d.dataset.cli", "run every stage of every scene of a dataset (local or Slurm); show its status"),
    Command("demo", "brave6d.pipeline.demo", "run the whole pipeline on the embedded demo scene"),
)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("brave6d")
    except PackageNotFoundError:
        return "unknown"


def _top_parser() -> argparse.ArgumentParser:
    width = max(len(c.name) for c in COMMANDS)
    listing = "\n".join(f"  {c.name.ljust(width)}  {c.help}" for c in COMMANDS)
    parser = argparse.ArgumentParser(
        prog="brave6d",
        description="BRAVE-6D pipeline: capture, calibrate, train 3D Gaussian Splatting scenes, "
        "annotate, export and serve them to active-vision agents.",
        epilog=f"commands (in pipeline order):\n{listing}\n\nRun 'brave6d COMMAND --help' for a command's options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"brave6d {_version()}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    parser.add_argument("command", choices=[c.name for c in COMMANDS], metavar="COMMAND", help="see below")
    parser.add_argument("args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script."""
    from brave6d.core.progress import setup_logging
    from brave6d.core.runtime import prepare_process

    prepare_process()  # before any stage imports torch / numba
    top = _top_parser()
    ns = top.parse_args(argv)
    command = next(c for c in COMMANDS if c.name == ns.command)
    module = importlib.import_module(command.module)
    parser = argparse.ArgumentParser(prog=f"brave6d {command.name}", description=command.help)
    module.configure(parser)
    args = parser.parse_args(ns.args)
    args.verbose = ns.verbose + getattr(args, "verbose", 0)
    setup_logging(args.verbose)
    try:
        return int(module.run(args) or 0)
    except BraveError as exc:  # user-facing: one line, no traceback
        print(f"brave6d {command.name}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"brave6d {command.name}: interrupted", file=sys.stderr)
        return 130
    except RecursionError:  # e.g. an input nested thousands deep: one line, not a 3,000-line traceback
        print(f"brave6d {command.name}: error: an input is nested too deeply to process "
              "(Python's recursion limit was reached); check the files this command reads", file=sys.stderr)
        return 2


def console() -> None:
    """The console script: :func:`main`; a server command's process then ends at once (``exits_fast``),
    its logs and output flushed."""
    code = main()
    name = next((a for a in sys.argv[1:] if not a.startswith("-")), None)
    if any(c.name == name and c.exits_fast for c in COMMANDS):
        import logging
        import os

        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    console()

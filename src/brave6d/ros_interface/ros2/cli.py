"""``brave6d ros2 BUNDLE_OR_RELEASE``: serve a bundle's (or a release's) episodes as a ROS 2 node on
rclpy (the ``ros2`` extra: ROS 2 Kilted wheels with Fast DDS; docs/ROS.md).

Loopback by default (:mod:`brave6d.ros_interface.ros2.transport`): UDP on 127.0.0.1 and shared
memory, discovery ``LOCALHOST``, so ROS 2 agents on this machine started with ROS 2's defaults
see it and no other host does. ``--allow-remote`` keeps ROS 2's defaults (every interface,
``SUBNET`` discovery): every host on the network can then drive episodes (and, with ``--training``,
read the ground truth).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
from pathlib import Path
from typing import TYPE_CHECKING

from brave6d.core.errors import BraveError
from brave6d.core.extras import require
from brave6d.core.runtime import quiet_openmp

if TYPE_CHECKING:
    from brave6d.serve import SourcesOf

log = logging.getLogger(__name__)

#: ROS 2's domain ids on one host (rmw: 0..232 with the default port mapping).
MAX_DOMAIN_ID = 232


def configure(parser: argparse.ArgumentParser) -> None:
    from brave6d.core.cli_types import int_in
    from brave6d.ros_interface.ros2.defaults import DEFAULT_NAMESPACE, DEFAULT_TWIST_DURATION_S
    from brave6d.serve import add_mode_flags, limit_arg  # every number bounded at parse time, as the server's

    parser.add_argument("scenes", type=Path, metavar="BUNDLE_OR_RELEASE",
                        help="a bundle folder ('brave6d export') or a dataset release ('brave6d release build')")
    parser.add_argument("--domain-id", type=int_in(0, MAX_DOMAIN_ID), default=None,
                        help="ROS 2 domain id (default: $ROS_DOMAIN_ID, else 0)")
    parser.add_argument("--allow-remote", action="store_true",
                        help="let other hosts reach the node (ROS 2's default discovery and interfaces; "
                             "default: this machine only)")
    parser.add_argument("--peer", action="append", default=[], metavar="HOST",
                        help="also discover participants at HOST by unicast (ROS_STATIC_PEERS; repeatable; a "
                             "remote HOST needs --allow-remote)")
    parser.add_argument("--namespace", default=DEFAULT_NAMESPACE,
                        help=f"namespace of the topics and services (default {DEFAULT_NAMESPACE})")
    parser.add_argument("--twist-duration", type=limit_arg("move_duration_s"),
                        default=DEFAULT_TWIST_DURATION_S,
                        help=f"seconds a move with duration 0 lasts (default {DEFAULT_TWIST_DURATION_S})")
    parser.add_argument("--width", type=limit_arg("width"), default=None, help="image width (default: the bundle's)")
    parser.add_argument("--height", type=limit_arg("height"), default=None, help="image height (default: the bundle's)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="rasterizer device")
    parser.add_argument("--log-dir", type=Path, default=None,
                        help="where episode logs (JSONL) go (default: 'episodes' beside the bundle)")
    parser.add_argument("--scene", default=None, help="the scene a reset uses when it names none (a release's scene)")
    parser.add_argument("--idle-timeout", type=limit_arg("idle_timeout_s"), default=900.0,
                        help="close an episode idle for this many seconds (default 900)")
    parser.add_argument("--agent", default="ros2", help="agent name written in the episode logs (default ros2)")
    add_mode_flags(parser)  # --training, --log-key: as brave6d serve's


def domain_id_from(value: int | None, environ: dict[str, str] | None = None) -> int:
    """``--domain-id``, else ``$ROS_DOMAIN_ID``, else 0; refused outside 0..232 naming the source."""
    if value is not None:
        source, raw = "--domain-id", str(value)
    else:
        source, raw = "$ROS_DOMAIN_ID", (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
        if not raw:
            return 0
    try:
        domain = int(raw)
    except ValueError:
        raise BraveError(f"{source} {raw!r}: not an integer") from None
    if not 0 <= domain <= MAX_DOMAIN_ID:
        raise BraveError(f"{source} {domain}: must be in 0..{MAX_DOMAIN_ID}")
    return domain


def run(args: argparse.Namespace, sources_of: SourcesOf) -> int:
    """Run the node on the scenes ``sources_of(args.scenes, None)`` gives until SIGINT / SIGTERM."""
    quiet_openmp()
    from brave6d.ros_interface.ros2.transport import apply_environment, node_environment

    domain_id = domain_id_from(args.domain_id)
    if not args.twist_duration > 0:
        raise BraveError(f"--twist-duration must be > 0 seconds, got {args.twist_duration}")
    require("rclpy", "ros2", "brave6d ros2")
    from brave6d.ros_interface.ros2.node import check_namespace

    check_namespace(args.namespace)  # before the scenes load: a one-line refusal, not rclpy's traceback
    apply_environment(node_environment(args.allow_remote, tuple(args.peer)))  # before rclpy.init reads them
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    from brave6d.ros_interface.bridge import EpisodeBridge
    from brave6d.ros_interface.ros2.node import Ros2Node
    from brave6d.serve import EpisodeManager, mode_of, open_scenes, server_log_key

    scenes = open_scenes(sources_of(args.scenes, None), device=args.device)
    log_dir = args.log_dir if args.log_dir is not None else Path(args.scenes).resolve().parent / "episodes"
    manager = EpisodeManager(scenes, log_dir, max_episodes=4, idle_timeout_s=args.idle_timeout,
                             mode=mode_of(args), log_key=server_log_key(args.log_key))
    bridge = EpisodeBridge(manager, agent=args.agent, width=args.width, height=args.height)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = Ros2Node(bridge, namespace=args.namespace, twist_duration_s=args.twist_duration,
                    default_scene=args.scene, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node.node)
    reach = "any host (--allow-remote)" if args.allow_remote else "this machine only"
    print(f"brave6d ros2: {', '.join(map(str, scenes.names()))} on ROS 2 domain {domain_id} ({reach}), "
          f"{manager.mode} mode, services and topics under {node.namespace}/ and /tf; episode logs: {log_dir}",
          flush=True)
    stop = _StopOnSignals()
    try:
        while not stop.signal and context.ok():  # rcl_wait returns every SPIN_S, so Python's handlers run
            executor.spin_once(timeout_sec=SPIN_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        stop.restore()
        node.destroy()  # closes the open episode (its log's close record)
        executor.shutdown()
        rclpy.try_shutdown(context=context)
    if stop.signal is not None:
        log.info("brave6d ros2: %s: closed the open episode and stopped", signal.Signals(stop.signal).name)
    return 0


#: Seconds the executor waits for work before it looks at the signals that came.
SPIN_S = 0.1


class _StopOnSignals:
    """SIGINT and SIGTERM ask the node to stop (the open episode is closed, then the command returns).

    rclpy installs no signal handlers for a context of its own, and ``executor.spin()`` blocks in
    ``rcl_wait``, where Python's handlers never run: the node spins in steps of :data:`SPIN_S`."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signal: int | None = None
        self.previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}

    def _handle(self, signum: int, frame: object) -> None:
        self.signal = signum

    def restore(self) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler)

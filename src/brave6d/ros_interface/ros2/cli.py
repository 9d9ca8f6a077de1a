"""``brave6d ros2 BUNDLE_OR_RELEASE``: serve a bundle's (or a release's) episodes as ROS 2 topics
over DDS (Cyclone DDS; no ROS 2 installation needed on this side).

Loopback by default: DDS is configured on 127.0.0.1 with multicast off, so only ROS 2 nodes on
this machine (with ``ROS_LOCALHOST_ONLY=1`` or a loopback Cyclone configuration) see it. Another
``--interface`` (an address or an interface name) needs ``--allow-remote``: every host on that
network can then drive episodes and read the ground truth.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from brave6d.core.errors import BraveError
from brave6d.core.extras import require
from brave6d.core.runtime import quiet_openmp

if TYPE_CHECKING:
    from brave6d.serve import SourcesOf

log = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    from brave6d.core.cli_types import int_in
    from brave6d.ros_interface.ros2.dds import MAX_DOMAIN_ID
    from brave6d.ros_interface.ros2.defaults import DEFAULT_NAMESPACE, DEFAULT_TWIST_DURATION_S
    from brave6d.serve import limit_arg  # every number bounded at parse time, as the render server's flags

    parser.add_argument("scenes", type=Path, metavar="BUNDLE_OR_RELEASE",
                        help="a bundle folder ('brave6d export') or a dataset release ('brave6d release build')")
    parser.add_argument("--domain-id", type=int_in(0, MAX_DOMAIN_ID), default=None,
                        help="DDS domain id, as ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID, else 0)")
    parser.add_argument("--interface", default="127.0.0.1",
                        help="network interface for DDS: an address or a name (default 127.0.0.1: this machine "
                             "only; any other needs --allow-remote)")
    parser.add_argument("--allow-remote", action="store_true",
                        help="allow a non-loopback --interface (every host on that network can use the node)")
    parser.add_argument("--peer", action="append", default=[], metavar="HOST",
                        help="also discover DDS participants at HOST by unicast (repeatable; for networks "
                             "without multicast)")
    parser.add_argument("--namespace", default=DEFAULT_NAMESPACE, help=f"topic namespace (default {DEFAULT_NAMESPACE})")
    parser.add_argument("--twist-duration", type=limit_arg("move_duration_s"),
                        default=DEFAULT_TWIST_DURATION_S,
                        help=f"seconds one cmd_twist message is applied (default {DEFAULT_TWIST_DURATION_S})")
    parser.add_argument("--width", type=limit_arg("width"), default=None, help="image width (default: the bundle's)")
    parser.add_argument("--height", type=limit_arg("height"), default=None, help="image height (default: the bundle's)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="rasterizer device")
    parser.add_argument("--log-dir", type=Path, default=None,
                        help="where episode logs (JSONL) go (default: 'episodes' beside the bundle)")
    parser.add_argument("--scene", default=None, help="the scene a reset uses when it names none (a release's scene)")
    parser.add_argument("--idle-timeout", type=limit_arg("idle_timeout_s"), default=900.0,
                        help="close an episode idle for this many seconds (default 900)")
    parser.add_argument("--agent", default="ros2", help="agent name written in the episode logs (default ros2)")


def domain_id_from(value: int | None, environ: dict[str, str] | None = None) -> int:
    """``--domain-id``, else ``$ROS_DOMAIN_ID``, else 0 (checked by :func:`dds.check_domain_id`)."""
    from brave6d.ros_interface.ros2.dds import check_domain_id

    if value is not None:
        return check_domain_id(value)
    env = os.environ if environ is None else environ
    raw = env.get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return 0
    try:
        return check_domain_id(int(raw))
    except ValueError:
        raise BraveError(f"$ROS_DOMAIN_ID {raw!r}: not an integer") from None


def run(args: argparse.Namespace, sources_of: SourcesOf) -> int:
    """Run the node on the scenes ``sources_of(args.scenes, None)`` gives (``brave6d.commands.ros2``
    hands it: a bundle's or a release's)."""
    quiet_openmp()
    require("cyclonedds", "ros2", "brave6d ros2")
    from brave6d.ros_interface.bridge import EpisodeBridge
    from brave6d.ros_interface.ros2.dds import DdsDomain, check_interface
    from brave6d.ros_interface.ros2.node import Ros2Node
    from brave6d.serve import EpisodeManager, open_scenes

    domain_id = domain_id_from(args.domain_id)
    check_interface(args.interface, args.allow_remote)
    if not args.twist_duration > 0:
        raise BraveError(f"--twist-duration must be > 0 seconds, got {args.twist_duration}")
    scenes = open_scenes(sources_of(args.scenes, None), device=args.device)
    log_dir = args.log_dir if args.log_dir is not None else Path(args.scenes).resolve().parent / "episodes"
    manager = EpisodeManager(scenes, log_dir, max_episodes=4, idle_timeout_s=args.idle_timeout)
    bridge = EpisodeBridge(manager, agent=args.agent, width=args.width, height=args.height)
    dds = DdsDomain(domain_id, args.interface, allow_remote=args.allow_remote, peers=tuple(args.peer))
    node = Ros2Node(bridge, dds, namespace=args.namespace, twist_duration_s=args.twist_duration,
                    default_scene=args.scene).start()
    print(f"brave6d ros2: {', '.join(map(str, scenes.names()))} on DDS domain {domain_id} ({args.interface}), "
          f"topics under {node.namespace}/ and /tf; episode logs: {log_dir}", flush=True)
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        stop.wait()
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        node.stop()
        dds.close()
    return 0

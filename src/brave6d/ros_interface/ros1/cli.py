"""``brave6d ros1 BUNDLE_OR_RELEASE``: serve a scene's episodes as the ROS 1 node ``brave6d_sim``.

Needs Debian's ROS 1 packages (``apt-get install python3-rospy python3-rosmaster
python3-sensor-msgs python3-geometry-msgs python3-std-srvs python3-tf2-msgs``). The node talks to
the master at ``--master-uri`` (default ``$ROS_MASTER_URI``, else http://127.0.0.1:11311);
``--start-master`` runs one there first. It binds its own sockets to loopback unless
``ROS_IP``/``ROS_HOSTNAME`` say otherwise. Topics and services: docs/ROS.md.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlparse

from brave6d.core.errors import BraveError
from brave6d.core.runtime import quiet_openmp

if TYPE_CHECKING:
    from brave6d.serve import SourcesOf

DEFAULT_MASTER = "http://127.0.0.1:11311"


def configure(parser: argparse.ArgumentParser) -> None:
    from brave6d.serve import add_mode_flags, limit_arg  # every number bounded at parse time, as the server's

    parser.add_argument("scenes", type=Path, metavar="BUNDLE_OR_RELEASE",
                        help="a bundle folder ('brave6d export') or a dataset release ('brave6d release build')")
    parser.add_argument("--master-uri", default=None,
                        help=f"the ROS master (default: $ROS_MASTER_URI, else {DEFAULT_MASTER})")
    parser.add_argument("--start-master", action="store_true",
                        help="start 'rosmaster --core' on the --master-uri port (loopback) and stop it on exit")
    parser.add_argument("--scene", default=None, help="the scene a reset uses when it names none (a release's scene)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                        help="rasterizer device (auto: cuda when torch sees a GPU)")
    parser.add_argument("--log-dir", type=Path, default=None,
                        help="where episode logs (JSONL) go (default: 'episodes' beside BUNDLE_OR_RELEASE)")
    parser.add_argument("--width", type=limit_arg("width"), default=None, help="image width (default: the bundle's)")
    parser.add_argument("--height", type=limit_arg("height"), default=None, help="image height (default: the bundle's)")
    parser.add_argument("--twist-duration", type=limit_arg("move_duration_s"), default=None,
                        help="seconds each ~cmd_twist message is integrated for (default 0.1: a 10 Hz control loop)")
    parser.add_argument("--agent", default="ros1", help="the agent name written in the episode logs (default ros1)")
    add_mode_flags(parser)  # --training, --log-key: as brave6d serve's
    parser.add_argument("--node-name", default=None, help="the node's name (default brave6d_sim)")
    parser.add_argument("--idle-timeout", type=limit_arg("idle_timeout_s"), default=900.0,
                        help="close an episode idle for this many seconds (default 900)")


def master_uri_of(arg: str | None) -> str:
    uri = arg or os.environ.get("ROS_MASTER_URI") or DEFAULT_MASTER
    parsed = urlparse(uri)
    if parsed.scheme != "http" or not parsed.hostname or not parsed.port:
        raise BraveError(f"--master-uri: must look like http://HOST:PORT, got {uri!r}")
    return uri


def run(args: argparse.Namespace, sources_of: SourcesOf) -> int:
    """Run the node on the scenes ``sources_of(args.scenes, None)`` gives (``brave6d.commands.ros1``
    hands it: a bundle's or a release's)."""
    quiet_openmp()
    from brave6d.ros_interface.ros1.master import RosMaster, master_is_up
    from brave6d.ros_interface.ros1.node import DEFAULT_TWIST_DURATION_S, NODE_NAME
    from brave6d.ros_interface.ros1.ros_env import loopback_environment, require_ros1

    require_ros1()
    uri = master_uri_of(args.master_uri)
    for key, value in loopback_environment(uri).items():  # before rospy reads them
        if os.environ.get(key) != value:
            os.environ[key] = value
    if (args.width is None) != (args.height is None):
        raise BraveError("--width and --height go together")
    master = None
    if args.start_master:
        parsed = urlparse(uri)
        if parsed.hostname not in ("127.0.0.1", "localhost"):
            raise BraveError(f"--start-master starts a master on loopback only; --master-uri names {parsed.hostname}")
        master = RosMaster(int(parsed.port or 11311)).start()
    elif not master_is_up(uri):
        raise BraveError(f"no ROS master answers at {uri}: start one ('rosmaster --core -p PORT', or roscore) "
                         "or pass --start-master")
    try:
        return _serve(args, sources_of, uri, args.node_name or NODE_NAME,
                      args.twist_duration if args.twist_duration is not None else DEFAULT_TWIST_DURATION_S)
    finally:
        if master is not None:
            master.stop()


def _serve(args: argparse.Namespace, sources_of: SourcesOf, uri: str, node_name: str, twist_duration: float) -> int:
    import rospy

    from brave6d.ros_interface.bridge import EpisodeBridge
    from brave6d.ros_interface.ros1.messages import load_messages
    from brave6d.ros_interface.ros1.node import Ros1Node
    from brave6d.serve import EpisodeManager, mode_of, open_scenes, server_log_key

    msgs = load_messages()
    scenes = open_scenes(sources_of(args.scenes, None), device=args.device)
    log_dir = args.log_dir if args.log_dir is not None else Path(args.scenes).resolve().parent / "episodes"
    manager = EpisodeManager(scenes, log_dir, max_episodes=4, idle_timeout_s=args.idle_timeout,
                             mode=mode_of(args), log_key=server_log_key(args.log_key))
    bridge = EpisodeBridge(manager, agent=args.agent, width=args.width, height=args.height)
    rospy.init_node(node_name, anonymous=False)
    node = Ros1Node(bridge, msgs, twist_duration_s=twist_duration, default_scene=args.scene)
    rospy.on_shutdown(lambda: manager.close_all("node shutdown"))
    print(f"brave6d ros1: node {rospy.get_name()} on {uri} (ROS_IP {os.environ.get('ROS_IP', '-')}), scenes "
          f"{', '.join(scenes.names())}, {manager.mode} mode, twist duration {node.twist_duration_s:g} s, "
          f"episode logs {log_dir}; "
          f"messages: PYTHONPATH={msgs.path}", flush=True)
    rospy.spin()
    return 0

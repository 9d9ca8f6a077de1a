"""Where the ROS 2 node can be reached: the DDS settings it starts rclpy with (Fast DDS, the rmw the
``ros2`` extra installs).

Loopback by default. The node's participant gets a Fast DDS profile with two transports: UDPv4
on 127.0.0.1 only (nothing listens on another interface) and shared memory with a 32 MB segment
(an image of 640x480 RGB is 0.9 MB: with Fast DDS's default 0.5 MB segment such a sample falls
back to fragmented UDP, where a best-effort (sensor-data) subscriber loses one image in four).
Discovery uses ROS 2's own setting, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: the node
announces itself to the local participants' unicast ports, which is how an agent started with
ROS 2's defaults (no variable set: ``SUBNET``) on the same machine finds it.

``--allow-remote`` keeps ROS 2's defaults (``SUBNET`` discovery, every interface) and only enlarges
the shared-memory segment; ``--peer HOST`` adds ``ROS_STATIC_PEERS``. A user's own
``FASTDDS_DEFAULT_PROFILES_FILE`` is respected (and then the node cannot promise loopback).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from brave6d.core.atomic import atomic_write
from brave6d.core.errors import BraveError

#: Fast DDS shared-memory segment of the node (bytes): room for several full images in flight.
SHM_SEGMENT_BYTES = 32 * 1024 * 1024
PROFILE_NAME = "brave6d_ros2_node"
DISCOVERY_RANGES = ("OFF", "LOCALHOST", "SUBNET", "SYSTEM_DEFAULT")


def fastdds_profile(loopback: bool) -> str:
    """The Fast DDS XML profile of the node's participant (the default profile of its process)."""
    udp = ("<interfaceWhiteList><address>127.0.0.1</address></interfaceWhiteList>" if loopback else "")
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>brave6d_udp</transport_id>
        <type>UDPv4</type>
        {udp}
      </transport_descriptor>
      <transport_descriptor>
        <transport_id>brave6d_shm</transport_id>
        <type>SHM</type>
        <segment_size>{SHM_SEGMENT_BYTES}</segment_size>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="{PROFILE_NAME}" is_default_profile="true">
      <rtps>
        <userTransports>
          <transport_id>brave6d_shm</transport_id>
          <transport_id>brave6d_udp</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def node_environment(allow_remote: bool, peers: tuple[str, ...] = (), environ: dict[str, str] | None = None,
                     profile_dir: Path | None = None) -> dict[str, str]:
    """The variables to set in the node's process before ``rclpy.init`` (a new dict; ``environ``,
    default ``os.environ``, is not changed). A discovery range wider than LOCALHOST set by the user
    needs ``allow_remote``: refused with the reason otherwise."""
    env = dict(os.environ if environ is None else environ)
    current = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip().upper()
    if current and current not in DISCOVERY_RANGES:
        raise BraveError(f"$ROS_AUTOMATIC_DISCOVERY_RANGE {current!r}: must be one of {', '.join(DISCOVERY_RANGES)}")
    if not allow_remote:
        if current in ("SUBNET", "SYSTEM_DEFAULT"):
            raise BraveError(f"$ROS_AUTOMATIC_DISCOVERY_RANGE={current} would let other hosts reach the node: "
                             "unset it (the node stays on this machine) or pass --allow-remote")
        if current != "OFF":
            env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if peers:
        if not allow_remote and any(p not in ("127.0.0.1", "localhost", "::1") for p in peers):
            raise BraveError(f"--peer {', '.join(peers)}: a remote peer needs --allow-remote")
        env["ROS_STATIC_PEERS"] = ";".join([*filter(None, env.get("ROS_STATIC_PEERS", "").split(";")), *peers])
    if not env.get("FASTDDS_DEFAULT_PROFILES_FILE"):
        folder = profile_dir or Path(tempfile.gettempdir()) / f"brave6d-{os.getuid()}"
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / ("fastdds_loopback.xml" if not allow_remote else "fastdds_remote.xml")
        text = fastdds_profile(loopback=not allow_remote).encode()
        atomic_write(path, lambda f: f.write(text))
        env["FASTDDS_DEFAULT_PROFILES_FILE"] = str(path)
    return env


def apply_environment(env: dict[str, str]) -> None:
    """Set ``env``'s ROS / Fast DDS variables in this process (before ``rclpy.init``)."""
    for key in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS", "FASTDDS_DEFAULT_PROFILES_FILE"):
        if key in env:
            os.environ[key] = env[key]

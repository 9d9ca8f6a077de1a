"""Reaching the Debian ROS 1 packages (``python3-rospy`` and friends) from the project's Python.

Debian installs them under ``/usr/lib/python3/dist-packages``. That folder is *appended* to
``sys.path`` (never prepended: the environment's numpy, yaml, ... keep precedence), and only
when the ROS 1 code path runs. :func:`require_ros1` names the Debian package to install when a
module is missing; the acceptance test skips with the same message.
"""

from __future__ import annotations

import importlib
import os
import sys

from brave6d.core.errors import BraveError

DEBIAN_DIST_PACKAGES = "/usr/lib/python3/dist-packages"
#: Python module -> the Debian package that provides it (what the ROS 1 node and agent import).
REQUIRED_MODULES = {
    "rospy": "python3-rospy",
    "rosgraph": "python3-rosgraph",
    "genpy": "python3-genpy",
    "genmsg": "python3-genmsg",
    "std_msgs.msg": "python3-std-msgs",
    "std_srvs.srv": "python3-std-srvs",
    "geometry_msgs.msg": "python3-geometry-msgs",
    "sensor_msgs.msg": "python3-sensor-msgs",
    "tf2_msgs.msg": "python3-tf2-msgs",
}
#: The Debian packages CI installs (apt pulls in the rest); ``rosmaster`` is the master's executable.
DEBIAN_PACKAGES = ("python3-rospy", "python3-rosmaster", "python3-sensor-msgs", "python3-geometry-msgs",
                   "python3-std-srvs", "python3-tf2-msgs")
ROSMASTER = "/usr/bin/rosmaster"


def add_debian_path() -> None:
    """Append Debian's dist-packages to ``sys.path`` (once; after the environment's own packages)."""
    if DEBIAN_DIST_PACKAGES not in sys.path:
        sys.path.append(DEBIAN_DIST_PACKAGES)


def missing_ros1(import_modules: bool = True) -> list[str]:
    """The Debian packages whose modules cannot be imported (empty when ROS 1 is usable).
    ``import_modules=False`` only looks for their files (nothing imported, ``sys.path`` untouched:
    what a test's skip condition wants)."""
    if import_modules:
        add_debian_path()
    missing = []
    for module, package in REQUIRED_MODULES.items():
        if not import_modules:
            base = os.path.join(DEBIAN_DIST_PACKAGES, *module.split("."))
            if not (os.path.isfile(os.path.join(base, "__init__.py")) or os.path.isfile(base + ".py")):
                missing.append(package)
            continue
        try:
            importlib.import_module(module)
        except ImportError:
            missing.append(package)
    if not os.path.exists(ROSMASTER):
        missing.append("python3-rosmaster")
    return sorted(set(missing))


def require_ros1() -> None:
    """Make rospy importable, or raise one line naming the Debian packages to install."""
    missing = missing_ros1()
    if missing:
        raise BraveError("ROS 1 is not installed: apt-get install " + " ".join(missing)
                         + f" (Debian's ROS 1 packages, reached through {DEBIAN_DIST_PACKAGES})")


def loopback_environment(master_uri: str, environ: dict[str, str] | None = None) -> dict[str, str]:
    """``environ`` with the ROS 1 master URI set and, unless the user set one, ``ROS_IP=127.0.0.1``
    (rospy then binds its sockets to loopback only)."""
    env = dict(os.environ if environ is None else environ)
    env["ROS_MASTER_URI"] = master_uri
    if not env.get("ROS_IP") and not env.get("ROS_HOSTNAME"):
        env["ROS_IP"] = "127.0.0.1"
    return env

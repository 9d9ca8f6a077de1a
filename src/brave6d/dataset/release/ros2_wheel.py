"""The ROS 2 interfaces wheel in a release, so an agent's environment needs only ``pip install`` (docs/ROS.md).

``brave6d release build`` writes ``brave6d_ros2_interfaces-<version>-<tag>.whl``
(:mod:`brave6d.ros_interface.ros2.interfaces`: ``brave6d_msgs`` and ``tf2_msgs``, requiring the ROS 2
runtime wheels it was compiled against) into the release when a ROS 2 Python with the build wheels
is at hand: ``$BRAVE6D_ROS2_PYTHON``, else the building Python itself. Without one the build log
says why and the release ships without the wheel: it is a convenience, never a reason to fail.
The manifest's ``ros2_interfaces`` entry records the file, its SHA-256, version and tag;
``release verify`` checks the file against it, that its directory is the interfaces wheel's, and that
it holds nothing that runs when installed or at Python's start (:func:`wheel_member_problem`: no
``.pth`` file, no top-level module, no scripts, headers or entry points); it never installs it.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import re
import sys
from pathlib import Path
from typing import Any

from brave6d.core.atomic import file_sha256
from brave6d.core.errors import BraveError
from brave6d.dataset.release.source import ReleaseError
from brave6d.dataset.release.zips import open_zip

log = logging.getLogger(__name__)

#: The ROS 2 environment's Python (the variable the ROS 2 tests and benchmarks use too).
ROS2_PYTHON_ENV = "BRAVE6D_ROS2_PYTHON"
#: The manifest's entry.
ENTRY = "ros2_interfaces"
#: The wheel's distribution name.
WHEEL_DISTRIBUTION = "brave6d_ros2_interfaces"
WHEEL_NAME = re.compile(r"brave6d_ros2_interfaces-(?P<version>[0-9][0-9A-Za-z.+]*)-(?P<tag>cp\d+-cp\d+-[0-9A-Za-z_]+)\.whl")


def ros2_python() -> str | None:
    """``$BRAVE6D_ROS2_PYTHON``, else this Python when it has rclpy and the rosidl generators, else None."""
    if os.environ.get(ROS2_PYTHON_ENV):
        return os.environ[ROS2_PYTHON_ENV]
    if all(importlib.util.find_spec(m) is not None for m in ("rclpy", "rosidl_generator_c")):
        return sys.executable
    return None


def build_interfaces_wheel(out_dir: Path) -> dict[str, Any] | None:
    """Write the interfaces wheel into ``out_dir``; the manifest's entry, or None (logged) when no
    ROS 2 Python can build it."""
    python = ros2_python()
    if python is None:
        log.warning("release: no ROS 2 interfaces wheel: this Python has no ROS 2 wheels and $%s is not set "
                    "(e.g. %s=.venv-ros2/bin/python); the release ships without it", ROS2_PYTHON_ENV, ROS2_PYTHON_ENV)
        return None
    from brave6d.ros_interface import build_ros2_interfaces_wheel

    try:
        wheel = build_ros2_interfaces_wheel(out_dir, python=python)
    except BraveError as exc:
        log.warning("release: no ROS 2 interfaces wheel (%s): %s", python, exc)
        return None
    match = WHEEL_NAME.fullmatch(wheel.name)
    assert match is not None, wheel.name
    log.info("release: ROS 2 interfaces wheel %s", wheel.name)
    return {"wheel": wheel.name, "sha256": file_sha256(wheel), "version": match["version"], "tag": match["tag"]}


#: The only files of the wheel's ``.dist-info`` (what :mod:`brave6d.ros_interface.ros2.interfaces` writes).
DIST_INFO_FILES = ("METADATA", "WHEEL", "RECORD", "top_level.txt")
_PACKAGE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: Modules Python imports by itself at every start, from any folder of the path.
_STARTUP_MODULES = ("sitecustomize", "usercustomize")


def wheel_member_problem(member: str, version: str) -> str | None:
    """Why ``member`` must not be in the interfaces wheel of ``version``, or None. Allowed: files of
    its packages (a first folder that is a Python name), its libraries (``.data/data/lib/*.so*``)
    and the four metadata files. Refused: a ``.pth`` anywhere (pip installs one into site-packages,
    where Python runs its import lines at every start), a top-level module (``sitecustomize`` and
    the like run at every start too), scripts, headers, entry points and anything else pip would
    install beside the packages (install hooks)."""
    parts = member.rstrip("/").split("/")
    if parts[-1].endswith(".pth"):
        return "a .pth file (once installed, Python runs its import lines at every start)"
    dist = f"{WHEEL_DISTRIBUTION}-{version}"
    if parts[0] == f"{dist}.dist-info":
        if member.endswith("/") and len(parts) == 1 or len(parts) == 2 and parts[1] in DIST_INFO_FILES:
            return None
        return "not one of the wheel's metadata files (entry points and scripts run code once installed)"
    if parts[0] == f"{dist}.data":
        if parts[1:3] == ["data", "lib"] and (member.endswith("/") or len(parts) == 4 and ".so" in parts[3]):
            return None
        return "installs outside the wheel's packages and libraries (scripts, headers and data are install hooks)"
    if len(parts) == 1 and not member.endswith("/"):
        return "a top-level module (Python imports sitecustomize and usercustomize at every start)"
    if _PACKAGE.fullmatch(parts[0]) is None or parts[0] in _STARTUP_MODULES:
        return f"{parts[0]!r} is not a Python package name"
    return None


def check_interfaces_wheel(base: Path, sums: dict[str, str], manifest: dict[str, Any], manifest_name: str) -> str | None:
    """Verify the release's interfaces wheel against the manifest's entry (none without an entry);
    returns the wheel's name."""
    wheels = sorted(n for n in sums if n.endswith(".whl"))
    entry = manifest.get(ENTRY)
    if entry is None:
        for name in wheels:
            raise ReleaseError(f"{base / name}: in the release, but {manifest_name} has no '{ENTRY}' entry for it")
        return None
    if not isinstance(entry, dict) or not all(isinstance(entry.get(k), str) for k in ("wheel", "sha256", "version")):
        raise ReleaseError(f"{manifest_name}: field '{ENTRY}': 'wheel', 'sha256' and 'version' (strings) are required")
    name = entry["wheel"]
    match = WHEEL_NAME.fullmatch(name)
    if match is None or match["version"] != entry["version"]:
        raise ReleaseError(f"{manifest_name}: field '{ENTRY}.wheel': {name[:200]!r} is not an interfaces wheel "
                           f"of version {entry['version'][:50]!r}")
    for other in wheels:
        if other != name:
            raise ReleaseError(f"{base / other}: in the release, but {manifest_name}'s '{ENTRY}' names {name}")
    if name not in sums:
        raise ReleaseError(f"{base / name}: required by {manifest_name} ({ENTRY}) but not in the release")
    if sums[name] != entry["sha256"]:
        raise ReleaseError(f"{base / name}: sha256 {sums[name][:12]}... does not match {manifest_name}'s "
                           f"{ENTRY}.sha256 ({entry['sha256'][:12]}...); the wheel was altered")
    metadata = f"brave6d_ros2_interfaces-{entry['version']}.dist-info/METADATA"
    with open_zip(base / name, shown=name) as zf:
        for member in (metadata, "brave6d_msgs/__init__.py"):
            if member not in zf.names:
                raise ReleaseError(f"{name}:{member}: missing (not the interfaces wheel {entry['version']})")
        for member in zf.names:
            problem = wheel_member_problem(member, entry["version"])
            if problem is not None:
                raise ReleaseError(f"{name}:{member}: {problem}; the interfaces wheel holds its packages, their "
                                   "libraries and its metadata only")
        for member in zf.names:  # every member's length and CRC, streamed
            for _ in zf.chunks(member):
                pass
    return name

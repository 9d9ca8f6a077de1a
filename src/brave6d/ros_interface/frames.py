"""ROS conventions of the bridge, as plain numpy: frame names, poses as (position, quaternion
x-y-z-w), camera-info arrays and REP 118 depth.

Frames (REP 103/105: metres, radians, right-handed):

* ``world``: the robot base frame of the scene (z up), the parent of every transform;
* ``brave6d_camera_optical_frame``: the camera, optical convention (x right, y down, z forward,
  REP 103's ``_optical`` suffix), the frame of every image, camera info and estimate;
* ``gt/<name>_<gt_id>``: an object instance's ground-truth pose, under a ``gt/`` namespace so that
  no agent takes it for a sensor or a perception output.

Both ROS generations build their messages from these functions, so they agree to the bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.errors import BraveError, NonRigidTransformError
from brave6d.core.transforms import unit_quaternion

FRAME_WORLD = "world"
FRAME_CAMERA_OPTICAL = "brave6d_camera_optical_frame"
#: Namespace of the ground-truth object frames (``gt/<name>_<gt_id>``).
GT_FRAME_PREFIX = "gt/"
#: Depth images' value for "no data" (REP 118: NaN is an invalid or missing measurement).
DEPTH_NO_DATA = float("nan")


def gt_frame(name: str, gt_id: int) -> str:
    """The tf frame of ground-truth instance ``gt_id`` of object ``name``: ``gt/<name>_<gt_id>``."""
    return f"{GT_FRAME_PREFIX}{name}_{int(gt_id)}"


def matrix_to_pose(T: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """4x4 rigid transform -> (position xyz metres, unit quaternion x, y, z, w with w >= 0)."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise BraveError(f"pose: must be a finite 4x4 matrix, got shape {M.shape}")
    q = Rotation.from_matrix(M[:3, :3]).as_quat(canonical=True)
    return M[:3, 3].copy(), q / np.linalg.norm(q)


def pose_to_matrix(position: ArrayLike, quaternion_xyzw: ArrayLike, field: str = "pose") -> NDArray[np.float64]:
    """(position xyz, quaternion x, y, z, w) -> 4x4 rigid transform. The quaternion must be finite
    with unit norm within :data:`brave6d.core.transforms.QUATERNION_TOLERANCE` (a zero quaternion, ROS's uninitialised
    default, is refused naming ``field``); it is normalised before use."""
    p = np.asarray(position, dtype=np.float64).reshape(-1)
    q = np.asarray(quaternion_xyzw, dtype=np.float64).reshape(-1)
    if p.size != 3 or not np.all(np.isfinite(p)):
        raise BraveError(f"{field}.position: must be 3 finite numbers (metres), got {p.tolist()}")
    try:
        unit = unit_quaternion(q, f"{field}.orientation")
    except NonRigidTransformError as exc:
        zero = "; a zero quaternion is ROS's uninitialised default" if np.all(q == 0) else ""
        raise BraveError(f"{exc}{zero}") from None
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(unit).as_matrix()
    T[:3, 3] = p
    return T


def camera_info_arrays(K: ArrayLike) -> dict[str, Any]:
    """``sensor_msgs/CameraInfo``'s arrays for an undistorted pinhole image with intrinsics ``K``:
    plumb_bob with zero distortion, identity rectification, ``P = [K | 0]`` (a monocular camera)."""
    K3 = np.asarray(K, dtype=np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K3
    return {"distortion_model": "plumb_bob", "D": [0.0] * 5, "K": K3.reshape(-1).tolist(),
            "R": np.eye(3).reshape(-1).tolist(), "P": P.reshape(-1).tolist()}


def depth_to_rep118(depth_m: ArrayLike) -> NDArray[np.float32]:
    """Depth in metres for a ``32FC1`` image: the server's 0 ("no data") becomes NaN (REP 118)."""
    d = np.array(depth_m, dtype=np.float32, copy=True)
    d[~(d > 0)] = DEPTH_NO_DATA
    return d


def stamp_parts(stamp_ns: int) -> tuple[int, int]:
    """A nanosecond stamp as ROS's (secs, nsecs)."""
    return int(stamp_ns) // 1_000_000_000, int(stamp_ns) % 1_000_000_000


"""Bridge values <-> ROS 2 messages: images, camera info and tf from a :class:`BridgeStep`, poses,
twists and estimates from what an agent sends. Frames and conventions come from
:mod:`brave6d.ros_interface.frames` (shared with ROS 1), so both generations publish the same numbers."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.ros_interface.bridge import BridgeStep, Estimate
from brave6d.ros_interface.frames import (
    FRAME_CAMERA_OPTICAL,
    FRAME_WORLD,
    camera_info_arrays,
    depth_to_rep118,
    matrix_to_pose,
    pose_to_matrix,
)
from brave6d.ros_interface.ros2 import messages as m


def header(stamp_ns: int, frame_id: str) -> m.Header:
    return m.Header(stamp=m.stamp_from_ns(stamp_ns), frame_id=frame_id)


def rgb_image(step: BridgeStep) -> m.Image:
    """``rgb8`` image of the step, in the camera optical frame."""
    rgb = np.ascontiguousarray(step.rgb, dtype=np.uint8)
    h, w = rgb.shape[:2]
    return m.Image(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=h, width=w, encoding="rgb8",
                   is_bigendian=0, step=3 * w, data=rgb.tobytes())


def depth_image(step: BridgeStep) -> m.Image:
    """``32FC1`` depth in metres (REP 118: NaN where there is no data), little-endian."""
    depth = np.ascontiguousarray(depth_to_rep118(step.depth_m).astype("<f4"))
    h, w = depth.shape
    return m.Image(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=h, width=w, encoding="32FC1",
                   is_bigendian=0, step=4 * w, data=depth.tobytes())


def camera_info(step: BridgeStep) -> m.CameraInfo:
    """The pinhole camera of the step's images (undistorted: plumb_bob with zero distortion)."""
    a = camera_info_arrays(step.K)
    return m.CameraInfo(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=step.height, width=step.width,
                        distortion_model=a["distortion_model"], d=list(a["D"]), k=list(a["K"]), r=list(a["R"]),
                        p=list(a["P"]))


def transform_stamped(T: Any, parent: str, child: str, stamp_ns: int) -> m.TransformStamped:
    position, q = matrix_to_pose(T)
    return m.TransformStamped(
        header=header(stamp_ns, parent), child_frame_id=child,
        transform=m.Transform(translation=m.Vector3(*map(float, position)), rotation=m.Quaternion(*map(float, q))))


def tf_message(step: BridgeStep) -> m.TFMessage:
    """``world -> brave6d_camera_optical_frame`` and ``world -> gt/<name>_<gt_id>`` per object."""
    transforms = [transform_stamped(step.world_T_cam, FRAME_WORLD, FRAME_CAMERA_OPTICAL, step.stamp_ns)]
    transforms += [transform_stamped(o.world_T_obj, FRAME_WORLD, o.frame, step.stamp_ns) for o in step.objects]
    return m.TFMessage(transforms=transforms)


def pose_to_msg(T: Any) -> m.Pose:
    position, q = matrix_to_pose(T)
    return m.Pose(position=m.Point(*map(float, position)), orientation=m.Quaternion(*map(float, q)))


def pose_from_msg(pose: m.Pose, field: str) -> NDArray[np.float64]:
    p, q = pose.position, pose.orientation
    return pose_to_matrix((p.x, p.y, p.z), (q.x, q.y, q.z, q.w), field)


def camera_pose_from_msg(msg: m.PoseStamped, topic: str) -> NDArray[np.float64]:
    """``world_T_cam`` from a ``PoseStamped`` in ``world`` (an empty frame_id means world)."""
    frame = msg.header.frame_id.lstrip("/")
    if frame not in ("", FRAME_WORLD):
        raise BraveError(f"{topic}: header.frame_id {msg.header.frame_id!r}: camera poses are given in "
                         f"{FRAME_WORLD!r} (no tf lookup is done)")
    return pose_from_msg(msg.pose, f"{topic}.pose")


#: Twist frames accepted by the node and the ``move`` frame each means.
TWIST_FRAMES = {"": "camera", FRAME_CAMERA_OPTICAL: "camera", FRAME_WORLD: "world"}


def twist_from_msg(msg: m.TwistStamped, topic: str) -> tuple[list[float], list[float], str]:
    """(linear m/s, angular rad/s, move frame) from a ``TwistStamped`` in the camera optical frame
    (empty frame_id) or in ``world``."""
    frame = msg.header.frame_id.lstrip("/")
    if frame not in TWIST_FRAMES:
        raise BraveError(f"{topic}: header.frame_id {msg.header.frame_id!r}: must be {FRAME_CAMERA_OPTICAL!r} "
                         f"(or empty) or {FRAME_WORLD!r}")
    lin, ang = msg.twist.linear, msg.twist.angular
    return [lin.x, lin.y, lin.z], [ang.x, ang.y, ang.z], TWIST_FRAMES[frame]


def estimates_from_msg(msg: m.ObjectEstimateArray, topic: str) -> list[Estimate]:
    """Estimates in the camera optical frame of the current view (the header's frame; empty = that)."""
    frame = msg.header.frame_id.lstrip("/")
    if frame not in ("", FRAME_CAMERA_OPTICAL):
        raise BraveError(f"{topic}: header.frame_id {msg.header.frame_id!r}: estimates are given in "
                         f"{FRAME_CAMERA_OPTICAL!r}")
    return [Estimate(int(e.obj_id), pose_from_msg(e.pose, f"{topic}.estimates.{i}.pose"), float(e.score))
            for i, e in enumerate(msg.estimates)]


def estimates_to_msg(estimates: list[Estimate], stamp_ns: int = 0) -> m.ObjectEstimateArray:
    return m.ObjectEstimateArray(header=header(stamp_ns, FRAME_CAMERA_OPTICAL),
                               estimates=[m.ObjectEstimate(obj_id=int(e.obj_id), pose=pose_to_msg(e.cam_T_obj),
                                                         score=float(e.score)) for e in estimates])


def image_to_array(msg: m.Image) -> NDArray[Any]:
    """An ``rgb8`` (HxWx3 uint8) or ``32FC1`` (HxW float32) image message as an array."""
    if msg.encoding == "rgb8":
        return np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)[:, :3 * msg.width].reshape(
            msg.height, msg.width, 3)
    if msg.encoding == "32FC1":
        dtype = ">f4" if msg.is_bigendian else "<f4"
        rows = np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)[:, :4 * msg.width]
        return rows.copy().view(dtype).reshape(msg.height, msg.width).astype(np.float32)
    raise BraveError(f"image encoding {msg.encoding!r}: only rgb8 and 32FC1 are read here")


def transform_to_matrix(t: m.TransformStamped) -> NDArray[np.float64]:
    tr, q = t.transform.translation, t.transform.rotation
    return pose_to_matrix((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w), f"tf {t.child_frame_id}")

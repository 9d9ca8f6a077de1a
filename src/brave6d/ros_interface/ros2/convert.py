"""Bridge values <-> ROS 2 messages (rclpy's own classes): images, camera info, tf and the services'
Step answer from a :class:`BridgeStep`; poses, twists and estimates from what an agent sends, as
the fields the HTTP API validates. Frames and conventions come from
:mod:`brave6d.ros_interface.frames` (shared with ROS 1), so both generations publish the same numbers.
Import only where rclpy and the generated ``brave6d_msgs`` / ``tf2_msgs`` are installed."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, Quaternion, Transform, TransformStamped, Vector3
from numpy.typing import NDArray
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from brave6d.core.errors import BraveError
from brave6d.ros_interface.bridge import BridgeStep, Estimate
from brave6d.ros_interface.frames import (
    FRAME_CAMERA_OPTICAL,
    FRAME_WORLD,
    camera_info_arrays,
    depth_to_rep118,
    matrix_to_pose,
    pose_to_matrix,
    stamp_parts,
)


def stamp(stamp_ns: int) -> Time:
    sec, nanosec = stamp_parts(stamp_ns)
    return Time(sec=sec, nanosec=nanosec)


def stamp_to_ns(t: Time) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def header(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=stamp(stamp_ns), frame_id=frame_id)


def rgb_image(step: BridgeStep) -> Image:
    """``rgb8`` image of the step, in the camera optical frame."""
    rgb = np.ascontiguousarray(step.rgb, dtype=np.uint8)
    h, w = rgb.shape[:2]
    return Image(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=h, width=w, encoding="rgb8",
                 is_bigendian=0, step=3 * w, data=rgb.tobytes())


def depth_image(step: BridgeStep) -> Image:
    """``32FC1`` depth in metres (REP 118: NaN where there is no data), little-endian."""
    depth = np.ascontiguousarray(depth_to_rep118(step.depth_m).astype("<f4"))
    h, w = depth.shape
    return Image(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=h, width=w, encoding="32FC1",
                 is_bigendian=0, step=4 * w, data=depth.tobytes())


def camera_info(step: BridgeStep) -> CameraInfo:
    """The pinhole camera of the step's images (undistorted: plumb_bob with zero distortion)."""
    a = camera_info_arrays(step.K)
    return CameraInfo(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=step.height, width=step.width,
                      distortion_model=a["distortion_model"], d=[float(v) for v in a["D"]],
                      k=[float(v) for v in a["K"]], r=[float(v) for v in a["R"]], p=[float(v) for v in a["P"]])


def pose_msg(T: Any) -> Pose:
    position, q = matrix_to_pose(T)
    x, y, z = map(float, position)
    qx, qy, qz, qw = map(float, q)
    return Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))


def transform_stamped(T: Any, parent: str, child: str, stamp_ns: int) -> TransformStamped:
    p = pose_msg(T)
    return TransformStamped(header=header(stamp_ns, parent), child_frame_id=child,
                            transform=Transform(translation=Vector3(x=p.position.x, y=p.position.y, z=p.position.z),
                                                rotation=p.orientation))


def tf_message(step: BridgeStep) -> TFMessage:
    """``world -> brave6d_camera_optical_frame`` and, in training mode, ``world -> gt/<name>_<gt_id>`` per
    object (a scored step has no objects)."""
    transforms = [transform_stamped(step.world_T_cam, FRAME_WORLD, FRAME_CAMERA_OPTICAL, step.stamp_ns)]
    transforms += [transform_stamped(o.world_T_obj, FRAME_WORLD, o.frame, step.stamp_ns) for o in step.objects]
    return TFMessage(transforms=transforms)


def fill_step(msg: Any, step: BridgeStep) -> Any:
    """Fill a ``brave6d_msgs/Step`` from the bridge's step (the status JSON included)."""
    target = step.target_ref
    msg.episode_id = step.episode_id
    msg.step = int(step.step)
    msg.accepted = bool(step.accepted)
    msg.collided = bool(step.collided)
    msg.refusal = step.refusal or ""
    msg.adjustments = int(step.adjustments)
    msg.stamp = stamp(step.stamp_ns)
    msg.camera_pose = pose_msg(step.world_T_cam)
    msg.target_frame = step.target_frame  # "" in scored mode: no gt/ frame is published
    msg.target_obj_id = -1 if target is None else int(target.obj_id)
    msg.status_json = json.dumps(step.status())
    return msg


def pose_fields(pose: Pose) -> dict[str, list[float]]:
    """A ``geometry_msgs/Pose`` as the HTTP API's pose (position + quaternion_wxyz), to validate."""
    p, q = pose.position, pose.orientation
    return {"position": [p.x, p.y, p.z], "quaternion_wxyz": [q.w, q.x, q.y, q.z]}


def check_frame(frame_id: str, allowed: dict[str, str], where: str) -> str:
    """The meaning of ``frame_id`` in ``allowed`` (frame -> meaning), else one line naming the field."""
    frame = frame_id.lstrip("/")
    if frame not in allowed:
        names = " or ".join(repr(f) for f in allowed if f) + (" (or empty)" if "" in allowed else "")
        raise BraveError(f"{where}: header.frame_id {frame_id[:80]!r}: must be {names}")
    return allowed[frame]


#: Frames of a set_pose and what they mean.
POSE_FRAMES = {"": "world", FRAME_WORLD: "world"}
#: Twist frames accepted by the node and the ``move`` frame each means.
TWIST_FRAMES = {"": "camera", FRAME_CAMERA_OPTICAL: "camera", FRAME_WORLD: "world"}
#: Frames of submitted estimates.
ESTIMATE_FRAMES = {"": "camera", FRAME_CAMERA_OPTICAL: "camera"}


def estimate_fields(e: Any, where: str) -> dict[str, Any]:
    """One ``brave6d_msgs/ObjectEstimate`` as the HTTP API's estimate (R row-major, t_m, score);
    a quaternion that is not unit (or not finite) is refused naming the estimate."""
    p, q = e.pose.position, e.pose.orientation
    try:
        T = pose_to_matrix((p.x, p.y, p.z), (q.x, q.y, q.z, q.w), where)
    except (TypeError, ValueError) as exc:
        raise BraveError(str(exc) if str(exc).startswith(where) else f"{where}: {exc}") from None
    return {"obj_id": int(e.obj_id), "R": T[:3, :3].reshape(-1).tolist(), "t_m": T[:3, 3].tolist(),
            "score": float(e.score)}


def estimates_to_msgs(estimates: list[Estimate], cls: type) -> list[Any]:
    """``brave6d_msgs/ObjectEstimate`` messages (``cls``) of bridge estimates."""
    return [cls(obj_id=int(e.obj_id), pose=pose_msg(e.cam_T_obj), score=float(e.score)) for e in estimates]


def image_to_array(msg: Image) -> NDArray[Any]:
    """An ``rgb8`` (HxWx3 uint8) or ``32FC1`` (HxW float32) image message as an array."""
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if msg.encoding == "rgb8":
        return data.reshape(msg.height, msg.step)[:, :3 * msg.width].reshape(msg.height, msg.width, 3)
    if msg.encoding == "32FC1":
        dtype = ">f4" if msg.is_bigendian else "<f4"
        rows = data.reshape(msg.height, msg.step)[:, :4 * msg.width]
        return rows.copy().view(dtype).reshape(msg.height, msg.width).astype(np.float32)
    raise BraveError(f"image encoding {msg.encoding!r}: only rgb8 and 32FC1 are read here")


def transform_to_matrix(t: TransformStamped) -> NDArray[np.float64]:
    tr, q = t.transform.translation, t.transform.rotation
    return pose_to_matrix((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w), f"tf {t.child_frame_id}")

"""Bridge values <-> ROS 1 messages (rospy classes), following brave6d.ros_interface.frames' conventions.

Outgoing (one :class:`~brave6d.ros_interface.bridge.BridgeStep` -> every message of its observation, all
with the step's stamp): ``sensor_msgs/Image`` rgb8 and 32FC1 (metres, NaN = no data, REP 118),
``sensor_msgs/CameraInfo`` (plumb_bob, zero distortion), ``tf2_msgs/TFMessage`` (world -> camera and,
in training mode only, world -> gt/<name>_<gt_id>) and ``brave6d_msgs/EpisodeStatus``. Incoming: ``PoseStamped`` (frame
"world") -> world_T_cam, ``TwistStamped`` -> (linear, angular, frame), ``ObjectEstimate[]`` ->
:class:`~brave6d.ros_interface.bridge.Estimate`. A message that breaks a convention raises a
:class:`BraveError` naming the topic and field.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.ros_interface.bridge import BridgeStep, Estimate, EpisodeResult
from brave6d.serve import MAX_HEIGHT, MAX_WIDTH
from brave6d.ros_interface.frames import (
    FRAME_CAMERA_OPTICAL,
    FRAME_WORLD,
    camera_info_arrays,
    depth_to_rep118,
    matrix_to_pose,
    pose_to_matrix,
    stamp_parts,
)

#: The frame_ids a TwistStamped may name, and the bridge's name for each ("" = the camera).
TWIST_FRAMES = {FRAME_CAMERA_OPTICAL: "camera", "": "camera", FRAME_WORLD: "world"}


def ros_time(stamp_ns: int) -> Any:
    import rospy

    secs, nsecs = stamp_parts(stamp_ns)
    return rospy.Time(secs, nsecs)


def header(stamp_ns: int, frame_id: str) -> Any:
    from std_msgs.msg import Header

    return Header(stamp=ros_time(stamp_ns), frame_id=frame_id)


def stamp_ns_of(h: Any) -> int:
    return int(h.stamp.secs) * 1_000_000_000 + int(h.stamp.nsecs)


def rgb_image(step: BridgeStep) -> Any:
    from sensor_msgs.msg import Image

    rgb = np.ascontiguousarray(step.rgb, dtype=np.uint8)
    return Image(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=step.height, width=step.width,
                 encoding="rgb8", is_bigendian=0, step=3 * step.width, data=rgb.tobytes())


def depth_image(step: BridgeStep) -> Any:
    from sensor_msgs.msg import Image

    depth = np.ascontiguousarray(depth_to_rep118(step.depth_m), dtype="<f4")
    return Image(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=step.height, width=step.width,
                 encoding="32FC1", is_bigendian=0, step=4 * step.width, data=depth.tobytes())


def camera_info(step: BridgeStep) -> Any:
    from sensor_msgs.msg import CameraInfo

    a = camera_info_arrays(step.K)
    return CameraInfo(header=header(step.stamp_ns, FRAME_CAMERA_OPTICAL), height=step.height, width=step.width,
                      distortion_model=a["distortion_model"], D=a["D"], K=a["K"], R=a["R"], P=a["P"])


def transform(stamp_ns: int, parent: str, child: str, parent_T_child: NDArray[np.float64]) -> Any:
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3

    p, q = matrix_to_pose(parent_T_child)
    return TransformStamped(header=header(stamp_ns, parent), child_frame_id=child,
                            transform=Transform(translation=Vector3(*p.tolist()), rotation=Quaternion(*q.tolist())))


def tf_message(step: BridgeStep) -> Any:
    """world -> the camera's optical frame, and world -> each object's ground-truth frame (training mode:
    a scored step has no objects)."""
    from tf2_msgs.msg import TFMessage

    transforms = [transform(step.stamp_ns, FRAME_WORLD, FRAME_CAMERA_OPTICAL, step.world_T_cam)]
    transforms += [transform(step.stamp_ns, FRAME_WORLD, o.frame, o.world_T_obj) for o in step.objects]
    return TFMessage(transforms=transforms)


def status_message(msgs: Any, step: BridgeStep) -> Any:
    ref = step.refusal_detail or {}
    return msgs.msg.EpisodeStatus(
        header=header(step.stamp_ns, FRAME_WORLD), episode_id=step.episode_id, action=step.action,
        step=step.step, accepted=step.accepted, collided=step.collided, refusal_reason=ref.get("reason") or "",
        refusal_message=ref.get("message") or "", refusal_box=ref.get("box") or "", adjustments=step.adjustments,
        target_frame=step.target_frame, error="", json=json.dumps(step.status()))


def error_status(msgs: Any, stamp_ns: int, episode_id: str | None, error: str) -> Any:
    return msgs.msg.EpisodeStatus(header=header(stamp_ns, FRAME_WORLD), episode_id=episode_id or "",
                                  action="error", error=error, json=json.dumps({"error": error}))


def _point(p: Any) -> list[float]:
    return [float(p.x), float(p.y), float(p.z)]


def _quat(q: Any) -> list[float]:
    return [float(q.x), float(q.y), float(q.z), float(q.w)]


def pose_matrix(pose: Any, field: str) -> NDArray[np.float64]:
    """``geometry_msgs/Pose`` -> 4x4 (a non-unit quaternion is refused naming ``field``)."""
    return pose_to_matrix(_point(pose.position), _quat(pose.orientation), field)


def pose_message(T: NDArray[np.float64]) -> Any:
    from geometry_msgs.msg import Point, Pose, Quaternion

    p, q = matrix_to_pose(T)
    return Pose(position=Point(*p.tolist()), orientation=Quaternion(*q.tolist()))


def world_T_cam_from(msg: Any, topic: str) -> NDArray[np.float64]:
    """A ``PoseStamped`` on ``topic`` -> world_T_cam; its frame_id must be "world"."""
    if msg.header.frame_id != FRAME_WORLD:
        raise BraveError(f"{topic}: header.frame_id must be '{FRAME_WORLD}' (the camera's optical-frame pose in the "
                         f"world), got {msg.header.frame_id!r}")
    return pose_matrix(msg.pose, f"{topic}: pose")


def twist_from(msg: Any, topic: str) -> tuple[list[float], list[float], str]:
    """A ``TwistStamped`` on ``topic`` -> (linear m/s, angular rad/s, "camera" | "world")."""
    frame = TWIST_FRAMES.get(msg.header.frame_id)
    if frame is None:
        raise BraveError(f"{topic}: header.frame_id must be '{FRAME_CAMERA_OPTICAL}' (or empty) or '{FRAME_WORLD}', "
                         f"got {msg.header.frame_id!r}")
    linear, angular = _point(msg.twist.linear), _point(msg.twist.angular)
    if not all(math.isfinite(v) for v in linear + angular):
        raise BraveError(f"{topic}: twist must be finite, got linear {linear}, angular {angular}")
    return linear, angular, frame


def estimates_from(request: Any, service: str) -> list[Estimate]:
    """A ``SubmitEstimates`` request -> estimates (its frame_id: the camera's optical frame or empty)."""
    if request.header.frame_id not in (FRAME_CAMERA_OPTICAL, ""):
        raise BraveError(f"{service}: header.frame_id must be '{FRAME_CAMERA_OPTICAL}' (estimates are in the camera "
                         f"frame of the current view), got {request.header.frame_id!r}")
    return [Estimate(int(e.obj_id), pose_matrix(e.pose, f"{service}: estimates[{i}].pose"), float(e.score))
            for i, e in enumerate(request.estimates)]


def result_response(msgs: Any, result: EpisodeResult) -> Any:
    nan = float("nan")
    return msgs.srv.SubmitEstimatesResponse(
        success=True, message=f"episode {result.episode_id} submitted: AR {result.ar:.4f}",
        episode_id=result.episode_id, ar=result.ar,
        ar_vsd=nan if result.ar_vsd is None else result.ar_vsd, ar_mssd=nan if result.ar_mssd is None else result.ar_mssd,
        ar_mspd=nan if result.ar_mspd is None else result.ar_mspd, adjustments=result.adjustments, steps=result.steps,
        refusals=result.refusals, submitted=result.submitted, json=json.dumps(result.to_json()))


def image_array(msg: Any, max_pixels: int = MAX_WIDTH * MAX_HEIGHT) -> NDArray[Any]:
    """A ``sensor_msgs/Image`` (rgb8 or 32FC1) as a numpy array (for agents). The node is not trusted:
    its size (at most ``max_pixels``), row step and data length must agree, else :class:`BraveError`."""
    if msg.encoding not in ("rgb8", "32FC1"):
        raise BraveError(f"image encoding {str(msg.encoding)[:40]!r} is not handled here (rgb8 and 32FC1 are)")
    pixel = 3 if msg.encoding == "rgb8" else 4
    height, width, step = msg.height, msg.width, msg.step
    if not (0 < width and 0 < height and width * height <= max_pixels and step >= pixel * width
            and step % pixel == 0 and len(msg.data) == height * step):
        raise BraveError(f"image {width}x{height} ({msg.encoding}, step {step}, {len(msg.data)} bytes): its size, "
                         f"row step and data disagree or it has more than {max_pixels} pixels")
    if msg.encoding == "rgb8":
        return np.frombuffer(msg.data, dtype=np.uint8).reshape(height, step)[:, : 3 * width].reshape(height, width, 3)
    dtype = ">f4" if msg.is_bigendian else "<f4"
    return np.frombuffer(msg.data, dtype=dtype).reshape(height, step // 4)[:, :width].astype(np.float32)

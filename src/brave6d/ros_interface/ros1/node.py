"""The ``brave6d_sim`` rospy node: the bridge's episodes as ROS 1 topics and services.

Every action (``~reset``, a ``~set_pose`` or ``~cmd_twist`` message) produces one observation,
published with one stamp on: ``~rgb/image_raw``, ``~depth/image_raw``, ``~rgb/camera_info``,
``~depth/camera_info``, ``/tf`` and, last, ``~status``. A message the node cannot use (wrong
frame_id, non-unit quaternion, no open episode) is answered by an ``error`` status naming the
topic and field. See docs/ROS.md for the table, frames and units.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from typing import Any

from brave6d.core.errors import BraveError
from brave6d.ros_interface.bridge import BridgeStep, EpisodeBridge
from brave6d.ros_interface.ros1 import convert
from brave6d.ros_interface.ros1.messages import Brave6dMsgs

log = logging.getLogger(__name__)

NODE_NAME = "brave6d_sim"
#: Seconds one ``cmd_twist`` message is integrated for, unless the node is given another.
DEFAULT_TWIST_DURATION_S = 0.1
IMAGE_QUEUE = 2


def _target_arg(text: str) -> int | str | None:
    text = text.strip()
    if not text:
        return None
    return int(text) if text.isascii() and text.isdigit() else text  # "²".isdigit(), but int("²") fails


class Ros1Node:
    """Topics, services and the bridge of one running node (``rospy.init_node`` done by the caller)."""

    def __init__(self, bridge: EpisodeBridge, msgs: Brave6dMsgs, *, twist_duration_s: float = DEFAULT_TWIST_DURATION_S,
                 default_scene: str | None = None) -> None:
        import rospy
        from geometry_msgs.msg import PoseStamped, TwistStamped
        from sensor_msgs.msg import CameraInfo, Image
        from std_srvs.srv import Trigger
        from tf2_msgs.msg import TFMessage

        if not twist_duration_s > 0:
            raise BraveError(f"twist duration must be > 0 s, got {twist_duration_s}")
        self.bridge = bridge
        self.msgs = msgs
        self.twist_duration_s = float(twist_duration_s)
        self.default_scene = default_scene
        self._publish_lock = threading.Lock()
        self.pub_rgb = rospy.Publisher("~rgb/image_raw", Image, queue_size=IMAGE_QUEUE, latch=True)
        self.pub_depth = rospy.Publisher("~depth/image_raw", Image, queue_size=IMAGE_QUEUE, latch=True)
        self.pub_rgb_info = rospy.Publisher("~rgb/camera_info", CameraInfo, queue_size=IMAGE_QUEUE, latch=True)
        self.pub_depth_info = rospy.Publisher("~depth/camera_info", CameraInfo, queue_size=IMAGE_QUEUE, latch=True)
        self.pub_tf = rospy.Publisher("/tf", TFMessage, queue_size=10)
        self.pub_status = rospy.Publisher("~status", msgs.msg.EpisodeStatus, queue_size=10, latch=True)
        self.topic_set_pose = rospy.resolve_name("~set_pose")
        self.topic_twist = rospy.resolve_name("~cmd_twist")
        self.sub_pose = rospy.Subscriber("~set_pose", PoseStamped, self._on_set_pose, queue_size=10)
        self.sub_twist = rospy.Subscriber("~cmd_twist", TwistStamped, self._on_twist, queue_size=10)
        self.srv_reset = rospy.Service("~reset", msgs.srv.Reset, self._on_reset)
        self.srv_submit = rospy.Service("~submit", msgs.srv.SubmitEstimates, self._on_submit)
        self.srv_close = rospy.Service("~close", Trigger, self._on_close)

    # ------------------------------------------------------------------ publishing
    def publish(self, step: BridgeStep) -> None:
        """Every message of ``step``'s observation, status last (an agent waits for it)."""
        with self._publish_lock:
            self.pub_rgb.publish(convert.rgb_image(step))
            self.pub_depth.publish(convert.depth_image(step))
            info = convert.camera_info(step)
            self.pub_rgb_info.publish(info)
            self.pub_depth_info.publish(info)  # the depth image is registered to the colour image
            self.pub_tf.publish(convert.tf_message(step))
            self.pub_status.publish(convert.status_message(self.msgs, step))

    def publish_error(self, where: str, exc: BaseException) -> None:
        import rospy

        message = str(exc) if isinstance(exc, BraveError) else f"{where}: internal error: {exc!r}"
        if not isinstance(exc, BraveError):
            rospy.logerr("%s\n%s", message, traceback.format_exc())
        else:
            rospy.logwarn(message)
        with self._publish_lock:
            self.pub_status.publish(convert.error_status(self.msgs, time.time_ns(), self.bridge.episode_id, message))

    # ------------------------------------------------------------------ callbacks
    def _on_set_pose(self, msg: Any) -> None:
        try:
            self.publish(self.bridge.set_pose(convert.world_T_cam_from(msg, self.topic_set_pose)))
        except Exception as exc:  # noqa: BLE001 - reported on ~status, the node keeps running
            self.publish_error(self.topic_set_pose, exc)

    def _on_twist(self, msg: Any) -> None:
        try:
            linear, angular, frame = convert.twist_from(msg, self.topic_twist)
            self.publish(self.bridge.move(linear, angular, self.twist_duration_s, frame))
        except Exception as exc:  # noqa: BLE001
            self.publish_error(self.topic_twist, exc)

    def _on_reset(self, req: Any) -> Any:
        name = self.srv_reset.resolved_name
        try:
            start = convert.pose_matrix(req.start, f"{name}: start") if req.use_start else None
            step = self.bridge.reset(scene=req.scene or self.default_scene, target=_target_arg(req.target),
                                     seed=None if req.seed < 0 else int(req.seed), start=start)
            self.publish(step)
            return self.msgs.srv.ResetResponse(success=True, message=f"episode {step.episode_id} started "
                                               f"({step.mode} mode)",
                                               header=convert.header(step.stamp_ns, convert.FRAME_WORLD),
                                               episode_id=step.episode_id, target_frame=step.target_frame)
        except Exception as exc:  # noqa: BLE001
            self.publish_error(name, exc)
            return self.msgs.srv.ResetResponse(success=False, message=_one_line(name, exc))

    def _on_submit(self, req: Any) -> Any:
        name = self.srv_submit.resolved_name
        try:
            result = self.bridge.submit(convert.estimates_from(req, name))
            return convert.result_response(self.msgs, result)
        except Exception as exc:  # noqa: BLE001
            self.publish_error(name, exc)
            return self.msgs.srv.SubmitEstimatesResponse(success=False, message=_one_line(name, exc))

    def _on_close(self, req: Any) -> Any:
        from std_srvs.srv import TriggerResponse

        try:
            out = self.bridge.close()
            return TriggerResponse(success=True, message=f"episode {out.get('episode_id')}: {out.get('reason')}")
        except Exception as exc:  # noqa: BLE001
            return TriggerResponse(success=False, message=_one_line(self.srv_close.resolved_name, exc))


def _one_line(where: str, exc: BaseException) -> str:
    text = str(exc) if isinstance(exc, BraveError) else f"internal error: {exc!r}"
    return text if text.startswith(where) else f"{where}: {text}"

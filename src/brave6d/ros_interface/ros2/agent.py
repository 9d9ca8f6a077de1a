"""A Python rclpy agent of the ROS 2 node: call a service, then collect the images, camera info and
tf the node published under the answer's stamp. Used by the end-to-end test and the latency
benchmark; docs/ROS.md's minimal agent (``example_agent``) does the same with plain rclpy.
"""

from __future__ import annotations

import json
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.ros_interface.bridge import Estimate
from brave6d.ros_interface.frames import FRAME_CAMERA_OPTICAL, FRAME_WORLD, GT_FRAME_PREFIX
from brave6d.ros_interface.ros2 import convert
from brave6d.ros_interface.ros2.defaults import DEFAULT_NAMESPACE
from brave6d.ros_interface.ros2.node import TF_TOPIC, topic_name

#: Per stamp, what a step publishes besides the service's answer.
STEP_PARTS = ("rgb", "depth", "rgb_info", "depth_info", "tf")


class AgentError(BraveError):
    """The node refused a request (``success: false``) or did not answer in time."""


@dataclass
class Observation:
    """One step as the agent received it: the service's Step answer and the arrays of its messages."""

    status: dict[str, Any]  # the Step's status_json
    step: Any  # brave6d_msgs/Step
    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]
    K: NDArray[np.float64]
    world_T_cam: NDArray[np.float64]  # from /tf (world -> brave6d_camera_optical_frame)
    ground_truth: dict[str, NDArray[np.float64]]  # gt frame -> world_T_obj, from /tf
    messages: dict[str, Any]
    received: dict[str, float]  # part -> time.perf_counter() on arrival

    def cam_T_gt(self, frame: str) -> NDArray[np.float64]:
        """A ground-truth object's pose in the camera frame of this view."""
        return np.linalg.inv(self.world_T_cam) @ self.ground_truth[frame]


class Ros2Agent:
    """An rclpy node ``brave6d_agent`` that drives the node under ``namespace`` (its own executor
    thread; ``qos`` "sensor_data" or "default" for the image subscriptions)."""

    def __init__(self, namespace: str = DEFAULT_NAMESPACE, timeout_s: float = 60.0, context: Any = None,
                 qos: str = "sensor_data", node_name: str = "brave6d_agent") -> None:
        import brave6d_msgs.srv as srv
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image
        from std_srvs.srv import Trigger
        from tf2_msgs.msg import TFMessage

        self.srv = srv
        self.namespace = namespace.rstrip("/")
        self.timeout_s = float(timeout_s)
        self.node = Node(node_name, context=context)
        self._lock = threading.Condition()
        self._parts: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._received: dict[int, dict[str, float]] = {}
        image_qos = qos_profile_sensor_data if qos == "sensor_data" else QoSProfile(depth=10)
        for part, suffix, cls in (("rgb", "rgb/image_raw", Image), ("depth", "depth/image_raw", Image),
                                  ("rgb_info", "rgb/camera_info", CameraInfo),
                                  ("depth_info", "depth/camera_info", CameraInfo)):
            self.node.create_subscription(cls, self._name(suffix), lambda msg, p=part: self._on_part(p, msg),
                                          image_qos)
        self.node.create_subscription(TFMessage, TF_TOPIC, self._on_tf, QoSProfile(depth=100))
        self.clients = {"reset": self.node.create_client(srv.Reset, self._name("reset")),
                        "set_pose": self.node.create_client(srv.SetPose, self._name("set_pose")),
                        "move": self.node.create_client(srv.Move, self._name("move")),
                        "submit": self.node.create_client(srv.Submit, self._name("submit")),
                        "close": self.node.create_client(Trigger, self._name("close"))}
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._spinner = threading.Thread(target=self._spin, name="brave6d-ros2-agent", daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def destroy(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()

    def _name(self, suffix: str) -> str:
        return topic_name(self.namespace, suffix)

    # ------------------------------------------------------------------ incoming
    def _store(self, stamp_ns: int, part: str, value: Any) -> None:
        with self._lock:
            self._parts.setdefault(stamp_ns, {})[part] = value
            self._received.setdefault(stamp_ns, {})[part] = time.perf_counter()
            while len(self._parts) > 64:  # keep the recent steps only
                old, _ = self._parts.popitem(last=False)
                self._received.pop(old, None)
            self._lock.notify_all()

    def _on_part(self, part: str, msg: Any) -> None:
        self._store(convert.stamp_to_ns(msg.header.stamp), part, msg)

    def _on_tf(self, msg: Any) -> None:
        if msg.transforms:
            self._store(convert.stamp_to_ns(msg.transforms[0].header.stamp), "tf", msg)

    # ------------------------------------------------------------------ requests
    def wait_until_connected(self, timeout_s: float = 10.0) -> None:
        """Wait until every service is available and the image topics are matched."""
        deadline = time.monotonic() + timeout_s
        for name, client in self.clients.items():
            if not client.wait_for_service(timeout_sec=max(0.0, deadline - time.monotonic())):
                raise AgentError(f"no ROS 2 service {self._name(name)} within {timeout_s:g} s: is "
                                 "'brave6d ros2' running on this domain?")
        while self.node.count_publishers(self._name("depth/image_raw")) == 0:
            if time.monotonic() > deadline:
                raise AgentError(f"no publisher of {self._name('depth/image_raw')} within {timeout_s:g} s")
            time.sleep(0.05)

    def call(self, name: str, request: Any) -> Any:
        """The node's answer to ``request`` on service ``name`` (``AgentError`` when refused or late)."""
        future = self.clients[name].call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(self.timeout_s):
            self.clients[name].remove_pending_request(future)
            raise AgentError(f"{self._name(name)}: no answer within {self.timeout_s:g} s")
        response = future.result()
        if not response.success:
            raise AgentError(response.message)
        return response

    def _observation(self, step: Any) -> Observation:
        stamp_ns = convert.stamp_to_ns(step.stamp)
        deadline = time.monotonic() + self.timeout_s
        with self._lock:
            while not all(p in self._parts.get(stamp_ns, {}) for p in STEP_PARTS):
                left = deadline - time.monotonic()
                if left <= 0:
                    have = sorted(self._parts.get(stamp_ns, {}))
                    raise AgentError(f"step {step.step} (stamp {stamp_ns}): only {have or 'nothing'} of "
                                     f"{list(STEP_PARTS)} arrived within {self.timeout_s:g} s")
                self._lock.wait(min(left, 0.1))
            parts = dict(self._parts[stamp_ns])
            received = dict(self._received[stamp_ns])
        tf = {t.child_frame_id: convert.transform_to_matrix(t) for t in parts["tf"].transforms
              if t.header.frame_id == FRAME_WORLD}
        return Observation(status=json.loads(step.status_json), step=step,
                           rgb=np.array(convert.image_to_array(parts["rgb"])),
                           depth_m=np.array(convert.image_to_array(parts["depth"])),
                           K=np.asarray(parts["rgb_info"].k, dtype=np.float64).reshape(3, 3),
                           world_T_cam=tf[FRAME_CAMERA_OPTICAL],
                           ground_truth={k: v for k, v in tf.items() if k.startswith(GT_FRAME_PREFIX)},
                           messages=parts, received=received)

    def reset(self, scene: str | int | None = None, target: int | str | None = None, seed: int | None = None,
              start: Any = None) -> Observation:
        req = self.srv.Reset.Request(scene="" if scene is None else str(scene),
                                     target="" if target is None else str(target))
        if seed is not None:
            req.use_seed, req.seed = True, int(seed)
        if start is not None:
            req.use_start, req.start = True, convert.pose_msg(start)
        return self._observation(self.call("reset", req).step)

    def set_pose(self, world_T_cam: Any) -> Observation:
        from geometry_msgs.msg import PoseStamped

        req = self.srv.SetPose.Request(pose=PoseStamped(pose=convert.pose_msg(world_T_cam)))
        req.pose.header.frame_id = FRAME_WORLD
        return self._observation(self.call("set_pose", req).step)

    def move(self, linear: Any, angular: Any, duration: float = 0.0, frame: str = FRAME_CAMERA_OPTICAL) -> Observation:
        from geometry_msgs.msg import TwistStamped, Vector3

        twist = TwistStamped()
        twist.header.frame_id = frame
        twist.twist.linear = Vector3(x=float(linear[0]), y=float(linear[1]), z=float(linear[2]))
        twist.twist.angular = Vector3(x=float(angular[0]), y=float(angular[1]), z=float(angular[2]))
        return self._observation(self.call("move", self.srv.Move.Request(twist=twist, duration=float(duration))).step)

    def submit(self, estimates: list[Estimate]) -> dict[str, Any]:
        from brave6d_msgs.msg import ObjectEstimate

        req = self.srv.Submit.Request(estimates=convert.estimates_to_msgs(estimates, ObjectEstimate))
        req.header.frame_id = FRAME_CAMERA_OPTICAL
        return json.loads(self.call("submit", req).result_json)

    def close(self) -> dict[str, Any]:
        from std_srvs.srv import Trigger

        return json.loads(self.call("close", Trigger.Request()).message)

"""A Python agent of the ROS 2 node that speaks DDS directly (the same Cyclone DDS message types,
no ROS 2 installation): publish a command, wait for its answer on ``status`` / ``result`` (paired
by the command's id), and collect the images, camera info and tf published under that step's stamp.

Used by the example agent, the end-to-end test and the latency benchmark; an ``rclpy`` agent does
the same with ``create_publisher`` / ``create_subscription`` (docs/ROS.md).
"""

from __future__ import annotations

import itertools
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
from brave6d.ros_interface.ros2 import messages as m
from brave6d.ros_interface.ros2.dds import DEFAULT, SENSOR_DATA, TF, DdsDomain
from brave6d.ros_interface.ros2.node import DEFAULT_NAMESPACE, TF_TOPIC, topic_name

#: Per stamp, what a step publishes besides its status.
STEP_PARTS = ("rgb", "depth", "rgb_info", "depth_info", "tf")


@dataclass
class Observation:
    """One step as the agent received it: the status JSON and the arrays of its messages."""

    status: dict[str, Any]
    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]
    K: NDArray[np.float64]
    world_T_cam: NDArray[np.float64]  # from /tf (world -> brave6d_camera_optical_frame)
    ground_truth: dict[str, NDArray[np.float64]]  # gt frame -> world_T_obj, from /tf
    messages: dict[str, Any]
    received: dict[str, float]  # part (rgb, depth, rgb_info, depth_info, tf) -> time.perf_counter() on arrival

    def cam_T_gt(self, frame: str) -> NDArray[np.float64]:
        """A ground-truth object's pose in the camera frame of this view."""
        return np.linalg.inv(self.world_T_cam) @ self.ground_truth[frame]


class AgentError(BraveError):
    """The node answered a command with an error, or did not answer in time."""


class Ros2Agent:
    """Drives one ``brave6d ros2`` node on ``dds`` (see :class:`DdsDomain`)."""

    def __init__(self, dds: DdsDomain, namespace: str = DEFAULT_NAMESPACE, timeout_s: float = 60.0,
                 keep: int = 16) -> None:
        self.dds = dds
        self.namespace = namespace
        self.timeout_s = timeout_s
        self._keep = keep
        self._cond = threading.Condition()
        self._answers: OrderedDict[Any, dict[str, Any]] = OrderedDict()
        self._parts: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._ids = itertools.count(1)
        n = self._name
        self._readers = [
            dds.reader(n("status"), m.String, DEFAULT, on_data=self._on_answer),
            dds.reader(n("result"), m.String, DEFAULT, on_data=self._on_answer),
            dds.reader(n("rgb/image_raw"), m.Image, SENSOR_DATA, on_data=lambda x: self._on_part("rgb", x)),
            dds.reader(n("depth/image_raw"), m.Image, SENSOR_DATA, on_data=lambda x: self._on_part("depth", x)),
            dds.reader(n("rgb/camera_info"), m.CameraInfo, SENSOR_DATA,
                       on_data=lambda x: self._on_part("rgb_info", x)),
            dds.reader(n("depth/camera_info"), m.CameraInfo, SENSOR_DATA,
                       on_data=lambda x: self._on_part("depth_info", x)),
            dds.reader(TF_TOPIC, m.TFMessage, TF, on_data=self._on_tf),
        ]
        self._writers = {
            "reset": dds.writer(n("reset"), m.String, DEFAULT),
            "set_pose": dds.writer(n("set_pose"), m.PoseStamped, DEFAULT),
            "cmd_twist": dds.writer(n("cmd_twist"), m.TwistStamped, DEFAULT),
            "submit": dds.writer(n("submit"), m.ObjectEstimateArray, DEFAULT),
            "submit_json": dds.writer(n("submit_json"), m.String, DEFAULT),
            "close": dds.writer(n("close"), m.String, DEFAULT),
        }

    def _name(self, suffix: str) -> str:
        return topic_name(self.namespace, suffix)

    # ------------------------------------------------------------------ incoming
    def _on_answer(self, msg: m.String) -> None:
        value = json.loads(msg.data)
        request = value.get("request") or {}
        with self._cond:
            self._answers[(request.get("topic"), request.get("id"))] = value
            while len(self._answers) > self._keep:
                self._answers.popitem(last=False)
            self._cond.notify_all()

    def _store(self, stamp_ns: int, part: str, value: Any) -> None:
        arrived = time.perf_counter()
        with self._cond:
            self._parts.setdefault(stamp_ns, {})[part] = value
            self._parts[stamp_ns][f"{part}@"] = arrived
            while len(self._parts) > self._keep:
                self._parts.popitem(last=False)
            self._cond.notify_all()

    def _on_part(self, part: str, msg: Any) -> None:
        self._store(m.stamp_to_ns(msg.header.stamp), part, msg)

    def _on_tf(self, msg: m.TFMessage) -> None:
        if msg.transforms:
            self._store(m.stamp_to_ns(msg.transforms[0].header.stamp), "tf", msg)

    def wait_until_connected(self, timeout_s: float = 10.0) -> None:
        """Wait until every command writer has matched the node's reader (discovery done)."""
        deadline = time.monotonic() + timeout_s
        for name, w in self._writers.items():
            while w.get_publication_matched_status().current_count == 0:
                if time.monotonic() > deadline:
                    raise AgentError(f"{self._name(name)}: no brave6d ros2 node found on DDS domain "
                                     f"{self.dds.domain_id} within {timeout_s:g} s")
                time.sleep(0.01)
        for r in self._readers:
            while r.get_subscription_matched_status().current_count == 0:
                if time.monotonic() > deadline:
                    raise AgentError(f"{r.topic.name}: the node's writer was not discovered within {timeout_s:g} s")
                time.sleep(0.01)

    # ------------------------------------------------------------------ commands
    def _stamp_id(self) -> tuple[m.Header, int]:
        """A unique command id carried as a header stamp (nanoseconds; ids are small counters)."""
        i = next(self._ids)
        return convert.header(i, ""), i

    def _await(self, topic: str, request_id: Any) -> dict[str, Any]:
        deadline = time.monotonic() + self.timeout_s
        with self._cond:
            while (topic, request_id) not in self._answers:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AgentError(f"{self._name(topic)}: no answer within {self.timeout_s:g} s")
                self._cond.wait(left)
            answer = self._answers.pop((topic, request_id))
        if "error" in answer:
            raise AgentError(answer["error"])
        return answer

    def _observation(self, status: dict[str, Any]) -> Observation:
        stamp = int(status["stamp_ns"])
        deadline = time.monotonic() + self.timeout_s
        with self._cond:
            while not all(p in self._parts.get(stamp, {}) for p in STEP_PARTS):
                left = deadline - time.monotonic()
                if left <= 0:
                    missing = [p for p in STEP_PARTS if p not in self._parts.get(stamp, {})]
                    raise AgentError(f"step {status.get('step')}: {missing} not received within {self.timeout_s:g} s "
                                     "(best-effort topics: a lost sample is not resent)")
                self._cond.wait(left)
            parts = self._parts.pop(stamp)
        tf = {t.child_frame_id: convert.transform_to_matrix(t) for t in parts["tf"].transforms
              if t.header.frame_id == FRAME_WORLD}
        return Observation(status=status, rgb=convert.image_to_array(parts["rgb"]),
                           depth_m=convert.image_to_array(parts["depth"]),
                           K=np.asarray(parts["rgb_info"].k, dtype=np.float64).reshape(3, 3),
                           world_T_cam=tf[FRAME_CAMERA_OPTICAL],
                           ground_truth={k: v for k, v in tf.items() if k.startswith(GT_FRAME_PREFIX)},
                           messages={p: parts[p] for p in STEP_PARTS}, received={p: parts[f"{p}@"] for p in STEP_PARTS})

    def _json_command(self, topic: str, body: dict[str, Any]) -> Any:
        request_id = f"{topic}-{next(self._ids)}"
        self._writers[topic].write(m.String(json.dumps({**body, "id": request_id})))
        return request_id

    def send_json(self, topic: str, body: dict[str, Any]) -> dict[str, Any]:
        """Publish a JSON command on ``topic`` (reset, submit_json, close) and return its answer."""
        if topic not in ("reset", "submit_json", "close"):
            raise AgentError(f"{topic}: not a JSON command topic (reset, submit_json, close)")
        return self._await(topic, self._json_command(topic, body))

    def reset(self, scene: str | int | None = None, target: int | str | None = None, seed: int | None = None,
              start: Any = None) -> Observation:
        body: dict[str, Any] = {k: v for k, v in (("scene", scene), ("target", target), ("seed", seed))
                                if v is not None}
        if start is not None:
            body["start"] = np.asarray(start, dtype=np.float64).tolist()
        rid = self._json_command("reset", body)
        return self._observation(self._await("reset", rid))

    def set_pose(self, world_T_cam: Any) -> Observation:
        header, rid = self._stamp_id()
        header.frame_id = FRAME_WORLD
        self._writers["set_pose"].write(m.PoseStamped(header=header, pose=convert.pose_to_msg(world_T_cam)))
        return self._observation(self._await("set_pose", rid))

    def twist(self, linear: Any, angular: Any, frame: str = FRAME_CAMERA_OPTICAL) -> Observation:
        """One ``cmd_twist`` (applied for the node's twist duration)."""
        header, rid = self._stamp_id()
        header.frame_id = frame
        self._writers["cmd_twist"].write(m.TwistStamped(header=header, twist=m.Twist(
            linear=m.Vector3(*map(float, linear)), angular=m.Vector3(*map(float, angular)))))
        return self._observation(self._await("cmd_twist", rid))

    def submit(self, estimates: list[Estimate]) -> dict[str, Any]:
        """Hand in the estimates (camera frame of the current view); the scored result."""
        header, rid = self._stamp_id()
        msg = convert.estimates_to_msg(estimates)
        msg.header.stamp = header.stamp
        self._writers["submit"].write(msg)
        return self._await("submit", rid)

    def close(self) -> dict[str, Any]:
        return self._await("close", self._json_command("close", {}))

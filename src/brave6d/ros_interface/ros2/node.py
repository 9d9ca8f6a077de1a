"""The ROS 2 node of ``brave6d ros2``: the bridge's episodes as ROS 2 topics over DDS.

Every topic is a plain ROS 2 topic (DDS ``rt/<name>``, standard ROS 2 types except the estimates,
whose ``brave6d_msgs`` definitions ship in ``msg/``), so an ``rclpy`` node on Humble/Jazzy talks to
it with ``create_publisher``/``create_subscription``; see docs/ROS.md for the table. Commands are
topics rather than ROS 2 services: a ROS 2 service over DDS is a request/reply topic pair whose
samples carry an rmw-specific request header, which nothing here can check against a real rmw.
Every command is answered on ``status`` (``result`` for a submission), echoing the command's id
(``header.stamp`` of a stamped message, the ``"id"`` of a JSON one), so an agent can pair them.

Threads: Cyclone's listener threads only queue incoming commands; one worker thread runs them in
arrival order (renders are serial anyway) and publishes the answers: images, camera info and tf
first, then ``status``, all with the step's stamp.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
from dataclasses import dataclass
from typing import Any, Callable

from brave6d.core.errors import BraveError
from brave6d.ros_interface.bridge import BridgeStep, EpisodeBridge, Estimate
from brave6d.ros_interface.frames import pose_to_matrix
from brave6d.ros_interface.ros2 import convert
from brave6d.ros_interface.ros2 import messages as m
from brave6d.ros_interface.ros2.dds import DEFAULT, SENSOR_DATA, TF, DdsDomain, QosProfile
from brave6d.ros_interface.ros2.defaults import DEFAULT_NAMESPACE, DEFAULT_TWIST_DURATION_S

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Topic:
    """One ROS 2 topic of the node: its name under the namespace, message type, QoS and direction."""

    suffix: str
    msg_type: type
    qos: QosProfile
    inbound: bool
    doc: str


#: The node's interface (docs/ROS.md shows this table). ``/tf`` is global, not namespaced.
TOPICS: tuple[Topic, ...] = (
    Topic("reset", m.String, DEFAULT, True, 'JSON {"scene", "target", "seed", "start", "id"}, all optional; '
          "starts an episode (closing the open one); start: 4x4 world_T_cam or {position, orientation x-y-z-w}"),
    Topic("set_pose", m.PoseStamped, DEFAULT, True, "teleport the camera: world_T_cam of the optical frame, "
          "header.frame_id world"),
    Topic("cmd_twist", m.TwistStamped, DEFAULT, True, "constant twist (m/s, rad/s) for the node's twist duration, "
          "in the camera optical frame (frame_id empty or brave6d_camera_optical_frame) or world"),
    Topic("submit", m.ObjectEstimateArray, DEFAULT, True, "hand in pose estimates (camera optical frame of the "
          "current view); ends the episode; answered on result"),
    Topic("submit_json", m.String, DEFAULT, True, 'the same as JSON {"estimates": [{"obj_id", "position": [x, y, z], '
          '"orientation": [x, y, z, w], "score"}], "id"} for agents without brave6d_msgs'),
    Topic("close", m.String, DEFAULT, True, 'JSON {"id"} (or empty): close the episode without a submission'),
    Topic("rgb/image_raw", m.Image, SENSOR_DATA, False, "rgb8 view, frame brave6d_camera_optical_frame"),
    Topic("rgb/camera_info", m.CameraInfo, SENSOR_DATA, False, "pinhole intrinsics of the view (no distortion)"),
    Topic("depth/image_raw", m.Image, SENSOR_DATA, False, "32FC1 depth in metres, NaN = no data (REP 118)"),
    Topic("depth/camera_info", m.CameraInfo, SENSOR_DATA, False, "the same intrinsics (depth is registered to rgb)"),
    Topic("status", m.String, DEFAULT, False, "JSON answer to every command: step, accepted, collided, refusal, "
          "adjustments, stamp_ns, target, world_T_cam, request; or error"),
    Topic("result", m.String, DEFAULT, False, "JSON score of a submission: ar, ar_vsd, ar_mssd, ar_mspd, "
          "adjustments, steps, refusals, submitted, request"),
)
TF_TOPIC = "/tf"


def topic_name(namespace: str, suffix: str) -> str:
    return f"{namespace.rstrip('/')}/{suffix}"


def parse_json_command(msg: m.String, topic: str) -> dict[str, Any]:
    """The JSON object of a ``std_msgs/String`` command (empty data = ``{}``)."""
    text = msg.data.strip()
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BraveError(f"{topic}: data is not JSON ({exc.msg} at character {exc.pos})") from None
    if not isinstance(value, dict):
        raise BraveError(f"{topic}: data must be a JSON object, got {type(value).__name__}")
    return value


def start_pose(value: Any, topic: str) -> Any:
    """A reset's ``start``: None, a 4x4 ``world_T_cam`` (nested lists) or ``{"position": [x, y, z],
    "orientation": [x, y, z, w]}`` (the camera optical frame's pose in world, metres)."""
    if value is None or isinstance(value, list):
        return value
    if isinstance(value, dict) and set(value) == {"position", "orientation"}:
        try:
            return pose_to_matrix(value["position"], value["orientation"], f"{topic}.start")
        except (TypeError, ValueError) as exc:
            raise BraveError(f"{topic}.start: {exc}") from None
    raise BraveError(f"{topic}.start: a 4x4 world_T_cam or {{position: [x, y, z], orientation: [x, y, z, w]}}")


def estimates_from_json(command: dict[str, Any], topic: str) -> list[Estimate]:
    items = command.get("estimates")
    if not isinstance(items, list):
        raise BraveError(f"{topic}: 'estimates' must be a list of {{obj_id, position, orientation, score}}")
    out = []
    for i, e in enumerate(items):
        where = f"{topic}.estimates.{i}"
        if not isinstance(e, dict) or "obj_id" not in e:
            raise BraveError(f"{where}: must be an object with obj_id, position, orientation (x, y, z, w), score")
        try:
            T = pose_to_matrix(e.get("position"), e.get("orientation"), where)
            out.append(Estimate(int(e["obj_id"]), T, float(e.get("score", 1.0))))
        except (TypeError, ValueError) as exc:
            raise BraveError(f"{where}: {exc}") from None
    return out


class Ros2Node:
    """Serves one :class:`EpisodeBridge` on a :class:`DdsDomain` under ``namespace``."""

    def __init__(self, bridge: EpisodeBridge, dds: DdsDomain, *, namespace: str = DEFAULT_NAMESPACE,
                 twist_duration_s: float = DEFAULT_TWIST_DURATION_S, default_scene: str | None = None) -> None:
        if not namespace.startswith("/"):
            raise BraveError(f"--namespace {namespace!r}: must start with '/'")
        self.bridge = bridge
        self.dds = dds
        self.namespace = namespace.rstrip("/") or ""
        if not twist_duration_s > 0:
            raise BraveError(f"twist duration must be > 0 s, got {twist_duration_s}")
        self.twist_duration_s = float(twist_duration_s)
        self.default_scene = default_scene
        self._queue: queue.Queue[tuple[str, Any] | None] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._handlers: dict[str, Callable[[Any, str], None]] = {
            "reset": self._on_reset, "set_pose": self._on_pose, "cmd_twist": self._on_twist,
            "submit": self._on_submit, "submit_json": self._on_submit_json, "close": self._on_close,
        }

    def name(self, suffix: str) -> str:
        return topic_name(self.namespace, suffix)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "Ros2Node":
        """Create every writer and reader and start the worker thread."""
        for t in TOPICS:
            if t.inbound:
                self.dds.reader(self.name(t.suffix), t.msg_type, t.qos,
                                on_data=lambda msg, suffix=t.suffix: self._queue.put((suffix, msg)))
            else:
                self.dds.writer(self.name(t.suffix), t.msg_type, t.qos)
        self.dds.writer(TF_TOPIC, m.TFMessage, TF)
        self._worker = threading.Thread(target=self._run, name="brave6d-ros2-node", daemon=True)
        self._worker.start()
        return self

    def stop(self) -> None:
        """Stop the worker (after the commands already queued) and close the open episode."""
        if self._worker is not None:
            self._queue.put(None)
            self._worker.join(timeout=60)
            self._worker = None
        try:
            self.bridge.close()
        except BraveError as exc:  # the episode may have expired meanwhile
            log.warning("closing the episode at shutdown: %s", exc)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            suffix, msg = item
            topic = self.name(suffix)
            try:
                self._handlers[suffix](msg, topic)
            except BraveError as exc:
                self._publish_json("status", {"error": str(exc), "request": self._request(suffix, msg)})
            except Exception as exc:  # a bug must not kill the node; the agent hears of it
                log.exception("%s: command failed", topic)
                self._publish_json("status", {"error": f"{topic}: internal error: {type(exc).__name__}: {exc}",
                                              "request": self._request(suffix, msg)})

    # ------------------------------------------------------------------ commands
    @staticmethod
    def _request(suffix: str, msg: Any) -> dict[str, Any]:
        """What identifies a command in its answer: its topic and id (a stamp, or the JSON "id")."""
        out: dict[str, Any] = {"topic": suffix, "id": None}
        header = getattr(msg, "header", None)
        if header is not None:
            out["id"] = m.stamp_to_ns(header.stamp)
        elif isinstance(msg, m.String):
            try:
                value = json.loads(msg.data) if msg.data.strip() else {}
                out["id"] = value.get("id") if isinstance(value, dict) else None
            except json.JSONDecodeError:
                pass
        return out

    def _on_reset(self, msg: m.String, topic: str) -> None:
        c = parse_json_command(msg, topic)
        unknown = set(c) - {"scene", "target", "seed", "start", "id"}
        if unknown:
            raise BraveError(f"{topic}: unknown field(s) {sorted(unknown)} (known: scene, target, seed, start, id)")
        seed = c.get("seed")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise BraveError(f"{topic}: seed must be an integer, got {seed!r}")
        step = self.bridge.reset(scene=c.get("scene") or self.default_scene, target=c.get("target"), seed=seed,
                                 start=start_pose(c.get("start"), topic))
        self._publish_step(step, self._request("reset", msg))

    def _on_pose(self, msg: m.PoseStamped, topic: str) -> None:
        step = self.bridge.set_pose(convert.camera_pose_from_msg(msg, topic))
        self._publish_step(step, self._request("set_pose", msg))

    def _on_twist(self, msg: m.TwistStamped, topic: str) -> None:
        linear, angular, frame = convert.twist_from_msg(msg, topic)
        step = self.bridge.move(linear, angular, self.twist_duration_s, frame)
        self._publish_step(step, self._request("cmd_twist", msg))

    def _on_submit(self, msg: m.ObjectEstimateArray, topic: str) -> None:
        self._submit(convert.estimates_from_msg(msg, topic), self._request("submit", msg))

    def _on_submit_json(self, msg: m.String, topic: str) -> None:
        self._submit(estimates_from_json(parse_json_command(msg, topic), topic), self._request("submit_json", msg))

    def _submit(self, estimates: list[Estimate], request: dict[str, Any]) -> None:
        result = self.bridge.submit(estimates)
        self._publish_json("result", {**result.to_json(), "request": request})

    def _on_close(self, msg: m.String, topic: str) -> None:
        parse_json_command(msg, topic)
        out = self.bridge.close()
        self._publish_json("status", {"action": "close", **{k: v for k, v in out.items() if _jsonable(v)},
                                      "request": self._request("close", msg)})

    # ------------------------------------------------------------------ answers
    def _publish_step(self, step: BridgeStep, request: dict[str, Any]) -> None:
        """Images, camera info and tf of the step, then its status (all with the step's stamp)."""
        info = convert.camera_info(step)
        self.dds.publish(self.name("rgb/image_raw"), convert.rgb_image(step), SENSOR_DATA)
        self.dds.publish(self.name("rgb/camera_info"), info, SENSOR_DATA)
        self.dds.publish(self.name("depth/image_raw"), convert.depth_image(step), SENSOR_DATA)
        self.dds.publish(self.name("depth/camera_info"), info, SENSOR_DATA)
        self.dds.publish(TF_TOPIC, convert.tf_message(step), TF)
        self._publish_json("status", {**step.status(), "request": request})

    def _publish_json(self, suffix: str, value: dict[str, Any]) -> None:
        self.dds.publish(self.name(suffix), m.String(json.dumps(value)), DEFAULT)


def _jsonable(value: Any) -> bool:
    try:
        json.dumps(value)
        return True
    except (TypeError, ValueError):
        return False

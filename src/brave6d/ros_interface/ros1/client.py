"""An agent's side of the ``brave6d_sim`` node in rospy: actions as blocking calls that return the
observation they produced (matched by stamp), for agents, tests and the latency benchmark.

``Ros1Client`` publishes ``~set_pose`` / ``~cmd_twist`` and calls ``~reset`` / ``~submit`` /
``~close``; it waits for the ``~status`` whose stamp is newer than the last observation's, then
for the images, camera infos and ``/tf`` carrying that stamp. ``rospy.init_node`` is the caller's.

``python -m brave6d.ros_interface.ros1.client ACTIONS.json OUT_DIR`` replays a list of actions (what an
HTTP episode did, say) and records every observation (``OUT_DIR/record.json`` and
``step_<k>.npz``): the ROS 1 end-to-end test and the latency benchmark use it.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import BraveError
from brave6d.ros_interface.frames import FRAME_CAMERA_OPTICAL, FRAME_WORLD, matrix_to_pose, pose_to_matrix
from brave6d.ros_interface.ros1 import convert
from brave6d.ros_interface.ros1.ros_env import require_ros1

IMAGE_BUFF_SIZE = 1 << 26  # rospy's default (64 KiB) splits big images into many reads


def _node_json(text: str, where: str) -> Any:
    """JSON text a node sent, through the one JSON reader with the client's limits (one-line errors)."""
    from brave6d.serve import ClientLimits, parse_reply

    return parse_reply(text.encode("utf-8", "surrogatepass"), ClientLimits(), where)


@dataclass
class Ros1Observation:
    """One observation's messages (all with stamp ``stamp_ns``) and when they arrived (perf_counter)."""

    stamp_ns: int
    status: Any
    rgb: Any
    depth: Any
    rgb_info: Any
    depth_info: Any
    tf: Any
    received: dict[str, float] = field(default_factory=dict)

    @property
    def status_json(self) -> dict[str, Any]:
        """The status's JSON, read as any reply from a node this client does not trust (the client
        limits of :mod:`brave6d.serve.replies`: size, depth, number length)."""
        return _node_json(self.status.json, "EpisodeStatus.json")

    def rgb_array(self) -> NDArray[np.uint8]:
        return convert.image_array(self.rgb)

    def depth_array(self) -> NDArray[np.float32]:
        return convert.image_array(self.depth)

    def frames(self) -> dict[str, NDArray[np.float64]]:
        """child frame -> world_T_child from this observation's ``/tf`` message."""
        out = {}
        for t in self.tf.transforms:
            tr, q = t.transform.translation, t.transform.rotation
            out[t.child_frame_id] = pose_to_matrix([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w], "tf")
        return out


class _Inbox:
    """Messages of one topic by stamp (the last ``keep``), with a condition to wait on."""

    def __init__(self, cond: threading.Condition, keep: int = 16) -> None:
        self.cond = cond
        self.keep = keep
        self.by_stamp: dict[int, tuple[Any, float]] = {}

    def put(self, stamp_ns: int, msg: Any) -> None:
        t = time.perf_counter()
        with self.cond:
            self.by_stamp[stamp_ns] = (msg, t)
            while len(self.by_stamp) > self.keep:
                del self.by_stamp[min(self.by_stamp)]
            self.cond.notify_all()


class Ros1Client:
    """Drives the node ``node`` (default ``/brave6d_sim``) one action at a time."""

    def __init__(self, node: str = "/brave6d_sim", timeout_s: float = 60.0) -> None:
        require_ros1()
        import rospy
        from geometry_msgs.msg import PoseStamped, TwistStamped
        from sensor_msgs.msg import CameraInfo, Image
        from std_srvs.srv import Trigger
        from tf2_msgs.msg import TFMessage

        from brave6d.ros_interface.ros1.messages import load_messages

        self.msgs = load_messages()
        self.node = node.rstrip("/")
        self.timeout_s = timeout_s
        self.cond = threading.Condition()
        self.inbox = {k: _Inbox(self.cond) for k in ("status", "rgb", "depth", "rgb_info", "depth_info", "tf")}
        self.last_stamp_ns = 0
        self.episode_id: str | None = None
        n = self.node
        self._subs = [
            rospy.Subscriber(f"{n}/status", self.msgs.msg.EpisodeStatus, self._put("status"), queue_size=50),
            rospy.Subscriber(f"{n}/rgb/image_raw", Image, self._put("rgb"), queue_size=4, buff_size=IMAGE_BUFF_SIZE,
                             tcp_nodelay=True),
            rospy.Subscriber(f"{n}/depth/image_raw", Image, self._put("depth"), queue_size=4,
                             buff_size=IMAGE_BUFF_SIZE, tcp_nodelay=True),
            rospy.Subscriber(f"{n}/rgb/camera_info", CameraInfo, self._put("rgb_info"), queue_size=4, tcp_nodelay=True),
            rospy.Subscriber(f"{n}/depth/camera_info", CameraInfo, self._put("depth_info"), queue_size=4,
                             tcp_nodelay=True),
            rospy.Subscriber("/tf", TFMessage, self._put_tf, queue_size=50, tcp_nodelay=True),
        ]
        self.pub_pose = rospy.Publisher(f"{n}/set_pose", PoseStamped, queue_size=10)
        self.pub_twist = rospy.Publisher(f"{n}/cmd_twist", TwistStamped, queue_size=10)
        for srv in ("reset", "submit", "close"):
            rospy.wait_for_service(f"{n}/{srv}", timeout=timeout_s)
        self.srv_reset = rospy.ServiceProxy(f"{n}/reset", self.msgs.srv.Reset)
        self.srv_submit = rospy.ServiceProxy(f"{n}/submit", self.msgs.srv.SubmitEstimates)
        self.srv_close = rospy.ServiceProxy(f"{n}/close", Trigger)
        self._wait_connected()

    # ------------------------------------------------------------------ plumbing
    def _put(self, key: str) -> Any:
        def callback(msg: Any) -> None:
            self.inbox[key].put(convert.stamp_ns_of(msg.header), msg)
        return callback

    def _put_tf(self, msg: Any) -> None:
        ours = [t for t in msg.transforms if t.header.frame_id == FRAME_WORLD and t.child_frame_id == FRAME_CAMERA_OPTICAL]
        if ours:
            self.inbox["tf"].put(convert.stamp_ns_of(ours[0].header), msg)

    def _wait_connected(self) -> None:
        deadline = time.monotonic() + self.timeout_s
        while any(p.get_num_connections() == 0 for p in (self.pub_pose, self.pub_twist)) or any(
                s.get_num_connections() == 0 for s in self._subs):
            if time.monotonic() > deadline:
                raise BraveError(f"{self.node}: the node's topics did not connect within {self.timeout_s:g} s")
            time.sleep(0.02)

    def _wait(self, predicate: Any, what: str) -> Any:
        deadline = time.monotonic() + self.timeout_s
        with self.cond:
            while True:
                found = predicate()
                if found is not None:
                    return found
                left = deadline - time.monotonic()
                if left <= 0:
                    raise BraveError(f"{self.node}: no {what} within {self.timeout_s:g} s")
                self.cond.wait(left)

    def _newer_status(self) -> Any:
        newer = [s for s in self.inbox["status"].by_stamp if s > self.last_stamp_ns]
        return self.inbox["status"].by_stamp[min(newer)] if newer else None

    def observation(self, stamp_ns: int, status: Any = None, t_status: float | None = None) -> Ros1Observation:
        """Wait for every message of the observation stamped ``stamp_ns``."""
        keys = ("rgb", "depth", "rgb_info", "depth_info", "tf") + (("status",) if status is None else ())

        def complete() -> dict[str, tuple[Any, float]] | None:
            got = {k: self.inbox[k].by_stamp.get(stamp_ns) for k in keys}
            return None if any(v is None for v in got.values()) else got

        got = self._wait(complete, f"observation stamped {stamp_ns}")
        if status is not None:
            got["status"] = (status, t_status or time.perf_counter())
        self.last_stamp_ns = max(self.last_stamp_ns, stamp_ns)
        return Ros1Observation(stamp_ns, got["status"][0], got["rgb"][0], got["depth"][0], got["rgb_info"][0],
                               got["depth_info"][0], got["tf"][0], {k: v[1] for k, v in got.items()})

    def _after_publish(self, what: str) -> Ros1Observation:
        status, t = self._wait(self._newer_status, f"~status after {what}")
        stamp = convert.stamp_ns_of(status.header)
        if status.action == "error":
            self.last_stamp_ns = max(self.last_stamp_ns, stamp)
            raise BraveError(status.error)
        return self.observation(stamp, status, t)

    # ------------------------------------------------------------------ actions
    def reset(self, scene: str = "", target: str | int = "", seed: int = -1,
              start: ArrayLike | None = None) -> Ros1Observation:
        req = self.msgs.srv.ResetRequest(scene=scene, target=str(target), seed=int(seed), use_start=start is not None)
        if start is not None:
            req.start = convert.pose_message(np.asarray(start, dtype=np.float64))
        res = self.srv_reset(req)
        if not res.success:
            raise BraveError(res.message)
        self.episode_id = res.episode_id
        return self.observation(convert.stamp_ns_of(res.header))

    def set_pose(self, world_T_cam: ArrayLike) -> Ros1Observation:
        from geometry_msgs.msg import PoseStamped

        import rospy

        msg = PoseStamped(pose=convert.pose_message(np.asarray(world_T_cam, dtype=np.float64)))
        msg.header.frame_id, msg.header.stamp = FRAME_WORLD, rospy.Time.now()
        self.pub_pose.publish(msg)
        return self._after_publish("set_pose")

    def move(self, linear: ArrayLike, angular: ArrayLike = (0.0, 0.0, 0.0), frame: str = "camera") -> Ros1Observation:
        """One ``~cmd_twist`` (m/s, rad/s), integrated by the node for its twist duration."""
        import rospy
        from geometry_msgs.msg import TwistStamped, Vector3

        msg = TwistStamped()
        msg.header.frame_id = FRAME_CAMERA_OPTICAL if frame == "camera" else FRAME_WORLD
        msg.header.stamp = rospy.Time.now()
        msg.twist.linear, msg.twist.angular = Vector3(*map(float, linear)), Vector3(*map(float, angular))
        self.pub_twist.publish(msg)
        return self._after_publish("cmd_twist")

    def submit(self, estimates: list[tuple[int, ArrayLike, float]]) -> Any:
        """(obj_id, cam_T_obj 4x4, score) triples -> the ``SubmitEstimates`` response (success, AR, ...)."""
        req = self.msgs.srv.SubmitEstimatesRequest()
        req.header.frame_id = FRAME_CAMERA_OPTICAL
        for obj_id, T, score in estimates:
            req.estimates.append(self.msgs.msg.ObjectEstimate(obj_id=int(obj_id), score=float(score),
                                                              pose=convert.pose_message(np.asarray(T, dtype=np.float64))))
        return self.srv_submit(req)

    def close(self) -> Any:
        return self.srv_close()


# ----------------------------------------------------------------------------- replaying actions
def _record(obs: Ros1Observation, out: Path, k: int, t_sent: float) -> dict[str, Any]:
    np.savez(out / f"step_{k}.npz", rgb=obs.rgb_array(), depth=obs.depth_array())
    info = obs.rgb_info
    return {"status": obs.status_json, "stamp_ns": obs.stamp_ns, "error": obs.status.error,
            "refusal_box": obs.status.refusal_box, "target_frame": obs.status.target_frame,
            "rgb": {"encoding": obs.rgb.encoding, "width": obs.rgb.width, "height": obs.rgb.height,
                    "step": obs.rgb.step, "frame_id": obs.rgb.header.frame_id},
            "depth": {"encoding": obs.depth.encoding, "width": obs.depth.width, "height": obs.depth.height,
                      "step": obs.depth.step, "frame_id": obs.depth.header.frame_id,
                      "is_bigendian": obs.depth.is_bigendian},
            "camera_info": {"K": list(info.K), "P": list(info.P), "D": list(info.D), "R": list(info.R),
                            "distortion_model": info.distortion_model, "width": info.width, "height": info.height,
                            "frame_id": info.header.frame_id, "same_as_depth": list(info.K) == list(obs.depth_info.K)},
            "stamps_equal": len({convert.stamp_ns_of(m.header) for m in (obs.status, obs.rgb, obs.depth, obs.rgb_info,
                                                                            obs.depth_info)}
                                | {convert.stamp_ns_of(t.header) for t in obs.tf.transforms}) == 1,
            "frames": {k: v.tolist() for k, v in obs.frames().items()},
            "latency_s": {"status": obs.received["status"] - t_sent, "rgb": obs.received["rgb"] - t_sent,
                          "depth": obs.received["depth"] - t_sent}}


def run_actions(client: Ros1Client, actions: list[dict[str, Any]], out: Path) -> dict[str, Any]:
    """Run ``actions`` (``{"op": "reset"|"set_pose"|"move"|"submit"|"close", ...}``) and record them.
    ``submit`` takes ``estimates: [{obj_id, cam_T_obj, score}]``, else it sends every object's
    ground truth read from the last observation's ``/tf`` (``gt/`` frames), shifted by ``offset_m``
    in the object's frame."""
    out.mkdir(parents=True, exist_ok=True)
    steps: list[dict[str, Any]] = []
    record: dict[str, Any] = {"steps": steps}
    last: Ros1Observation | None = None
    for k, a in enumerate(actions):
        t0 = time.perf_counter()
        op = a["op"]
        if op == "reset":
            last = client.reset(a.get("scene", ""), a.get("target", ""), int(a.get("seed", -1)), a.get("start"))
        elif op == "set_pose":
            last = client.set_pose(a["world_T_cam"])
        elif op == "move":
            last = client.move(a["linear"], a.get("angular", (0, 0, 0)), a.get("frame", "camera"))
        elif op == "submit":
            estimates = a.get("estimates")
            if estimates is None:
                assert last is not None
                frames = last.frames()
                cam_T_world = np.linalg.inv(frames[FRAME_CAMERA_OPTICAL])
                shift = np.eye(4)
                shift[:3, 3] = a.get("offset_m", (0.0, 0.0, 0.0))
                gt = last.status_json["objects"]
                estimates = [{"obj_id": g["obj_id"], "cam_T_obj": (cam_T_world @ frames[g["frame"]] @ shift).tolist(),
                              "score": 1.0} for g in gt]
            res = client.submit([(e["obj_id"], e["cam_T_obj"], e.get("score", 1.0)) for e in estimates])
            record["submit"] = {"success": res.success, "message": res.message, "ar": res.ar, "ar_vsd": res.ar_vsd,
                                "ar_mssd": res.ar_mssd, "ar_mspd": res.ar_mspd, "adjustments": res.adjustments,
                                "steps": res.steps, "refusals": res.refusals, "submitted": res.submitted,
                                "json": _node_json(res.json, "SubmitEstimates.json") if res.json else None}
            record["estimates"] = estimates
            continue
        elif op == "close":
            res = client.close()
            record["close"] = {"success": res.success, "message": res.message}
            continue
        else:
            raise BraveError(f"actions[{k}].op: unknown {op!r}")
        steps.append({"op": op, **_record(last, out, len(steps), t0)})
    (out / "record.json").write_text(json.dumps(record, indent=1), encoding="utf-8")
    return record


def main(argv: list[str] | None = None) -> int:
    import rospy

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m brave6d.ros_interface.ros1.client ACTIONS.json OUT_DIR", file=sys.stderr)
        return 2
    actions = json.loads(Path(args[0]).read_text(encoding="utf-8"))
    rospy.init_node("brave6d_replay", anonymous=True, disable_signals=True)
    client = Ros1Client(actions.get("node", "/brave6d_sim"), float(actions.get("timeout_s", 60.0)))
    run_actions(client, actions["actions"], Path(args[1]))
    rospy.signal_shutdown("done")
    return 0


if __name__ == "__main__":
    require_ros1()
    sys.exit(main())

"""The agents' episode client over ROS: the same agent objects that play over HTTP and gym
(:class:`brave6d.evaluation.agents.EpisodeClient`) play through the ROS 2 and ROS 1 nodes.

:class:`Ros2EpisodeClient` wraps the rclpy :class:`~brave6d.ros_interface.ros2.agent.Ros2Agent` (the
node's reset / set_pose / submit services, images, camera info and /tf); :class:`Ros1EpisodeClient`
the rospy :class:`~brave6d.ros_interface.ros1.client.Ros1Client` (its reset / submit services and
``~set_pose`` topic; ``rospy.init_node`` is the caller's). The nodes publish neither the scene's
description nor its models: both come from the bundle folder the node serves, as ``GET /bundle``
shows it in scored mode (no object poses) and ``GET /bundle/models/{obj_id}``. The images are the
node's size (``--width/--height``: another size asked for is refused in one line), the depth the
server's (metres, 0 = no data: REP 118's NaN for no data is turned back), the episode logs
carry the node's ``--agent`` name, and ``submit`` answers with the node's score of the episode
(``ar``, ``adjustments``, ...).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import BraveError
from brave6d.evaluation.agents import TransportStep, TransportView
from brave6d.ros_interface.bridge import Estimate
from brave6d.ros_interface.frames import FRAME_CAMERA_OPTICAL

#: The largest object model (BOP PLY) read from the bundle folder.
MAX_MODEL_BYTES = 256 << 20


def served_depth(depth_m: NDArray[np.floating]) -> NDArray[np.float32]:
    """A ROS depth image (``32FC1`` metres, REP 118: NaN = no data) as the server and the estimators'
    interface give depth (float32 metres, 0 = no data): every value that is not a positive finite
    number becomes 0."""
    d = np.asarray(depth_m, dtype=np.float32)
    return np.where(np.isfinite(d) & (d > 0), d, np.float32(0.0)).astype(np.float32)


class _BundleFolder:
    """The scene's scored description and object models from the bundle folder a ROS node serves."""

    def __init__(self, bundle_dir: Path | str) -> None:
        from brave6d.serve import SCORED, load_bundle, public_bundle

        self._bundle = load_bundle(bundle_dir)
        self._description = public_bundle(self._bundle.summary(), SCORED)
        self.scene: str | int | None = None

    def _one_scene(self, scene: str | int | None, call: str) -> None:
        if scene is not None:
            raise BraveError(f"{type(self).__name__}.{call}: scene {scene!r}: this client plays the one scene of "
                             f"{self._bundle.root} (give none)")

    def bundle(self, scene: str | int | None = None) -> dict[str, Any]:
        self._one_scene(scene, "bundle")
        return dict(self._description)

    def model(self, obj_id: int, scene: str | int | None = None) -> bytes:
        self._one_scene(scene, "model")
        obj = next((o for o in self._bundle.objects if o.obj_id == int(obj_id)), None)
        if obj is None:
            raise BraveError(f"{self._bundle.root}: no object with obj_id {obj_id} "
                             f"(known: {sorted({o.obj_id for o in self._bundle.objects})})")
        path = self._bundle.model_path(obj)
        with path.open("rb") as f:
            data = f.read(MAX_MODEL_BYTES + 1)
        if len(data) > MAX_MODEL_BYTES:
            raise BraveError(f"{path}: the model is larger than {MAX_MODEL_BYTES >> 20} MiB")
        return data

    def _checked_size(self, step: TransportStep, width: int | None, height: int | None, close: Any) -> TransportStep:
        """``step`` when its images are ``width`` x ``height`` (None: any); else the episode is closed
        (``close()``) and refused in one line: the node's image size is set when it starts."""
        h, w = step.observation.rgb.shape[:2]
        if (width is not None and width != w) or (height is not None and height != h):
            close()
            raise BraveError(f"{type(self).__name__}: the node serves {w}x{h} images, the agent asked for "
                             f"{width}x{height}: start the node with --width {width} --height {height} or ask for "
                             "its size")
        return step


class Ros2EpisodeClient(_BundleFolder):
    """An episode client over a :class:`~brave6d.ros_interface.ros2.agent.Ros2Agent` driving
    ``brave6d ros2 BUNDLE``; ``bundle_dir`` is that bundle (its description and models)."""

    def __init__(self, ros_agent: Any, bundle_dir: Path | str) -> None:
        super().__init__(bundle_dir)
        self.ros = ros_agent

    def reset(self, target: int | str | None = None, width: int | None = None, height: int | None = None,
              seed: int | None = None, agent: str | None = None, scene: str | int | None = None) -> TransportStep:
        self._one_scene(scene, "reset")
        return self._checked_size(self._step(self.ros.reset(target=target, seed=seed)), width, height, self.ros.close)

    def set_pose(self, world_T_cam: ArrayLike) -> TransportStep:
        return self._step(self.ros.set_pose(np.asarray(world_T_cam, dtype=np.float64)))

    def submit(self, estimates: list[Any], agent: str | None = None) -> dict[str, Any]:
        return dict(self.ros.submit([Estimate(int(e.obj_id), np.asarray(e.cam_T_obj, dtype=np.float64), float(e.score))
                                     for e in estimates]))

    @staticmethod
    def _step(obs: Any) -> TransportStep:
        status = obs.status
        view = TransportView(obs.rgb, served_depth(obs.depth_m), obs.K, obs.world_T_cam)
        return TransportStep(str(status["episode_id"]), str(status["action"]), bool(status["accepted"]),
                             dict(status["target"] or {}), view)


class Ros1EpisodeClient(_BundleFolder):
    """An episode client over a :class:`~brave6d.ros_interface.ros1.client.Ros1Client` driving
    ``brave6d ros1 BUNDLE`` (``rospy.init_node`` is the caller's); ``bundle_dir`` is that bundle."""

    def __init__(self, ros_client: Any, bundle_dir: Path | str) -> None:
        super().__init__(bundle_dir)
        self.ros = ros_client

    def reset(self, target: int | str | None = None, width: int | None = None, height: int | None = None,
              seed: int | None = None, agent: str | None = None, scene: str | int | None = None) -> TransportStep:
        self._one_scene(scene, "reset")
        obs = self.ros.reset("", "" if target is None else str(target), -1 if seed is None else int(seed))
        return self._checked_size(self._step(obs), width, height, self.ros.close)

    def set_pose(self, world_T_cam: ArrayLike) -> TransportStep:
        return self._step(self.ros.set_pose(np.asarray(world_T_cam, dtype=np.float64)))

    def submit(self, estimates: list[Any], agent: str | None = None) -> dict[str, Any]:
        from brave6d.serve import ClientLimits, parse_reply

        res = self.ros.submit([(int(e.obj_id), np.asarray(e.cam_T_obj, dtype=np.float64), float(e.score))
                               for e in estimates])
        if not res.success:
            raise BraveError(f"Ros1EpisodeClient.submit: the node refused: {res.message}")
        out = parse_reply(res.json.encode("utf-8", "surrogatepass"), ClientLimits(), "SubmitEstimates.json")
        if not isinstance(out, dict):
            raise BraveError("Ros1EpisodeClient.submit: the node's SubmitEstimates.json is not a JSON object")
        return out

    @staticmethod
    def _step(obs: Any) -> TransportStep:
        status = obs.status_json
        K = np.asarray(obs.rgb_info.K, dtype=np.float64).reshape(3, 3)
        view = TransportView(obs.rgb_array(), served_depth(obs.depth_array()), K, obs.frames()[FRAME_CAMERA_OPTICAL])
        return TransportStep(str(status["episode_id"]), str(status["action"]), bool(status["accepted"]),
                             dict(status["target"] or {}), view)

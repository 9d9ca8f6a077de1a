"""The agents' episode client and its transports: the same agent objects play over HTTP, gym and ROS.

An agent and :func:`~brave6d.evaluation.agents.episode.run_episode` use a client only through
:class:`EpisodeClient`: ``reset`` / ``set_pose`` / ``submit`` and what a benchmark user is given
about the scene (``bundle``: ``GET /bundle``'s scored description, ``model``: an object's BOP PLY).
A step answers with :class:`EpisodeStep` (``action``, ``accepted``, ``target``, ``episode_id`` and
the ``observation``'s ``rgb``, ``depth``, ``K``, ``world_T_cam``). The implementations:

- HTTP: ``serve``'s :class:`~brave6d.serve.BraveClient` itself.
- gym: :class:`GymEpisodeClient` over a :class:`~brave6d.serve.BraveEnv` (its ``reset``, the
  ``{"world_T_cam": ...}`` action and ``submit``); the scene description and models come from the
  env's server (Gymnasium's API has no call for them).
- ROS 2: :class:`Ros2EpisodeClient` over a :class:`~brave6d.ros_interface.ros2.agent.Ros2Agent`
  (the node's reset / set_pose / submit services, images, camera info and /tf); ROS 1:
  :class:`Ros1EpisodeClient` over a :class:`~brave6d.ros_interface.ros1.client.Ros1Client` (its
  reset / submit services and ``~set_pose`` topic). The scene description and models come from
  the bundle folder the node serves (the nodes publish neither). The images are the node's size
  (``--width/--height``), the episode logs carry the node's ``--agent`` name, and ``submit``
  answers with the episode's score (``ar``).

None of them forwards anything beyond what the transport itself gives the agent: in a scored run
no ground truth exists to forward.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import BraveError

#: The largest object model (BOP PLY) the ROS 2 client reads from the bundle folder.
MAX_MODEL_BYTES = 256 << 20


class EpisodeStep(Protocol):
    """What a reset or a move answers, as the agents read it."""

    episode_id: str
    action: str  # "reset", "set_pose"
    accepted: bool
    target: Mapping[str, Any]  # the target's obj_id, gt_id, name
    observation: Any  # rgb (H, W, 3) uint8, depth (H, W) float32 m or None, K (3, 3), world_T_cam (4, 4)


class EpisodeClient(Protocol):
    """The client interface the agents and the episode loop are written against (module docstring)."""

    scene: str | int | None  # the scene of the last reset (None: the only one)

    def reset(self, target: int | str | None = None, width: int | None = None, height: int | None = None,
              seed: int | None = None, agent: str | None = None, scene: str | int | None = None) -> EpisodeStep: ...

    def set_pose(self, world_T_cam: ArrayLike) -> EpisodeStep: ...

    def submit(self, estimates: list[Any], agent: str | None = None) -> dict[str, Any]: ...

    def bundle(self, scene: str | int | None = None) -> dict[str, Any]: ...

    def model(self, obj_id: int, scene: str | int | None = None) -> bytes: ...


@dataclass(frozen=True)
class View:
    """One observation as a transport delivers it (the fields the agents read)."""

    rgb: NDArray[np.uint8]
    depth: NDArray[np.float32] | None
    K: NDArray[np.float64]
    world_T_cam: NDArray[np.float64]


@dataclass(frozen=True)
class Step:
    """An :class:`EpisodeStep` made by a transport other than HTTP."""

    episode_id: str
    action: str
    accepted: bool
    target: Mapping[str, Any]
    observation: View


def _one_scene(scene: str | int | None, where: str) -> None:
    if scene is not None:
        raise BraveError(f"{where}: scene {scene!r}: this transport plays its server's one scene (give none)")


class GymEpisodeClient:
    """:class:`EpisodeClient` over a :class:`~brave6d.serve.BraveEnv` (a scored or training env)."""

    def __init__(self, env: Any) -> None:
        self.env = env
        self.scene: str | int | None = None

    def bundle(self, scene: str | int | None = None) -> dict[str, Any]:
        _one_scene(scene, "GymEpisodeClient.bundle")
        return dict(self.env.client.bundle())

    def model(self, obj_id: int, scene: str | int | None = None) -> bytes:
        _one_scene(scene, "GymEpisodeClient.model")
        return bytes(self.env.client.model(obj_id))

    def reset(self, target: int | str | None = None, width: int | None = None, height: int | None = None,
              seed: int | None = None, agent: str | None = None, scene: str | int | None = None) -> Step:
        _one_scene(scene, "GymEpisodeClient.reset")
        options = {k: v for k, v in (("target", target), ("width", width), ("height", height), ("agent", agent))
                   if v is not None}
        obs, info = self.env.reset(seed=seed, options=options)
        return self._step("reset", obs, info)

    def set_pose(self, world_T_cam: ArrayLike) -> Step:
        obs, _, _, truncated, info = self.env.step({"world_T_cam": np.asarray(world_T_cam, dtype=np.float64)})
        if truncated:
            raise BraveError(f"GymEpisodeClient: the env ended the episode after its max_steps={self.env.max_steps} "
                             "steps, before the agent submitted (give BraveEnv a larger max_steps)")
        return self._step("set_pose", obs, info)

    def submit(self, estimates: list[Any], agent: str | None = None) -> dict[str, Any]:
        *_, info = self.env.submit(list(estimates), agent=agent)
        return dict(info["submission"])

    @staticmethod
    def _step(action: str, obs: Mapping[str, Any], info: Mapping[str, Any]) -> Step:
        return Step(str(info["episode_id"]), action, bool(info["accepted"]), dict(info["target"]),
                    View(obs["rgb"], obs["depth"], np.asarray(obs["K"], dtype=np.float64),
                         np.asarray(obs["world_T_cam"], dtype=np.float64)))


class _BundleFolder:
    """The scene's scored description and object models from the bundle folder a ROS node serves
    (the nodes publish neither): what ``GET /bundle`` and ``GET /bundle/models/{obj_id}`` answer."""

    def __init__(self, bundle_dir: Path | str) -> None:
        from brave6d.serve import SCORED, load_bundle, public_bundle

        self._bundle = load_bundle(bundle_dir)
        self._description = public_bundle(self._bundle.summary(), SCORED)
        self.scene: str | int | None = None

    def bundle(self, scene: str | int | None = None) -> dict[str, Any]:
        _one_scene(scene, f"{type(self).__name__}.bundle")
        return dict(self._description)

    def model(self, obj_id: int, scene: str | int | None = None) -> bytes:
        _one_scene(scene, f"{type(self).__name__}.model")
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

    def _checked_size(self, step: Step, width: int | None, height: int | None, close: Any) -> Step:
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
    """:class:`EpisodeClient` over a :class:`~brave6d.ros_interface.ros2.agent.Ros2Agent` driving
    ``brave6d ros2 BUNDLE``; ``bundle_dir`` is that bundle (its description and models)."""

    def __init__(self, ros_agent: Any, bundle_dir: Path | str) -> None:
        super().__init__(bundle_dir)
        self.ros = ros_agent

    def reset(self, target: int | str | None = None, width: int | None = None, height: int | None = None,
              seed: int | None = None, agent: str | None = None, scene: str | int | None = None) -> Step:
        _one_scene(scene, "Ros2EpisodeClient.reset")
        return self._checked_size(self._step(self.ros.reset(target=target, seed=seed)), width, height, self.ros.close)

    def set_pose(self, world_T_cam: ArrayLike) -> Step:
        return self._step(self.ros.set_pose(np.asarray(world_T_cam, dtype=np.float64)))

    def submit(self, estimates: list[Any], agent: str | None = None) -> dict[str, Any]:
        from brave6d.ros_interface import Estimate

        return dict(self.ros.submit([Estimate(int(e.obj_id), np.asarray(e.cam_T_obj, dtype=np.float64), float(e.score))
                                     for e in estimates]))

    @staticmethod
    def _step(obs: Any) -> Step:
        status = obs.status
        return Step(str(status["episode_id"]), str(status["action"]), bool(status["accepted"]),
                    dict(status["target"] or {}), View(obs.rgb, obs.depth_m, obs.K, obs.world_T_cam))


class Ros1EpisodeClient(_BundleFolder):
    """:class:`EpisodeClient` over a :class:`~brave6d.ros_interface.ros1.client.Ros1Client` driving
    ``brave6d ros1 BUNDLE`` (``rospy.init_node`` is the caller's); ``bundle_dir`` is that bundle."""

    def __init__(self, ros_client: Any, bundle_dir: Path | str) -> None:
        super().__init__(bundle_dir)
        self.ros = ros_client

    def reset(self, target: int | str | None = None, width: int | None = None, height: int | None = None,
              seed: int | None = None, agent: str | None = None, scene: str | int | None = None) -> Step:
        _one_scene(scene, "Ros1EpisodeClient.reset")
        obs = self.ros.reset("", "" if target is None else str(target), -1 if seed is None else int(seed))
        return self._checked_size(self._step(obs), width, height, self.ros.close)

    def set_pose(self, world_T_cam: ArrayLike) -> Step:
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
    def _step(obs: Any) -> Step:
        from brave6d.ros_interface import FRAME_CAMERA_OPTICAL

        status = obs.status_json
        return Step(str(status["episode_id"]), str(status["action"]), bool(status["accepted"]),
                    dict(status["target"] or {}),
                    View(obs.rgb_array(), obs.depth_array(), np.asarray(obs.rgb_info.K, dtype=np.float64).reshape(3, 3),
                         obs.frames()[FRAME_CAMERA_OPTICAL]))

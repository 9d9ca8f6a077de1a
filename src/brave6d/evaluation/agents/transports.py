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
- ROS 2 and ROS 1: ``brave6d.ros_interface``'s ``Ros2EpisodeClient`` (over the rclpy ``Ros2Agent``)
  and ``Ros1EpisodeClient`` (over the rospy ``Ros1Client``), in the ROS stage
  (:mod:`brave6d.ros_interface.episode_clients`), built from :class:`TransportStep` and
  :class:`TransportView`.

None of them forwards anything beyond what the transport itself gives the agent: in a scored run
no ground truth exists to forward.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import BraveError


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
class TransportView:
    """One observation as a transport delivers it (the fields the agents read)."""

    rgb: NDArray[np.uint8]
    depth: NDArray[np.float32] | None
    K: NDArray[np.float64]
    world_T_cam: NDArray[np.float64]


@dataclass(frozen=True)
class TransportStep:
    """An :class:`EpisodeStep` made by a transport other than HTTP."""

    episode_id: str
    action: str
    accepted: bool
    target: Mapping[str, Any]
    observation: TransportView


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
              seed: int | None = None, agent: str | None = None, scene: str | int | None = None) -> TransportStep:
        _one_scene(scene, "GymEpisodeClient.reset")
        options = {k: v for k, v in (("target", target), ("width", width), ("height", height), ("agent", agent))
                   if v is not None}
        obs, info = self.env.reset(seed=seed, options=options)
        return self._step("reset", obs, info)

    def set_pose(self, world_T_cam: ArrayLike) -> TransportStep:
        obs, _, _, truncated, info = self.env.step({"world_T_cam": np.asarray(world_T_cam, dtype=np.float64)})
        if truncated:
            raise BraveError(f"GymEpisodeClient: the env ended the episode after its max_steps={self.env.max_steps} "
                             "steps, before the agent submitted (give BraveEnv a larger max_steps)")
        return self._step("set_pose", obs, info)

    def submit(self, estimates: list[Any], agent: str | None = None) -> dict[str, Any]:
        *_, info = self.env.submit(list(estimates), agent=agent)
        return dict(info["submission"])

    @staticmethod
    def _step(action: str, obs: Mapping[str, Any], info: Mapping[str, Any]) -> TransportStep:
        view = TransportView(obs["rgb"], obs["depth"], np.asarray(obs["K"], dtype=np.float64),
                             np.asarray(obs["world_T_cam"], dtype=np.float64))
        return TransportStep(str(info["episode_id"]), action, bool(info["accepted"]), dict(info["target"]), view)

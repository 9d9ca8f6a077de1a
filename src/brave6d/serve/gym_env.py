"""A Gymnasium environment over the render server.

    from brave6d.serve import BraveEnv

    env = BraveEnv("http://127.0.0.1:8765", target="hex_nut", width=320, height=240)
    obs, info = env.reset(seed=0)
    for _ in range(20):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        if terminated or truncated:
            break
    env.close()

**Observation** (a dict of arrays, what a robot would sense): ``rgb`` (H, W, 3) uint8, ``depth``
(H, W) float32 metres (0 = no data), ``K`` (3, 3), ``world_T_cam`` (4, 4); never the ground truth,
which the benchmark's agents must estimate.

**Mode** (``mode``, :mod:`brave6d.serve.modes`): ``"scored"`` (the default) plays on a scored
server, which sends no ground truth at all; ``"training"`` on a ``--training`` server, whose
objects' ``cam_T_obj`` and visible fractions go to ``info["objects"]``. A server in the other
mode is refused at ``reset`` (a one-line :class:`BraveError` saying how to start it).

**Actions**:

* a ``(6,)`` array in ``[-1, 1]``: a camera-frame twist ``(vx, vy, vz, wx, wy, wz)`` scaled by
  ``max_linear`` (m/s) and ``max_angular`` (rad/s), applied for ``step_duration`` s;
* ``{"linear": ..., "angular": ..., "duration": ..., "frame": "camera"|"world"}``: a twist;
* ``{"world_T_cam": 4x4}`` (or any pose dict the API takes): teleport (``set_pose``);
* ``{"stop": True}``: the agent declares it is done (habitat's STOP): the episode ends with
  ``terminated = True`` and is closed on the server.
* ``{"submit": [PoseEstimate | {obj_id, R, t_m, score}, ...]}`` (or :meth:`BraveEnv.submit`):
  hand in the final pose estimates (camera frame of the current view); the episode ends with
  ``terminated = True``; ``info["submission"]`` holds the server's reply.

**Reward** (documented choice): in training mode, the increase of the target's visible pixel area
since the previous step, as a fraction of the image area (``px_count_visib`` difference / (W * H));
0 for a refused action. In scored mode always 0: the visible area is ground truth, and the
episode's score is ``brave6d evaluate``'s once ``submit`` has closed it. ``truncated`` is True
after ``max_steps`` steps. ``info`` holds ``accepted``, ``collided``, ``refusal``, ``adjustments``
(position adjustments, the benchmark's cost), ``target`` (its ids and name), ``mode``,
``timings_ms``, ``episode_id`` and, in training mode only, ``objects``.

The class is a ``gymnasium.Env`` and its spaces are ``gymnasium.spaces`` (``Box``, ``Dict``).
"""

from __future__ import annotations

import logging
from typing import Any, ClassVar

import gymnasium as gym
import httpx
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.serve.client import BraveClient, Observation, PoseEstimate, ServerError, StepResult
from brave6d.serve.modes import SCORED, TRAINING, check_mode

log = logging.getLogger(__name__)


def twist_space() -> spaces.Box:
    """The action space: a camera-frame twist ``(vx, vy, vz, wx, wy, wz)`` in ``[-1, 1]`` (scaled by the env)."""
    return spaces.Box(-1.0, 1.0, (6,), np.float32)


def observation_space(width: int, height: int) -> spaces.Dict:
    """One agent's observation space at ``width`` x ``height`` (the module docstring)."""
    return spaces.Dict({
        "rgb": spaces.Box(0, 255, (height, width, 3), np.uint8),
        "depth": spaces.Box(0.0, np.inf, (height, width), np.float32),
        "K": spaces.Box(-np.inf, np.inf, (3, 3), np.float64),
        "world_T_cam": spaces.Box(-np.inf, np.inf, (4, 4), np.float64),
    })


def visible_px(view: Any) -> int:
    """The target's visible pixel count in ``view`` (a client ``Observation`` or a server
    ``RenderedView``: both have ``target()``); 0 without a view, a target or visibility."""
    t = view.target() if view is not None else None
    return int(t.px_count_visib or 0) if t is not None else 0


def visibility_reward(accepted: bool, before_px: int, after_px: int, width: int, height: int) -> float:
    """The documented reward: the target's visible area gained, as a fraction of the image; 0 when refused."""
    return (after_px - before_px) / float(width * height) if accepted else 0.0


class BraveEnv(gym.Env):  # type: ignore[misc]
    """See the module docstring."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"]}

    def __init__(self, base_url: str = "http://127.0.0.1:8765", *, client: BraveClient | None = None,
                 target: int | str | None = None, width: int = 320, height: int = 240, max_steps: int = 100,
                 step_duration: float = 0.5, max_linear: float = 0.1, max_angular: float = 0.5,
                 frame: str = "camera", render_mode: str | None = "rgb_array", agent: str | None = None,
                 mode: str = SCORED) -> None:
        self.mode = check_mode(mode, "BraveEnv: mode")
        self.client = client if client is not None else BraveClient(base_url)
        self.agent = agent
        self._own_client = client is None
        self.target = target
        self.width, self.height = int(width), int(height)
        self.max_steps = int(max_steps)
        self.step_duration = float(step_duration)
        self.max_linear, self.max_angular = float(max_linear), float(max_angular)
        self.frame = frame
        self.render_mode = render_mode
        self.action_space = twist_space()
        self.observation_space = observation_space(self.width, self.height)
        self._steps = 0
        self._last: Observation | None = None
        self._done = True

    # -------------------------------------------------------------- helpers
    @staticmethod
    def _obs(o: Observation) -> dict[str, NDArray[Any]]:
        h, w = o.height, o.width
        return {"rgb": o.rgb if o.rgb is not None else np.zeros((h, w, 3), np.uint8),
                "depth": o.depth if o.depth is not None else np.zeros((h, w), np.float32),
                "K": o.K, "world_T_cam": o.world_T_cam}

    def _info(self, step: StepResult) -> dict[str, Any]:
        info = {"episode_id": step.episode_id, "accepted": step.accepted, "collided": step.collided,
                "refusal": step.refusal, "adjustments": step.adjustments, "target": step.target, "mode": self.mode,
                "timings_ms": step.timings_ms, "move": step.move}
        if self.mode == TRAINING:
            info["objects"] = step.observation.objects
        return info

    def _check_mode(self, step: StepResult) -> None:
        """Refuse (after closing the new episode) a server whose mode is not the env's."""
        if step.mode == self.mode:
            return
        try:
            self.client.close()
        except (ServerError, httpx.HTTPError) as exc:
            log.debug("closing the refused episode failed: %s", exc)
        self._done = True
        how = ("start it with --training" if self.mode == TRAINING else
               "start it without --training, or pass BraveEnv(..., mode='training') to develop with the truth")
        raise BraveError(f"BraveEnv(mode={self.mode!r}): the server runs in {step.mode} mode: {how}")

    # -------------------------------------------------------------- Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
        """Start a new episode. ``options``: ``target``, ``start`` (4x4 world_T_cam or pose dict),
        ``width``, ``height``. ``seed`` seeds the random start pose (and ``action_space.sample``)."""
        super().reset(seed=seed)
        opts = dict(options or {})
        if self.client.episode_id is not None and not self._done:
            try:
                self.client.close()
            except (ServerError, httpx.HTTPError) as exc:  # the old episode may have expired
                log.debug("closing the previous episode failed: %s", exc)
        if seed is not None:
            self.action_space.seed(seed)
        step = self.client.reset(target=opts.get("target", self.target), width=opts.get("width", self.width),
                                 height=opts.get("height", self.height), start=opts.get("start"), seed=seed,
                                 agent=opts.get("agent", self.agent))
        self._check_mode(step)
        self._steps = 0
        self._done = False
        self._last = step.observation
        return self._obs(step.observation), self._info(step)

    def step(self, action: Any) -> tuple[dict[str, NDArray[Any]], float, bool, bool, dict[str, Any]]:
        if self._done or self._last is None:
            raise RuntimeError("call reset() before step() (the episode has ended)")
        if isinstance(action, dict) and action.get("stop"):
            summary = self.client.close()
            self._done = True
            obs = self._obs(self._last)
            return obs, 0.0, True, False, {"episode_id": summary.get("episode_id"), "stopped": True, "mode": self.mode,
                                           "adjustments": summary.get("adjustments"), "summary": summary}
        if isinstance(action, dict) and "submit" in action:
            reply = self.client.submit(list(action["submit"]), agent=action.get("agent"))
            self._done = True
            return self._obs(self._last), 0.0, True, False, {
                "episode_id": reply.get("episode_id"), "submitted": True, "mode": self.mode,
                "adjustments": reply.get("adjustments"), "submission": reply, "summary": reply}
        if isinstance(action, dict) and ("world_T_cam" in action or "position" in action or "look_at" in action):
            step = self.client.set_pose(action.get("world_T_cam", action))
        elif isinstance(action, dict):
            step = self.client.move(action.get("linear", (0, 0, 0)), action.get("angular", (0, 0, 0)),
                                    float(action.get("duration", self.step_duration)), action.get("frame", self.frame))
        else:
            a = np.clip(np.asarray(action, dtype=np.float64).reshape(6), -1.0, 1.0)
            if not np.any(a):  # a null twist: nothing to ask the server (no adjustment)
                self._steps += 1
                return self._end_step(self._last, 0.0, {"accepted": True, "noop": True, "mode": self.mode,
                                                        "episode_id": self.client.episode_id})
            step = self.client.move(a[:3] * self.max_linear, a[3:] * self.max_angular, self.step_duration, self.frame)
        before = visible_px(self._last)
        self._last = step.observation
        self._steps += 1
        reward = visibility_reward(step.accepted, before, visible_px(step.observation), step.observation.width,
                                   step.observation.height) if self.mode == TRAINING else 0.0
        return self._end_step(step.observation, reward, self._info(step))

    def submit(self, estimates: list[PoseEstimate | dict[str, Any]], agent: str | None = None
               ) -> tuple[dict[str, NDArray[Any]], float, bool, bool, dict[str, Any]]:
        """Hand in the final estimates and end the episode (the ``{"submit": ...}`` action)."""
        action: dict[str, Any] = {"submit": estimates}
        if agent is not None:
            action["agent"] = agent
        return self.step(action)

    def _end_step(self, observation: Observation, reward: float, info: dict[str, Any]
                  ) -> tuple[dict[str, NDArray[Any]], float, bool, bool, dict[str, Any]]:
        truncated = self._steps >= self.max_steps
        if truncated:
            self._done = True
            try:
                info["summary"] = self.client.close()
            except (ServerError, httpx.HTTPError) as exc:  # the episode may have expired on the server
                log.debug("closing the truncated episode failed: %s", exc)
        return self._obs(observation), float(reward), False, truncated, info

    def render(self) -> NDArray[np.uint8] | None:
        return None if self._last is None else self._last.rgb

    def close(self) -> None:
        if self.client.episode_id is not None and not self._done:
            try:
                self.client.close()
            except (ServerError, httpx.HTTPError) as exc:
                log.debug("closing the episode failed: %s", exc)
        self._done = True
        if self._own_client:
            self.client.disconnect()

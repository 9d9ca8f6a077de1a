"""N agents on one scene stepping together: a ``gymnasium.vector.VectorEnv`` whose renders are batched.

    from brave6d.serve import BraveVectorEnv, SceneServer, load_bundle

    envs = BraveVectorEnv(SceneServer(load_bundle("runs/demo/scene/bundle"), "auto"), num_envs=64,
                          target="hex_nut", width=320, height=240)
    obs, info = envs.reset(seed=0)                    # obs["rgb"]: (64, 240, 320, 3) uint8
    obs, rewards, terminated, truncated, info = envs.step(envs.action_space.sample())

Each sub-environment is a :class:`brave6d.serve.BraveEnv` run in process instead of over HTTP:
the same episodes (an :class:`brave6d.serve.episode_manager.EpisodeManager`, its rules, logs and
counters), the same observation and action spaces, the same twist scaling, null-twist no-op,
reward and truncation at ``max_steps``. A sub-environment reset with seed ``s`` sees what
``BraveEnv.reset(seed=s)`` sees, and the same actions give the same observations and rewards.

What differs is the render: :meth:`step` runs the N moves through
:meth:`EpisodeManager.move_many`, which draws all accepted views in one
:meth:`SplatRenderer.render_batch` call (gsplat batches the cameras on CUDA; the CPU kernels
spread the cameras' Gaussians and tiles over the cores).

Only twists (the ``(6,)`` Box actions, batched to ``(N, 6)``): teleports, ``stop`` and
``submit`` stay :class:`BraveEnv`'s. ``reset(seed=s)`` seeds sub-environment ``i`` with
``s + i`` (gymnasium's rule; a list gives each its own); episodes never terminate, they are
truncated after ``max_steps`` and reset on the next step (``AutoresetMode.NEXT_STEP``: that
step ignores the sub-environment's action and returns its first observation with reward 0),
with a start seed drawn from the sub-environment's generator, so a seeded run repeats.
``info`` holds ``episode_id``, ``accepted``, ``collided`` and ``adjustments`` per sub-environment
(gymnasium's ``_key`` masks beside them).

``mode`` is :class:`BraveEnv`'s: ``"scored"`` (default; the episodes run on an
:class:`EpisodeManager` of that mode, whose views carry no ground truth, so the reward is 0) or
``"training"`` (the visible-area reward). Given an :class:`EpisodeManager`, its mode must be ``mode``.

**Observations** are read-only (``writeable`` False: an agent cannot change the images it is
scored on) and fresh each step: the renders are drawn straight into a new batch (the renderer's
``out``), only the sub-environments that did not render (a refusal, a null twist, a reset) have
their image copied in, and no later step writes into a batch already returned.

``visibility_stride`` (default :data:`VECTOR_VISIBILITY_STRIDE`; given an :class:`EpisodeManager`,
its stride unless one is named, which must then be the manager's) is the episodes' stride of the
visible fractions, hence of the training reward: one pixel per ``s x s`` block
(:mod:`brave6d.serve.visibility`). A server computes every pixel unless started with ``--visibility-stride``;
a single env equals the vector env bit for bit when both use the same stride.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.serve.episode_manager import EpisodeManager, MoveRequest
from brave6d.serve.episodes import ActionResult, RenderedView, SceneServer
from brave6d.serve.gym_env import observation_space, twist_space, visibility_reward, visible_px
from brave6d.serve.modes import SCORED, check_mode

Obs = dict[str, NDArray[Any]]

#: the vector env's visible-fraction stride unless one is given: chosen by measurement (docs/BENCHMARKS.md,
#: the host side of a batched step: its time and its error against every pixel)
VECTOR_VISIBILITY_STRIDE = 4


def sub_seeds(seed: int | Sequence[int | None] | None, n: int) -> list[int | None]:
    """Gymnasium's seeding of ``n`` sub-environments: ``seed + i``, a list as given, or all None."""
    if seed is None:
        return [None] * n
    if isinstance(seed, (int, np.integer)):
        return [int(seed) + i for i in range(n)]
    seeds = list(seed)
    if len(seeds) != n:
        raise BraveError(f"reset: {len(seeds)} seeds given for {n} environments")
    return seeds


class BraveVectorEnv(VectorEnv):  # type: ignore[misc]
    """See the module docstring."""

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}  # noqa: RUF012

    def __init__(self, scene: SceneServer | EpisodeManager, num_envs: int, *, target: int | str | None = None,
                 width: int = 320, height: int = 240, max_steps: int = 100, step_duration: float = 0.5,
                 max_linear: float = 0.1, max_angular: float = 0.5, frame: str = "camera",
                 agent: str | None = None, mode: str = SCORED,
                 visibility_stride: int | None = None) -> None:
        if num_envs < 1:
            raise BraveError(f"BraveVectorEnv: num_envs must be at least 1, got {num_envs}")
        mode = check_mode(mode, "BraveVectorEnv: mode")
        if isinstance(scene, EpisodeManager) and scene.mode != mode:
            raise BraveError(f"BraveVectorEnv(mode={mode!r}): the episode manager given runs in {scene.mode} mode")
        if isinstance(scene, EpisodeManager) and visibility_stride not in (None, scene.visibility_stride):
            raise BraveError(f"BraveVectorEnv(visibility_stride={visibility_stride}): the episode manager given "
                             f"computes visible fractions at stride {scene.visibility_stride}")
        self.manager = scene if isinstance(scene, EpisodeManager) else EpisodeManager(
            scene, max_episodes=num_envs, mode=mode,
            visibility_stride=VECTOR_VISIBILITY_STRIDE if visibility_stride is None else visibility_stride)
        self.mode = mode
        self.num_envs = int(num_envs)
        self.target, self.agent, self.frame = target, agent, frame
        self.width, self.height, self.max_steps = int(width), int(height), int(max_steps)
        self.step_duration, self.max_linear, self.max_angular = float(step_duration), float(max_linear), float(max_angular)
        self.single_observation_space = observation_space(self.width, self.height)
        self.single_action_space = twist_space()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._ids: list[str | None] = [None] * self.num_envs
        self._views: list[RenderedView | None] = [None] * self.num_envs
        self._steps = np.zeros(self.num_envs, np.int64)
        self._needs_reset = np.zeros(self.num_envs, bool)
        self._rngs = [np.random.default_rng() for _ in range(self.num_envs)]

    # -------------------------------------------------------------- Gymnasium API
    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
              ) -> tuple[Obs, dict[str, Any]]:
        """Start a new episode in every sub-environment (open ones are closed first); ``options``: ``target``."""
        if isinstance(seed, (int, np.integer)):
            self.action_space.seed(int(seed))
        target = (options or {}).get("target", self.target)
        entries = []
        for i, s in enumerate(sub_seeds(seed, self.num_envs)):
            self._rngs[i] = np.random.default_rng(s)
            entries.append((i, self._reset_one(i, s, target)))
        return self._batch_obs(), self._infos(entries)

    def step(self, actions: Any) -> tuple[Obs, NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_], dict[str, Any]]:
        """One step of every sub-environment; the accepted moves' views are rendered in one batch."""
        if any(i is None for i in self._ids):
            raise RuntimeError("call reset() before step()")
        twists = self._twists(actions)
        rgb = np.empty((self.num_envs, self.height, self.width, 3), np.uint8)
        depth = np.empty((self.num_envs, self.height, self.width), np.float32)
        rewards = np.zeros(self.num_envs, np.float64)
        entries: list[tuple[int, dict[str, Any]]] = []  # (sub-environment, its info), in _add_info's order
        moving = np.any(twists != 0.0, axis=1)
        linear, angular = twists[:, :3] * self.max_linear, twists[:, 3:] * self.max_angular
        requests: dict[int, MoveRequest] = {}
        for i in range(self.num_envs):
            if self._needs_reset[i]:  # NEXT_STEP autoreset: this step starts a new episode
                seed = int(self._rngs[i].integers(2**31))
                entries.append((i, self._reset_one(i, seed, self.target)))
            elif not moving[i]:  # a null twist: nothing moves, nothing is rendered
                self._steps[i] += 1
                entries.append((i, {"episode_id": self._ids[i], "accepted": True, "noop": True}))
            else:
                requests[i] = MoveRequest(str(self._ids[i]), linear[i], angular[i], self.step_duration, self.frame)
        slots = {i: (rgb[i], depth[i]) for i in requests}  # each move's view is rendered into the batch
        results = self.manager.move_many(list(requests.values()), list(slots.values()))
        for i, result in zip(requests, results):
            rewards[i] = self._record_move(i, result)
            entries.append((i, self._info(result)))
        truncated = ~self._needs_reset & (self._steps >= self.max_steps)
        self._end_truncated(truncated)
        return (self._batch_obs(rgb, depth, slots), rewards, np.zeros(self.num_envs, bool), truncated,
                self._infos(entries))

    def close_extras(self, **kwargs: Any) -> None:
        """Close the open episodes (their logs get their close records)."""
        for i in range(self.num_envs):
            self._close_one(i)

    # -------------------------------------------------------------- helpers
    def _twists(self, actions: Any) -> NDArray[np.float64]:
        """``actions`` as an (N, 6) array clipped to ``[-1, 1]``, or a BraveError naming the shape."""
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (self.num_envs, 6):
            raise BraveError(f"step: actions must have shape ({self.num_envs}, 6) (one twist per agent), got {a.shape}")
        return np.clip(a, -1.0, 1.0)

    def _reset_one(self, i: int, seed: int | None, target: int | str | None) -> dict[str, Any]:
        """Close sub-environment ``i``'s episode if open and start a new one (``BraveEnv.reset``)."""
        self._close_one(i)
        result = self.manager.reset(target=target, width=self.width, height=self.height, seed=seed, agent=self.agent)
        self._ids[i], self._views[i] = result.episode_id, result.observation
        self._steps[i], self._needs_reset[i] = 0, False
        return self._info(result)

    def _record_move(self, i: int, result: ActionResult) -> float:
        """Count the step, keep the new view and return its reward (``BraveEnv.step``'s rule)."""
        before = visible_px(self._views[i])
        self._views[i] = result.observation
        self._steps[i] += 1
        return visibility_reward(result.accepted, before, visible_px(result.observation), self.width, self.height)

    def _end_truncated(self, truncated: NDArray[np.bool_]) -> None:
        """Close the episodes that reached ``max_steps``; they reset on the next step."""
        for i in np.flatnonzero(truncated):
            self._close_one(int(i))
            self._needs_reset[i] = True

    def _close_one(self, i: int) -> None:
        """Close sub-environment ``i``'s episode if it is still open."""
        eid = self._ids[i]
        if eid is not None and not self._needs_reset[i] and not self.manager.get(eid).closed:
            self.manager.close(eid)

    def _infos(self, entries: list[tuple[int, dict[str, Any]]]) -> dict[str, Any]:
        """Gymnasium's vector info of the sub-environments' flat ``(index, info)`` entries, key by key
        instead of entry by entry: what :meth:`VectorEnv._add_info` gives for them in this order (keys
        in order of first appearance, each with its ``_key`` mask; the array's type from the first value)."""
        columns: dict[str, tuple[list[int], list[Any]]] = {}
        for i, info in entries:
            for key, value in info.items():
                rows, values = columns.setdefault(key, ([], []))
                rows.append(i)
                values.append(value)
        infos: dict[str, Any] = {}
        for key, (rows, values) in columns.items():
            first = values[0]
            if type(first) in (int, float, bool) or issubclass(type(first), np.number):
                array = np.zeros(self.num_envs, dtype=type(first))
                array[rows] = values
            else:  # ids (str) and None: an object array, as gymnasium makes for unknown types
                array = np.full(self.num_envs, fill_value=None, dtype=object)
                for i, value in zip(rows, values):
                    array[i] = value
            mask = np.zeros(self.num_envs, dtype=np.bool_)
            mask[rows] = True
            infos[key], infos[f"_{key}"] = array, mask
        return infos

    @staticmethod
    def _info(result: ActionResult) -> dict[str, Any]:
        return {"episode_id": result.episode_id, "accepted": result.accepted, "collided": result.collided,
                "adjustments": result.adjustments}

    def _batch_obs(self, rgb: NDArray[np.uint8] | None = None, depth: NDArray[np.float32] | None = None,
                   slots: dict[int, tuple[NDArray[np.uint8], NDArray[np.float32]]] | None = None) -> Obs:
        """The batch of the current views, read-only: ``rgb`` / ``depth`` (fresh arrays) hold the views
        rendered into ``slots``; every other view's images are copied in (all of them without ``rgb``)."""
        views = [v for v in self._views if v is not None]
        if rgb is None or depth is None:
            rgb, depth = np.stack([v.rgb for v in views]), np.stack([v.depth for v in views])
        else:
            slots = slots or {}
            for i, v in enumerate(views):
                slot = slots.get(i)
                if slot is None or v.rgb is not slot[0] or v.depth is not slot[1]:  # not rendered into the batch
                    rgb[i], depth[i] = v.rgb, v.depth
        rgb.flags.writeable = depth.flags.writeable = False
        return {"rgb": rgb, "depth": depth, "K": np.stack([v.camera.K for v in views]),
                "world_T_cam": np.stack([v.world_T_cam for v in views])}

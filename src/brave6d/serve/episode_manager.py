"""The episode manager: creates, runs and expires the episodes of a server (thread-safe).

The actions and their rules are described in :mod:`brave6d.serve.episodes` (the episode, its scene
server, the checks of every input); this module runs them on the scenes of a
:class:`brave6d.serve.catalog.SceneCatalog`, one lock per episode, and writes each episode's log.
It sits above both, so that the catalog (which loads :class:`SceneServer` s) and the episodes never
import each other.

The manager's ``mode`` (:mod:`brave6d.serve.modes`) decides what its results show: in ``scored``
mode every :class:`ActionResult`'s observation is the view without its ground truth (no objects),
whatever front end (HTTP, ROS, the vector env) passes it on; the log keeps the truth either way.
With a log folder, every log is signed with the server's key (:mod:`brave6d.serve.log_digest`).

``visibility_stride`` is the stride of every step's visible fractions (:mod:`brave6d.serve.visibility`:
1, the default, casts every pixel, as BOP's export does; ``s`` one pixel per ``s x s`` block, the
vector env's default), the same for single moves and batches; a submit records the final view's
exact truth whatever the stride (:meth:`SceneServer.complete`), so scores do not depend on it.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import atomic_write_bytes, depth_m_to_mm_u16, png_bytes
from brave6d.core.camera import PinholeCamera
from brave6d.serve.catalog import SceneCatalog
from brave6d.serve.episode_log import FINAL_DEPTH_SUFFIX, CloseRecord, EpisodeLog, ResetRecord, format_action
from brave6d.serve.episodes import (
    ActionResult,
    Episode,
    EpisodeBusy,
    EpisodeClosed,
    EpisodeNotFound,
    InvalidAction,
    Matrix4,
    RenderedView,
    SceneServer,
    Ticket,
    TooManyEpisodes,
    check_estimate,
    check_pose,
    check_twist,
    check_twists,
    free_pose,
    submission_record,
    target_ref,
)
from brave6d.serve.geometry import MoveResult, Refusal, integrate_twist
from brave6d.serve.log_digest import LogKey, server_log_key
from brave6d.serve.modes import SCORED, check_mode
from brave6d.serve.twist_batch import integrate_twists

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MoveRequest:
    """One episode's twist in :meth:`EpisodeManager.move_many` (the arguments of :meth:`EpisodeManager.move`)."""

    episode_id: str
    linear: Any
    angular: Any
    duration: float
    frame: str = "camera"


@dataclass(frozen=True)
class _MovePlan:
    """A checked and integrated twist, before its view: the pose to reach, the refusal (None: the
    move is accepted), the move's record, the request as logged and, for a move stopped part-way,
    what stopped it."""

    T: Matrix4
    refusal: Refusal | None
    move: dict[str, Any]
    requested: dict[str, Any]
    stopped_by: Refusal | None = None


def _target_truth(obs: RenderedView) -> dict[str, Any]:
    """The target's ground truth in ``obs`` for the log (nothing when the view has no target)."""
    t = obs.target()
    if t is None:
        return {}
    return {"target_cam_T_obj": t.cam_T_obj, "target_visib_fract": t.visib_fract}


def _commit(ticket: Ticket | None, apply: Any) -> None:
    """Run ``apply`` (the state change of an action) unless its request was withdrawn."""
    if ticket is not None:
        ticket.commit(apply)
    else:
        apply()


class EpisodeManager:
    """Creates, runs and expires episodes (thread-safe) on the scenes of a
    :class:`brave6d.serve.catalog.SceneCatalog` (or on one loaded :class:`SceneServer`). An open episode
    keeps its scene loaded; closing it lets the catalog evict the scene when room is needed.

    ``mode``: ``"scored"`` (default: no ground truth in the results) or ``"training"``. ``log_key``:
    the key the logs are signed with (default: the server's key file, made on first use,
    :func:`brave6d.serve.log_digest.server_log_key`; None: unsigned logs); unused without ``log_dir``."""

    def __init__(self, scenes: Any, log_dir: Path | str | None = None, max_episodes: int = 32,
                 idle_timeout_s: float = 900.0, keep_closed: int = 256, lock_timeout_s: float = 30.0,
                 mode: str = SCORED, log_key: LogKey | str | None = "default",
                 visibility_stride: int = 1) -> None:
        self.scenes: SceneCatalog = scenes if isinstance(scenes, SceneCatalog) else SceneCatalog.of_scene(scenes)
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.mode = check_mode(mode)
        if isinstance(visibility_stride, bool) or not isinstance(visibility_stride, (int, np.integer)) \
                or not 1 <= visibility_stride <= 64:
            raise ValueError(f"visibility_stride must be an integer in [1, 64], got {visibility_stride!r}")
        self.visibility_stride = int(visibility_stride)
        self.log_key: LogKey | None = None
        if self.log_dir is not None and log_key is not None:
            self.log_key = server_log_key() if log_key == "default" else (
                log_key if isinstance(log_key, LogKey) else server_log_key(log_key))
        self.max_episodes = max_episodes
        self.idle_timeout_s = idle_timeout_s
        self.keep_closed = keep_closed
        self.lock_timeout_s = lock_timeout_s
        self._episodes: OrderedDict[str, Episode] = OrderedDict()
        self._lock = threading.Lock()

    # -------------------------------------------------------------- bookkeeping
    def _expire(self) -> None:
        now = time.monotonic()
        with self._lock:
            stale = [e for e in self._episodes.values()
                     if not e.closed and now - e.last_active > self.idle_timeout_s]
        for e in stale:
            if e.lock.acquire(timeout=0):
                try:
                    self._close(e, "expired (idle)")
                finally:
                    e.lock.release()
        with self._lock:
            closed = [k for k, e in self._episodes.items() if e.closed]
            for k in closed[: max(0, len(closed) - self.keep_closed)]:
                del self._episodes[k]

    def open_count(self) -> int:
        with self._lock:
            return sum(1 for e in self._episodes.values() if not e.closed)

    def list(self) -> list[dict[str, Any]]:
        self._expire()
        with self._lock:
            return [{"episode_id": e.id, "scene": e.scene_name, "closed": e.closed, "steps": e.steps, "adjustments": e.adjustments,
                     "target": e.target.name} for e in self._episodes.values()]

    def shown(self, view: RenderedView) -> RenderedView:
        """``view`` as this server's mode lets an agent see it (scored: without the objects)."""
        return view if self.mode != SCORED else view.without_truth()

    def get(self, episode_id: str) -> Episode:
        with self._lock:
            ep = self._episodes.get(episode_id)
        if ep is None:
            raise EpisodeNotFound(f"unknown episode {episode_id!r} (never created, or closed and forgotten)",
                                  "episode_id")
        return ep

    @staticmethod
    def _scene(ep: Episode) -> SceneServer:
        assert ep.scene is not None  # only closed episodes have none, and _acquire refuses them
        return ep.scene

    def _acquire(self, ep: Episode) -> None:
        if not ep.lock.acquire(timeout=self.lock_timeout_s):
            raise EpisodeBusy(f"episode {ep.id} is busy with another request")
        if ep.closed:
            ep.lock.release()
            raise EpisodeClosed(f"episode {ep.id} is closed ({ep.close_reason}); reset a new one", "episode_id")

    # -------------------------------------------------------------- actions
    def reset(self, *, scene: str | int | None = None, target: int | str | None = None, width: int | None = None,
              height: int | None = None, start: Matrix4 | None = None, seed: int | None = None,
              agent: str | None = None, ticket: Ticket | None = None) -> ActionResult:
        """Start an episode on ``scene`` (a name or BOP scene_id; None: the only scene) at target
        ``target``; the scene is loaded first when needed (see :class:`brave6d.serve.catalog.SceneCatalog`)."""
        self._expire()
        source = self.scenes.source(scene)  # an unknown scene is refused before anything is loaded
        with self._lock:
            if sum(1 for e in self._episodes.values() if not e.closed) >= self.max_episodes:
                raise TooManyEpisodes(f"too many open episodes ({self.max_episodes}); close one first")
        server = self.scenes.acquire(scene)
        try:
            return self._reset(server, source.name, source.scene_id, target, width, height, start, seed, agent,
                               ticket)
        except BaseException:
            self.scenes.release(server)
            raise

    def _reset(self, server: SceneServer, scene_name: str, scene_id: int | None, target: int | str | None,
               width: int | None, height: int | None, start: Matrix4 | None, seed: int | None, agent: str | None,
               ticket: Ticket | None) -> ActionResult:
        bundle = server.bundle
        if not bundle.objects:
            raise InvalidAction("target: the bundle has no objects to target (annotate them for episodes: brave6d "
                                "annotate); look at the scene without an episode with POST /render", "target")
        if target is None:
            tgt = bundle.objects[0]
        else:
            try:
                tgt = bundle.object_by(target)
            except KeyError as exc:
                raise InvalidAction(str(exc.args[0]), "target") from None
        camera = server.camera_of(width, height)
        w, h = camera.width, camera.height
        if start is not None:
            T0 = free_pose(bundle.world, start, "start")
            used_seed = seed
        else:
            used_seed = seed if seed is not None else secrets.randbits(31)
            T0 = server.random_start(tgt, np.random.default_rng(used_seed))
        with self._lock:
            if sum(1 for e in self._episodes.values() if not e.closed) >= self.max_episodes:
                raise TooManyEpisodes(f"too many open episodes ({self.max_episodes}); close one first")
            eid = secrets.token_hex(8)
            ep = Episode(eid, server, scene_name, tgt, camera, T0, used_seed,
                         EpisodeLog(self.log_dir / f"{eid}.jsonl" if self.log_dir else None, self.log_key), agent,
                         mode=self.mode)
            self._episodes[eid] = ep  # reserve the slot
        ep.lock.acquire()
        try:
            t0 = time.perf_counter()
            try:
                obs = server.observe(T0, camera, tgt.gt_id, self.visibility_stride)
                timings = {**obs.timings_ms, "step": (time.perf_counter() - t0) * 1000.0}
                line = ep.log.format(ResetRecord(
                    episode_id=eid, bundle=bundle.name, agent=agent, target=target_ref(tgt), scene=scene_name,
                    scene_id=scene_id, width=w, height=h,
                    K=camera.K, seed=used_seed, start="given" if start is not None else "random", world_T_cam=T0,
                    timings_ms=timings, mode=self.mode, **_target_truth(obs)))
                shown = self.shown(obs)

                def apply() -> None:
                    ep.log.append(line)
                    ep.last, ep.shown = obs, shown
                    ep.render_ms.append(obs.timings_ms["render"])

                _commit(ticket, apply)
            except BaseException:  # the episode never existed
                with self._lock:
                    self._episodes.pop(eid, None)
                ep.log.close(sign=False)
                if ep.log.path is not None and ep.log.path.exists():
                    ep.log.path.unlink()
                raise
            return ActionResult(eid, "reset", 0, True, False, None, 0, shown, None, timings, target_ref(tgt),
                                self.mode)
        finally:
            ep.lock.release()

    def render(self, world_T_cam: Matrix4, *, scene: str | int | None = None, width: int | None = None,
               height: int | None = None, ticket: Ticket | None = None) -> RenderedView:
        """The splat of ``scene`` at ``world_T_cam``, without an episode (free viewing: any bundle,
        with or without objects). The pose must be free as a reset's start must be, the image within
        the same cap; the scene is loaded first when needed and pinned only while it renders."""
        server = self.scenes.acquire(scene)  # an unknown scene is refused before anything is loaded
        try:
            T = free_pose(server.bundle.world, world_T_cam, "pose")
            view = server.free_view(T, server.camera_of(width, height))
            _commit(ticket, lambda: None)  # a withdrawn request answers 504, not a late image
            return view
        finally:
            self.scenes.release(server)

    def set_pose(self, episode_id: str, world_T_cam: Matrix4, ticket: Ticket | None = None) -> ActionResult:
        ep = self.get(episode_id)
        self._acquire(ep)
        try:
            T = check_pose(world_T_cam, "pose")
            return self._finish(ep, "set_pose", T, self._scene(ep).bundle.world.check(T), None,
                                {"world_T_cam": T.tolist()}, ticket=ticket)
        finally:
            ep.lock.release()

    def move(self, episode_id: str, linear: Any, angular: Any, duration: float, frame: str = "camera",
             ticket: Ticket | None = None) -> ActionResult:
        ep = self.get(episode_id)
        self._acquire(ep)
        try:
            return self._finish_move(ep, self._plan_move(ep, linear, angular, duration, frame), ticket)
        finally:
            ep.lock.release()

    def move_many(self, requests: Sequence[MoveRequest],
                  out: Sequence[tuple[NDArray[np.uint8], NDArray[np.float32]] | None] | None = None
                  ) -> list[ActionResult]:
        """Run one ``move`` in each of several episodes with their renders batched: the views of the
        accepted moves that share a scene and a camera are drawn in one
        :meth:`SceneServer.observe_batch` call (many agents stepping together). Each result, log
        line and counter is what :meth:`move` gives for that request; a bad request (unknown,
        closed or repeated episode, invalid twist) refuses the whole batch before anything changes.
        ``out[k]``: arrays request ``k``'s view is rendered into when its move is accepted
        (:meth:`SplatRenderer.render_batch`'s ``out``; the vector env's observation batch)."""
        ids = [r.episode_id for r in requests]
        if len(set(ids)) != len(ids):
            raise InvalidAction("move_many: each episode may appear once per batch", "episode_id")
        eps = [self.get(i) for i in ids]
        held: list[Episode] = []
        try:
            for ep in eps:
                self._acquire(ep)
                held.append(ep)
            plans = self._plan_moves(eps, requests)
            views = self._observe_accepted(eps, plans, out)
            return [self._finish_move(ep, plan, None, views.get(k)) for k, (ep, plan) in enumerate(zip(eps, plans))]
        finally:
            for ep in held:
                ep.lock.release()

    def _observe_accepted(self, eps: list[Episode], plans: list[_MovePlan],
                          out: Sequence[tuple[NDArray[np.uint8], NDArray[np.float32]] | None] | None = None
                          ) -> dict[int, RenderedView]:
        """The views of the accepted plans (by index), one batched render per (scene, camera) group."""
        groups: dict[tuple[int, PinholeCamera], list[int]] = {}
        for k, (ep, plan) in enumerate(zip(eps, plans)):
            if plan.refusal is None:  # no refusal: the move is accepted and needs a view
                groups.setdefault((id(self._scene(ep)), ep.camera), []).append(k)
        views: dict[int, RenderedView] = {}
        for members in groups.values():
            scene, camera = self._scene(eps[members[0]]), eps[members[0]].camera
            rendered = scene.observe_batch([plans[k].T for k in members], camera,
                                           [eps[k].target.gt_id for k in members],
                                           targets_only=self.mode == SCORED,  # scored: nothing shows the rest
                                           stride=self.visibility_stride,
                                           out=None if out is None else [out[k] for k in members])
            views.update(zip(members, rendered))
        return views

    def _plan_moves(self, eps: list[Episode], requests: Sequence[MoveRequest]) -> list[_MovePlan]:
        """:meth:`_plan_move` of each request, the twists of episodes on one scene integrated together
        (:func:`brave6d.serve.twist_batch.integrate_twists`, equal to one by one bit for bit)."""
        checked = check_twists([(r.linear, r.angular, r.duration) for r in requests])
        groups: dict[int, list[int]] = {}
        for k, ep in enumerate(eps):
            groups.setdefault(id(self._scene(ep)), []).append(k)
        results: dict[int, MoveResult] = {}
        for members in groups.values():
            try:
                moved = integrate_twists(self._scene(eps[members[0]]).bundle.world,
                                         np.stack([eps[k].world_T_cam for k in members]),
                                         np.stack([checked[k][0] for k in members]),
                                         np.stack([checked[k][1] for k in members]),
                                         np.array([checked[k][2] for k in members]),
                                         [requests[k].frame for k in members])
            except ValueError as exc:
                raise InvalidAction(str(exc), "frame" if "frame" in str(exc) else "duration") from None
            results.update(zip(members, moved))
        return [self._move_plan(eps[k], results[k], *checked[k], requests[k].frame) for k in range(len(eps))]

    @staticmethod
    def _move_plan(ep: Episode, res: MoveResult, v: Any, w: Any, d: float, frame: str) -> _MovePlan:
        """The plan of an integrated move (refused when blocked at its first substep)."""
        move = {"fraction": res.fraction, "substeps": res.substeps, "path_m": res.path_m}
        requested = {"linear": v.tolist(), "angular": w.tolist(), "duration": d, "frame": frame}
        if not res.moved:  # blocked at the first substep: refused
            return _MovePlan(ep.world_T_cam, res.refusal, move, requested)
        return _MovePlan(res.world_T_cam, None, move, requested, res.refusal)

    def _plan_move(self, ep: Episode, linear: Any, angular: Any, duration: float, frame: str) -> _MovePlan:
        """Check a twist and integrate it from ``ep``'s pose -> the arguments of :meth:`_finish`."""
        v, w, d = check_twist(linear, angular, duration)
        try:
            res: MoveResult = integrate_twist(self._scene(ep).bundle.world, ep.world_T_cam, v, w, d, frame)
        except ValueError as exc:
            raise InvalidAction(str(exc), "frame" if "frame" in str(exc) else "duration") from None
        return self._move_plan(ep, res, v, w, d, frame)

    def _finish_move(self, ep: Episode, plan: _MovePlan, ticket: Ticket | None,
                     obs: RenderedView | None = None) -> ActionResult:
        """:meth:`_finish` of a planned move (``obs``: its view when rendered in a batch)."""
        return self._finish(ep, "move", plan.T, plan.refusal, plan.move, plan.requested, plan.stopped_by,
                            ticket=ticket, obs=obs)

    def _finish(self, ep: Episode, action: str, T: Matrix4, refusal: Refusal | None, move: dict[str, Any] | None,
                requested: dict[str, Any], stopped_by: Refusal | None = None, *, ticket: Ticket | None = None,
                obs: RenderedView | None = None) -> ActionResult:
        """Complete a ``set_pose``/``move`` to ``T`` (or refuse it) as one transaction: the
        observation, the counters and the log line are all computed first, then the log line is
        written and the state changed together; a failure before that changes nothing."""
        t0 = time.perf_counter()
        before = ep.world_T_cam
        accepted = refusal is None
        if accepted:
            if obs is None:  # not rendered beforehand in a batch (move_many)
                obs = self._scene(ep).observe(T, ep.camera, ep.target.gt_id, self.visibility_stride)
            after, timings, shown = T, {**obs.timings_ms}, self.shown(obs)
        else:
            assert ep.last is not None and ep.shown is not None
            obs, after, shown = ep.last, before, ep.shown
            timings = {"render": 0.0, "render_queue": 0.0, "visibility": 0.0, "observe": 0.0}
        steps, adjustments = ep.steps + 1, ep.adjustments + int(accepted)
        collided = refusal is not None or stopped_by is not None
        reason = refusal or stopped_by
        timings["step"] = (time.perf_counter() - t0) * 1000.0
        line = ""  # a log without a file (no log folder: the vector env's own manager) writes nothing: no line made
        if ep.log.writes:
            line = format_action(  # ActionRecord's line, without building the model (the same bytes)
                event=action, step=steps, accepted=accepted, collided=collided,
                refusal=reason.to_json() if reason else None, requested=requested, world_T_cam_before=before,
                world_T_cam=after, adjustments=adjustments, move=move, timings_ms=timings, **_target_truth(obs))

        def apply() -> None:
            ep.log.append(line)  # first: a failed write leaves the state as it was
            ep.steps, ep.adjustments, ep.world_T_cam = steps, adjustments, after
            if accepted:
                ep.last, ep.shown = obs, shown
                ep.render_ms.append(obs.timings_ms["render"])
                ep.collisions += int(stopped_by is not None)
            else:
                ep.refusals += 1
            ep.last_active = time.monotonic()

        _commit(ticket, apply)
        return ActionResult(ep.id, action, steps, accepted, collided, reason, adjustments, shown, move, timings,
                            target_ref(ep.target), self.mode)

    def submit(self, episode_id: str, estimates: list[dict[str, Any]], agent: str | None = None,
               ticket: Ticket | None = None) -> dict[str, Any]:
        """Log the final estimates (``{obj_id, R, t_m, score}``, camera frame of the current view)
        with the final view's ground truth and depth image, then close the episode."""
        ep = self.get(episode_id)
        self._acquire(ep)
        try:
            if ep.last is None:
                raise InvalidAction("the episode has no observation to refer the estimates to", "episode_id")
            scene = self._scene(ep)
            ep.last = scene.complete(ep.last)  # every object's truth, for the submit record
            known = {o.obj_id for o in scene.bundle.objects}
            clean = [check_estimate(i, e.get("obj_id", -1), e.get("R", ()), e.get("t_m", ()), e.get("score", 1.0),
                                    known) for i, e in enumerate(estimates)]
            depth_file = f"{ep.id}{FINAL_DEPTH_SUFFIX}" if ep.log.path is not None else None
            depth = b""
            if depth_file is not None:  # the reference's depth when the bundle has one
                depth = png_bytes(depth_m_to_mm_u16(ep.last.test_depth), depth_file)
            name = agent if agent is not None else ep.agent
            line = ep.log.format(submission_record(ep, clean, scene.bundle, depth_file, name,
                                                   hashlib.sha256(depth).hexdigest()))
            out: dict[str, Any] = {}

            def apply() -> None:
                if ep.log.path is not None and depth_file is not None:
                    atomic_write_bytes(ep.log.path.with_name(depth_file), depth)
                ep.log.append(line)
                ep.agent = name
                ep.submitted = True
                out.update(self._close(ep, "submitted"))
                out.update({"submitted": True, "estimates": len(clean), "depth_file": depth_file, "agent": ep.agent})

            _commit(ticket, apply)
            return out
        finally:
            ep.lock.release()

    def close(self, episode_id: str, reason: str = "closed by the client") -> dict[str, Any]:
        ep = self.get(episode_id)
        self._acquire(ep)
        try:
            return self._close(ep, reason)
        finally:
            ep.lock.release()

    def _close(self, ep: Episode, reason: str) -> dict[str, Any]:
        summary = ep.summary()
        ep.closed = True
        ep.close_reason = reason
        ep.log.write(CloseRecord(reason=reason, **summary))
        ep.log.close()
        ep.last = ep.shown = None  # free the images (closed episodes are kept for GET /episodes/{id})
        if ep.scene is not None:
            self.scenes.release(ep.scene)
            ep.scene = None
        return {"episode_id": ep.id, "closed": True, "reason": reason, "mode": ep.mode, **summary}

    def close_all(self, reason: str = "server shutdown") -> None:
        with self._lock:
            eps = [e for e in self._episodes.values() if not e.closed]
        for e in eps:
            if e.lock.acquire(timeout=5.0):
                try:
                    if not e.closed:
                        self._close(e, reason)
                finally:
                    e.lock.release()

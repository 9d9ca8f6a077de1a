"""Episodes: the state machine behind the API, independent of HTTP.

An episode has a target instance, an image size (a scaled copy of the bundle's pinhole
camera), the current camera pose ``world_T_cam`` and counters. Actions:

* ``reset`` (creating the episode): start pose given (any free pose) or drawn from a seeded
  random generator on a spherical cap around the target (capture-like distances and
  elevations, looking at the target's model centre); returns the first observation.
* ``set_pose``: teleport to an absolute pose (only the destination is checked, as habitat's
  ``get_observations_at``).
* ``move``: a constant twist for a duration, integrated and stopped at the last free substep
  (:mod:`brave6d.serve.geometry`). A move that is blocked at its first substep goes nowhere.
* ``submit``: hand in the final pose estimates (camera frame of the current view) and end the
  episode. The log then holds everything scoring needs that only the server knows: the final
  view's pose, ``K``, image size, every object's ground-truth ``cam_T_obj`` and visible
  fraction, and the final view's test depth (``<episode_id>_final_depth.png``, uint16 mm, beside
  the log): the bundle's reference geometry ray cast at that pose, not the splat the agent saw
  (a bundle without a reference: the splat's depth; ``final_view.depth_source`` says which).
  See :func:`submission_record`. Observations leave the server as :mod:`brave6d.serve.schema` models.

**Refusal** (AI2-THOR semantics): an action whose destination (``set_pose``) or first substep
(``move``) is in collision or outside the workspace is refused with the reason; the camera
stays where it was, the adjustment counter does not change, and the observation returned is
the previous one (not re-rendered). A move stopped part-way is *accepted* (``collided: true``
plus the reason) and the camera stays at the last free pose, as habitat does.

**Position adjustments**: every accepted ``set_pose`` or ``move`` counts one; the start pose
of ``reset`` does not.

Each episode is appended, one JSON record per action, to ``<log_dir>/<episode_id>.jsonl`` in the
versioned schema of :mod:`brave6d.serve.episode_log` (reset, every action with the poses before/after,
refusal, adjustments, timings, the target's pose in the camera frame and visible fraction; submit
with the estimates and the final view's ground truth; close with the totals). Every action holds the
episode's lock, so concurrent requests on one episode run one after the other; different
episodes run concurrently (renders share one device lock in the renderer).

This module holds the episode, its scene server and the checks of every input;
:class:`brave6d.serve.episode_manager.EpisodeManager` runs the actions on the scenes of a catalog.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache, partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, NonRigidTransformError
from brave6d.core.transforms import look_at, nearest_rotation
from brave6d.serve.bundle import Bundle, BundleObject, load_model_m
from brave6d.serve.episode_log import EpisodeLog, FinalView, LoggedEstimate, SubmitRecord
from brave6d.serve.geometry import CollisionWorld, Refusal
from brave6d.serve.limits import MAX_ANGULAR_SPEED_RAD_S, MAX_COORD_M, MAX_LINEAR_SPEED_M_S, MAX_MOVE_DURATION_S
from brave6d.serve.modes import SCORED
from brave6d.serve.reference import SPLAT_GEOMETRY, ReferenceGeometry, bundle_reference
from brave6d.serve.renderer import RenderOutput, SplatRenderer
from brave6d.serve.schema import ObjectState, TargetRef
from brave6d.serve.visibility import Visibility, VisibilityComputer, effective_stride

log = logging.getLogger(__name__)

Matrix4 = NDArray[np.float64]


# ----------------------------------------------------------------------------- errors
class EpisodeError(BraveError):
    """Base of the errors an API client can cause; ``status`` is the HTTP status to answer with."""

    status = 400
    field: str | None = None

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        if field is not None:
            self.field = field


class EpisodeNotFound(EpisodeError):
    status = 404


class EpisodeClosed(EpisodeError):
    status = 409


class EpisodeBusy(EpisodeError):
    status = 409


class TooManyEpisodes(EpisodeError):
    status = 429


class InvalidAction(EpisodeError):
    status = 422


class Cancelled(Exception):
    """The request timed out before its result was committed; nothing changed."""


class Ticket:
    """Lets a timed-out request withdraw an action before it is committed (all or nothing)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.cancelled = False
        self.committed = False

    def commit(self, apply: Any) -> None:
        with self._lock:
            if self.cancelled:
                raise Cancelled()
            apply()
            self.committed = True

    def cancel(self) -> bool:
        """True when the action is withdrawn (it will not be applied); False when it already was."""
        with self._lock:
            if self.committed:
                return False
            self.cancelled = True
            return True


# ----------------------------------------------------------------------------- views
def object_state(obj: BundleObject, cam_T_obj: Matrix4, visibility: Visibility | None, is_target: bool,
                 finite: bool | None = None) -> ObjectState:
    """The wire/log record of one object in one view (visibility fields None when not computed).

    When every value already is what the model's validation makes of it (exact ``int``/``str``/``bool``
    ids and flag, a float64 4x4 array, finite, ``finite``: already checked by the caller; counts that are
    ``int``, a finite ``float`` fraction, boxes of four ``int``), the model is built without running the
    validation (the same fields, fields set and dump: tested); anything else is validated. Why: a
    training step records every object of every agent's view."""
    if (type(obj.gt_id) is int and type(obj.obj_id) is int and type(obj.name) is str and type(is_target) is bool
            and type(cam_T_obj) is np.ndarray and cam_T_obj.dtype is _FLOAT64 and cam_T_obj.shape == (4, 4)
            and (finite if finite is not None else bool(np.isfinite(cam_T_obj).all()))):
        v = visibility
        if v is None:
            return _unvalidated_object_state({"gt_id": obj.gt_id, "obj_id": obj.obj_id, "name": obj.name,
                                              "is_target": is_target, "cam_T_obj": cam_T_obj, **_NO_VISIBILITY},
                                             _BASE_FIELDS)
        fract, box, box_visib = v.visib_fract, v.bbox_obj, v.bbox_visib
        if (type(v.px_count_all) is int and type(v.px_count_visib) is int and type(fract) is float
                and math.isfinite(fract) and _int_box(box) and _int_box(box_visib)):
            return _unvalidated_object_state(
                {"gt_id": obj.gt_id, "obj_id": obj.obj_id, "name": obj.name, "is_target": is_target,
                 "cam_T_obj": cam_T_obj, "px_count_all": v.px_count_all, "px_count_visib": v.px_count_visib,
                 "visib_fract": fract, "bbox_obj": list(box) if box else None,
                 "bbox_visib": list(box_visib) if box_visib else None}, _ALL_FIELDS)
    vis = visibility.to_json() if visibility is not None else {}
    return ObjectState(gt_id=obj.gt_id, obj_id=obj.obj_id, name=obj.name, is_target=is_target,
                       cam_T_obj=cam_T_obj, **vis)


_UNSET = object()
_FLOAT64 = np.dtype(np.float64)  # NumPy's one native float64 dtype (another byte order: validated)
_NO_VISIBILITY = {"px_count_all": None, "px_count_visib": None, "visib_fract": None, "bbox_obj": None,
                  "bbox_visib": None}
_BASE_FIELDS = frozenset(("gt_id", "obj_id", "name", "is_target", "cam_T_obj"))
_ALL_FIELDS = frozenset(ObjectState.model_fields)
_set_attribute = object.__setattr__


def _int_box(box: Any) -> bool:
    """True for None or an empty box (both recorded as None) or a tuple of four ``int``."""
    return not box or (type(box) is tuple and len(box) == 4 and type(box[0]) is int and type(box[1]) is int
                       and type(box[2]) is int and type(box[3]) is int)


def _unvalidated_object_state(values: dict[str, Any], fields_set: frozenset[str]) -> ObjectState:
    """``ObjectState.model_construct(**values)`` without its per-field default and alias lookups:
    ``values`` holds every field, in the model's order, already valid (:func:`object_state` checks)."""
    state = ObjectState.__new__(ObjectState)
    _set_attribute(state, "__dict__", values)
    _set_attribute(state, "__pydantic_fields_set__", set(fields_set))
    _set_attribute(state, "__pydantic_extra__", None)
    _set_attribute(state, "__pydantic_private__", None)
    return state


@dataclass(frozen=True)
class RenderedView:
    """What the server rendered for one pose: the raw images (RGB uint8, depth float32 metres),
    the camera, and every object's ground truth (:class:`brave6d.serve.schema.ObjectState`).

    ``test_depth``: the depth the view is scored on (VSD's test depth; the occluders of the
    visible fractions), from the scene's ``geometry``: ``"reference"`` (the bundle's reference
    geometry) or ``"splat"`` (a bundle without one: the rendered depth itself)."""

    rgb: NDArray[np.uint8]
    depth: NDArray[np.float32]
    camera: PinholeCamera
    world_T_cam: Matrix4
    objects: tuple[ObjectState, ...]
    timings_ms: dict[str, float]
    reference: ReferenceGeometry | None = None  # the scene's, when its bundle has one
    geometry: str = SPLAT_GEOMETRY
    #: False: ``objects`` holds only the target's truth (a scored batch computes no more per step);
    #: :meth:`SceneServer.complete` adds every object's, as :meth:`SceneServer.observe` gives them
    complete: bool = True
    #: the visible fractions' stride (:mod:`brave6d.serve.visibility`; 1: every pixel, exact)
    visibility_stride: int = 1

    @cached_property
    def test_depth(self) -> NDArray[np.float32]:
        """The depth scores are measured against (see the class docstring): the reference ray cast
        at this view (once, when first asked: at submit), else the rendered depth."""
        return self.depth if self.reference is None else self.reference.depth(self.world_T_cam, self.camera)

    def target(self) -> ObjectState | None:
        """The target's record (found once: each step asks for it three times, for its log line and reward)."""
        found = self.__dict__.get("_target", _UNSET)
        if found is _UNSET:
            found = self.__dict__["_target"] = next((o for o in self.objects if o.is_target), None)
        return found

    def without_truth(self) -> RenderedView:
        """This view as a scored server shows it: the images, camera and pose, no objects (``replace``'s
        result, built directly: every scored step makes one)."""
        return RenderedView(self.rgb, self.depth, self.camera, self.world_T_cam, (), self.timings_ms, self.reference,
                            self.geometry, self.complete, self.visibility_stride)


@dataclass
class ActionResult:
    """The outcome of ``reset``/``set_pose``/``move`` (the app encodes it as a :class:`brave6d.serve.schema.StepMessage`)."""

    episode_id: str
    action: str
    step: int
    accepted: bool
    collided: bool
    refusal: Refusal | None
    adjustments: int
    observation: RenderedView
    move: dict[str, Any] | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    target: TargetRef | None = None  # the episode's target (ids and name), in either mode
    mode: str = SCORED


class SceneServer:
    """Bundle + renderer + visibility: renders observations for any pose and image size.

    The agent sees the splat; the score depth and the visible fractions come from the bundle's
    reference geometry, loaded once here (an older bundle without one: the splat's depth, with
    one warning, and ``geometry`` says so in every score)."""

    def __init__(self, bundle: Bundle, device: str = "auto", renderer: SplatRenderer | None = None,
                 occlusion_tolerance: float = 0.015, visibility: bool = True) -> None:
        self.bundle = bundle
        self.renderer = renderer if renderer is not None else SplatRenderer(
            bundle.splat_path, device, antialiasing=bundle.render.antialiasing)
        models = [load_model_m(bundle.model_path(o)) for o in bundle.objects]
        self.centres_world = []
        for o, (verts, _) in zip(bundle.objects, models):
            c = 0.5 * (verts.min(axis=0) + verts.max(axis=0)) if len(verts) else np.zeros(3)
            self.centres_world.append(o.world_T_obj[:3, :3] @ c + o.world_T_obj[:3, 3])
        self.reference: ReferenceGeometry | None = bundle_reference(bundle)
        self.geometry = "reference" if self.reference is not None else SPLAT_GEOMETRY
        self.visibility: VisibilityComputer | None = None
        if visibility and bundle.objects:
            try:
                self.visibility = VisibilityComputer(models, [o.world_T_obj for o in bundle.objects],
                                                     occlusion_tolerance)
            except ImportError as exc:  # Open3D missing: poses still served, visibility null
                log.warning("visible fractions disabled: %s", exc)

    @property
    def device(self) -> str:
        return self.renderer.device

    def camera_for(self, width: int, height: int) -> PinholeCamera:
        cam = self.bundle.camera
        if (width, height) == (cam.width, cam.height):
            return cam
        return cam.scaled(width, height)

    def camera_of(self, width: int | None, height: int | None) -> PinholeCamera:
        """The camera of a request's ``width`` x ``height`` (None: the bundle's render default)."""
        return self.camera_for(width or self.bundle.render.width, height or self.bundle.render.height)

    def free_view(self, world_T_cam: Matrix4, camera: PinholeCamera) -> RenderedView:
        """The splat alone at ``world_T_cam``: no objects and no visibility (free viewing, ``POST
        /render``: a scene without objects can be looked at, and no ground truth leaves the server)."""
        t0 = time.perf_counter()
        out = self.renderer.render(world_T_cam, camera, **self._render_settings())
        timings = {"render": out.render_ms, "render_queue": out.queue_ms,
                   "observe": (time.perf_counter() - t0) * 1000.0}
        return RenderedView(out.rgb, out.depth, camera, np.array(world_T_cam, dtype=np.float64), (), timings)

    def observe(self, world_T_cam: Matrix4, camera: PinholeCamera, target_gt_id: int | None,
                stride: int = 1) -> RenderedView:
        """The view at ``world_T_cam``: the rendered images and every object's ground truth (visible
        fractions at ``stride``, :mod:`brave6d.serve.visibility`; 1: exact)."""
        t0 = time.perf_counter()
        out = self.renderer.render(world_T_cam, camera, **self._render_settings())
        return self._view(out, world_T_cam, camera, target_gt_id, time.perf_counter() - t0, stride=stride)

    def observe_batch(self, poses: Sequence[Matrix4], camera: PinholeCamera,
                      target_gt_ids: Sequence[int | None], targets_only: bool = False,
                      stride: int = 1, out: Sequence[tuple[NDArray[np.uint8], NDArray[np.float32]] | None] | None = None
                      ) -> list[RenderedView]:
        """The views at ``poses`` (one camera), rendered in one batched call
        (:meth:`SplatRenderer.render_batch`: many agents on one scene), each what :meth:`observe` gives.
        ``targets_only``: each view holds only its target's truth (``complete`` False; a scored step
        logs no more, and :meth:`complete` adds the rest when a submit needs it): the other objects'
        silhouettes are not cast. ``stride``: :meth:`observe`'s. ``out``: the arrays each view's images
        are rendered into (:meth:`SplatRenderer.render_batch`'s)."""
        if len(poses) != len(target_gt_ids):
            raise ValueError(f"observe_batch: {len(poses)} poses but {len(target_gt_ids)} targets")
        t0 = time.perf_counter()
        settings = self._render_settings() if out is None else {**self._render_settings(), "out": out}
        outs = self.renderer.render_batch(poses, camera, **settings)
        render_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        index = {o.gt_id: n for n, o in enumerate(self.bundle.objects)}
        wanted = sorted({index[g] for g in target_gt_ids if g in index}) if targets_only else None
        vis = self._visibilities(poses, camera, outs, wanted, stride)
        vis_s = (time.perf_counter() - t1) / max(len(poses), 1)  # each view's share of the batch
        if wanted is not None:  # only the target's truth: its visibility among the instances computed
            vis = [self._target_only(v, wanted, gt_id) for v, gt_id in zip(vis, target_gt_ids)]
        objects = self._objects_many(poses, vis, target_gt_ids, wanted is None)
        return [self._view(out, T, camera, gt_id, render_s, (v, vis_s), wanted, stride, objs)
                for out, T, gt_id, v, objs in zip(outs, poses, target_gt_ids, vis, objects)]

    def complete(self, view: RenderedView) -> RenderedView:
        """``view`` with every object's exact truth (:meth:`observe`'s at stride 1, bit for bit: the
        one-view visibility equals the batch's): a submit records this, whatever stride the steps
        used; a complete view at stride 1 as it is."""
        if view.complete and effective_stride(view.camera, view.visibility_stride) == 1:
            return view
        vis: list[Visibility | None] = [None] * len(self.bundle.objects)
        if self.visibility is not None:
            occluders = partial(self.reference.depth_along, view.world_T_cam) if self.reference is not None else None
            vis = list(self.visibility.compute(view.world_T_cam, view.camera, view.depth, occluders))
        target = view.target()
        return replace(view, objects=self._objects(view.world_T_cam, vis, None if target is None else target.gt_id),
                       complete=True, visibility_stride=1)

    def _visibilities(self, poses: Sequence[Matrix4], camera: PinholeCamera, outs: Sequence[RenderOutput],
                      wanted: list[int] | None = None, stride: int = 1) -> list[list[Visibility | None]]:
        """Every object's (or the ``wanted`` instances') visibility in each view, all views at once
        (:meth:`VisibilityComputer.compute_many`, equal to :meth:`_view`'s one view at a time)."""
        count = len(self.bundle.objects) if wanted is None else len(wanted)
        if self.visibility is None or not len(poses):
            return [[None] * count for _ in poses]
        if self.reference is not None:
            many = self.visibility.compute_many(np.asarray(poses), camera, occluder_depths=self.reference.depth_along_many,
                                                instances=wanted, stride=stride)
        else:
            many = self.visibility.compute_many(np.asarray(poses), camera, splat_depths=[out.depth for out in outs],
                                                instances=wanted, stride=stride)
        return [list(v) for v in many]

    def _render_settings(self) -> dict[str, Any]:
        """The bundle's render settings as the renderer's keyword arguments."""
        r = self.bundle.render
        return {"near": r.near, "far": r.far, "background": r.background, "depth_alpha_min": r.depth_alpha_min,
                "depth_mode": r.depth_mode}

    def _view(self, out: RenderOutput, world_T_cam: Matrix4, camera: PinholeCamera, target_gt_id: int | None,
              render_s: float, computed: tuple[list[Visibility | None], float] | None = None,
              instances: list[int] | None = None, stride: int = 1,
              objects: tuple[ObjectState, ...] | None = None) -> RenderedView:
        """One rendered view plus its visible fractions and objects' poses (``render_s``: the render's
        wall time; ``computed``: the visible fractions, one per object, and their seconds, when computed
        for a batch of the ``instances`` given: then the view holds its target's truth only, ``complete``
        False; ``objects``: the view's records when made for the batch, :meth:`_objects_many`)."""
        t1 = time.perf_counter()
        vis: list[Visibility | None] = [None] * len(self.bundle.objects)
        if computed is not None:
            vis, t1 = computed[0], t1 - computed[1]
        elif self.visibility is not None:
            occluders = partial(self.reference.depth_along, world_T_cam) if self.reference is not None else None
            vis = list(self.visibility.compute(world_T_cam, camera, out.depth, occluders, stride))
        complete = instances is None
        t2 = time.perf_counter()
        if objects is None:
            objects = self._objects(world_T_cam, vis, target_gt_id, complete)
        timings = {"render": out.render_ms, "render_queue": out.queue_ms, "visibility": (t2 - t1) * 1000.0,
                   "observe": render_s * 1000.0 + (t2 - t1) * 1000.0}
        return RenderedView(out.rgb, out.depth, camera, np.array(world_T_cam, dtype=np.float64), objects, timings,
                            self.reference, self.geometry, complete, stride)

    def _target_only(self, vis: list[Visibility | None], instances: list[int], target_gt_id: int | None
                     ) -> list[Visibility | None]:
        """One visibility per object from those of ``instances``: the target's, None for the others."""
        by_index = dict(zip(instances, vis))
        return [by_index.get(n) if o.gt_id == target_gt_id else None for n, o in enumerate(self.bundle.objects)]

    def _objects(self, world_T_cam: Matrix4, vis: list[Visibility | None], target_gt_id: int | None,
                 every: bool = True) -> tuple[ObjectState, ...]:
        """The objects' truth records at ``world_T_cam`` (``every`` False: the target's alone)."""
        return self._objects_many([world_T_cam], [vis], [target_gt_id], every)[0]

    def _objects_many(self, poses: Sequence[Matrix4], vis: Sequence[list[Visibility | None]],
                      target_gt_ids: Sequence[int | None], every: bool = True) -> list[tuple[ObjectState, ...]]:
        """:meth:`_objects` of many views: the views' ``cam_T_world`` (:func:`invert_stack`) and each object's
        ``cam_T_obj`` in one matrix product of the stack each (each 4x4 product computed as one view's, bit
        for bit: tested), their finiteness checked once."""
        objects = self.bundle.objects
        if not len(poses):
            return []
        cam_T_world = invert_stack(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4))
        cam_T_objs = [cam_T_world @ o.world_T_obj for o in objects]
        finite = (np.isfinite(np.stack(cam_T_objs)).all(axis=(2, 3)).tolist() if objects
                  else [[] for _ in poses])
        out = []
        for c, (views_vis, target) in enumerate(zip(vis, target_gt_ids)):
            out.append(tuple(object_state(o, cam_T_objs[n][c], v, o.gt_id == target, finite[n][c])
                             for n, (o, v) in enumerate(zip(objects, views_vis)) if every or o.gt_id == target))
        return out

    def random_start(self, target: BundleObject, rng: np.random.Generator, tries: int = 500) -> Matrix4:
        """A free pose on a spherical cap around the target, looking at its model centre."""
        s = self.bundle.start
        dists = s.get("distances_m") or [0.2, 0.5]
        d_lo, d_hi = float(min(dists)), float(max(dists))
        el_lo = math.radians(float(s.get("min_elevation_deg", 30.0)))
        el_hi = math.radians(float(s.get("max_elevation_deg", 80.0)))
        az_lo, az_hi = (math.radians(float(a)) for a in s.get("azimuth_range_deg", (-180.0, 180.0)))
        centre = self.centres_world[target.gt_id] if target.gt_id < len(self.centres_world) else target.world_T_obj[:3, 3]
        for _ in range(tries):
            d = rng.uniform(d_lo, d_hi)
            el = rng.uniform(el_lo, el_hi)
            az = rng.uniform(az_lo, az_hi)
            eye = centre + d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            T = look_at(eye, centre)
            if self.bundle.world.check(T) is None:
                return T
        raise InvalidAction(f"no free start pose found around object {target.name!r} in {tries} tries "
                            "(check the collision boxes and the workspace)", "start")


# ----------------------------------------------------------------------------- episodes
@dataclass
class Episode:
    id: str
    scene: SceneServer | None  # None once closed (a closed episode does not keep its scene loaded)
    scene_name: str
    target: BundleObject
    camera: PinholeCamera
    world_T_cam: Matrix4
    seed: int | None
    log: EpisodeLog
    agent: str | None = None
    created: float = field(default_factory=time.monotonic)
    last_active: float = field(default_factory=time.monotonic)
    adjustments: int = 0
    steps: int = 0
    refusals: int = 0
    collisions: int = 0
    closed: bool = False
    close_reason: str | None = None
    submitted: bool = False
    last: RenderedView | None = None  # the last view with its ground truth (the log's and the submit's)
    shown: RenderedView | None = None  # the last view as the agent got it (no ground truth when scored)
    mode: str = SCORED
    render_ms: list[float] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def state(self) -> dict[str, Any]:
        return {"episode_id": self.id, "scene": self.scene_name, "closed": self.closed,
                "close_reason": self.close_reason, "target": {"gt_id": self.target.gt_id, "obj_id": self.target.obj_id, "name": self.target.name},
                "width": self.camera.width, "height": self.camera.height, "K": self.camera.K.tolist(),
                "world_T_cam": self.world_T_cam.tolist(), "adjustments": self.adjustments,
                "steps": self.steps, "refusals": self.refusals, "collisions": self.collisions,
                "seed": self.seed, "agent": self.agent, "submitted": self.submitted, "mode": self.mode,
                "age_s": time.monotonic() - self.created,
                "log": str(self.log.path) if self.log.path else None}

    def summary(self) -> dict[str, Any]:
        ms = np.asarray(self.render_ms) if self.render_ms else np.zeros(0)
        return {"steps": self.steps, "adjustments": self.adjustments, "refusals": self.refusals,
                "collisions": self.collisions, "duration_s": time.monotonic() - self.created,
                "render_ms_median": float(np.median(ms)) if len(ms) else None,
                "world_T_cam": self.world_T_cam.tolist()}


def check_estimate(index: int, obj_id: int, R: Any, t_m: Any, score: float, known: set[int]) -> LoggedEstimate:
    """A validated (finite, a rotation up to rounding, known ``obj_id``) estimate, its rotation projected
    onto the nearest rotation (the one rule, :func:`brave6d.core.transforms.nearest_rotation`); else
    :class:`InvalidAction` naming the field."""
    where = f"estimates.{index}"
    if int(obj_id) not in known:
        raise InvalidAction(f"{where}.obj_id: unknown object id {obj_id} (known: {sorted(known)})", f"{where}.obj_id")
    rot = np.asarray(R, dtype=np.float64)
    if rot.size != 9:
        raise InvalidAction(f"{where}.R: must have 9 values (3x3, row-major), got {rot.size}", f"{where}.R")
    rot = rot.reshape(3, 3)
    t = np.asarray(t_m, dtype=np.float64).reshape(-1)
    if t.size != 3:
        raise InvalidAction(f"{where}.t_m: must have 3 values (metres), got {t.size}", f"{where}.t_m")
    for name, values in (("R", rot), ("t_m", t), ("score", np.asarray([score], dtype=np.float64))):
        if not np.all(np.isfinite(values)):
            raise InvalidAction(f"{where}.{name}: must be finite (NaN and inf are refused)", f"{where}.{name}")
    try:
        rot, _ = nearest_rotation(rot, f"{where}.R")
    except NonRigidTransformError as exc:
        raise InvalidAction(str(exc), f"{where}.R") from None
    return LoggedEstimate(obj_id=int(obj_id), R=rot, t_m=t, score=float(score))


def check_pose(world_T_cam: Any, field: str) -> Matrix4:
    """``world_T_cam`` as a 4x4 array when it is finite with its centre within ``MAX_COORD_M``
    (the request models check this too; this guards direct callers), else :class:`InvalidAction`."""
    T = np.array(world_T_cam, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InvalidAction(f"{field}: must be a finite 4x4 matrix", field)
    if float(np.max(np.abs(T[:3, 3]))) > MAX_COORD_M:
        raise InvalidAction(f"{field}: the camera centre must lie within {MAX_COORD_M:g} m of the origin", field)
    return T


def free_pose(world: CollisionWorld, world_T_cam: Any, field: str) -> Matrix4:
    """``world_T_cam`` checked (:func:`check_pose`) and free (inside the workspace, clear of every
    collision box), else :class:`InvalidAction` naming ``field`` with the refusal: the rule of a
    pose given without an episode to stay in (a reset's start, a free view)."""
    T = check_pose(world_T_cam, field)
    refusal = world.check(T)
    if refusal is not None:
        raise InvalidAction(f"{field}: refused: {refusal.message}", field)
    return T


def check_twist(linear: Any, angular: Any, duration: Any) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """The twist of a ``move`` as arrays when every value is finite and within the limits of
    :mod:`brave6d.serve.limits`, else :class:`InvalidAction` naming the field."""
    out = []
    for name, values, top in (("linear", linear, MAX_LINEAR_SPEED_M_S), ("angular", angular, MAX_ANGULAR_SPEED_RAD_S)):
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.size != 3 or not np.all(np.isfinite(v)) or float(np.max(np.abs(v))) > top:
            raise InvalidAction(f"{name}: must be 3 finite numbers of magnitude <= {top:.4g}", name)
        out.append(v)
    d = float(duration)
    if not (np.isfinite(d) and 0.0 < d <= MAX_MOVE_DURATION_S):
        raise InvalidAction(f"duration: must be a finite number in (0, {MAX_MOVE_DURATION_S:g}] seconds", "duration")
    return out[0], out[1], d


def check_twists(twists: Sequence[tuple[Any, Any, Any]]) -> list[tuple[NDArray[np.float64], NDArray[np.float64], float]]:
    """:func:`check_twist` of each ``(linear, angular, duration)``, checked together in arrays (many
    agents' moves); when any is malformed or out of its limits, one by one, so that the first bad
    one raises :func:`check_twist`'s error."""
    n = len(twists)
    try:
        lin = np.array([t[0] for t in twists], dtype=np.float64).reshape(n, -1)
        ang = np.array([t[1] for t in twists], dtype=np.float64).reshape(n, -1)
        dur = np.array([float(t[2]) for t in twists], dtype=np.float64)
    except (TypeError, ValueError):
        return [check_twist(*t) for t in twists]
    fine = (lin.shape == (n, 3) and ang.shape == (n, 3) and bool(np.all(np.isfinite(lin)) and np.all(np.isfinite(ang)))
            and bool(np.all(np.abs(lin) <= MAX_LINEAR_SPEED_M_S) and np.all(np.abs(ang) <= MAX_ANGULAR_SPEED_RAD_S))
            and bool(np.all(np.isfinite(dur) & (dur > 0.0) & (dur <= MAX_MOVE_DURATION_S))))
    if not fine:
        return [check_twist(*t) for t in twists]
    return [(lin[k], ang[k], float(dur[k])) for k in range(n)]


def submission_record(ep: Episode, estimates: list[LoggedEstimate], bundle: Bundle, depth_file: str | None,
                      agent: str | None, depth_sha256: str | None = None) -> SubmitRecord:
    """The ``submit`` log record: the estimates and what only the server knows about the final
    view (pose, ``K``, image size, depth file and its SHA-256, every object's ground truth in that
    camera frame)."""
    obs = ep.last
    assert obs is not None
    return SubmitRecord(
        episode_id=ep.id, agent=agent, bundle=bundle.name, bundle_root=str(bundle.root.resolve()),
        target=target_ref(ep.target), estimates=estimates,
        final_view=FinalView(world_T_cam=obs.world_T_cam, K=obs.camera.K, width=obs.camera.width,
                             height=obs.camera.height, depth_file=depth_file, depth_source=obs.geometry,
                             depth_sha256=depth_sha256 if depth_file is not None else None),
        objects=list(obs.objects), adjustments=ep.adjustments, steps=ep.steps, refusals=ep.refusals,
        collisions=ep.collisions, elapsed_s=time.monotonic() - ep.created)


def invert_stack(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """(C, 4, 4) :func:`brave6d.core.transforms.invert` of each rigid pose of ``poses`` (C, 4, 4), bit for bit:
    the same ``(-R^T) @ t`` product (NumPy's matrix product of a stack computes each as one product does;
    tested), in two array operations instead of one call per pose."""
    out = np.zeros_like(poses)
    rt = np.swapaxes(poses[:, :3, :3], 1, 2)
    out[:, :3, :3] = rt
    out[:, :3, 3] = np.matmul(-rt, poses[:, :3, 3:4])[:, :, 0]
    out[:, 3, 3] = 1.0
    return out


def target_ref(obj: BundleObject) -> TargetRef:
    """The wire/log reference of a target instance (one frozen model per instance: every step's result holds it)."""
    return _target_ref(obj.gt_id, obj.obj_id, obj.name)


@lru_cache(maxsize=4096)
def _target_ref(gt_id: int, obj_id: int, name: str) -> TargetRef:
    return TargetRef(gt_id=gt_id, obj_id=obj_id, name=name)

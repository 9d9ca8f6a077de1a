"""The learned agent (see the package docstring).

Every view: detect the target (the episode names its obj_id), keep its best detection and
estimate its pose. The static agent submits from the start view. The active agent moves while
its detection is missing, unsure (score below ``confident_score``) or small (box below
``min_box_px``): towards the target seen (on the ray through its box, at its pose's depth when
that agrees with the box's size) so the box grows to about ``approach_box_px``, never nearer than
the nearest capture ring or 3 diameters; with no detection, along its optical axis (the episode
starts looking at the target) to a fraction of the assumed distance. Then it flies back to the
start view (one more adjustment) and submits there the estimate of the view that saw the target
best, moved into the start view's frame: the nearer view's accuracy, scored where the object
covers the fewer pixels MSPD counts in (as the weight-free active baseline does). A move whose
every candidate pose the server refuses is given up and the plan goes on, so a refused approach or
orbit still ends at the start view (a refused way back: at the best view). With
``fuse_views`` it uses all the views that estimated the target, as one view cannot: RGB-only, the
object's position triangulated from the views' rays (parallax fixes the distance a single view
only guesses from the object's size); with depth, ICP onto the depth points of every view whose
estimate agrees, at once (the sides one view cannot see pin the rotation down). A submission
without any view that estimated the target is empty, and its notes name the cause.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.evaluation.agents.active import look_candidates
from brave6d.evaluation.agents.episode import scene_bundle
from brave6d.evaluation.estimators.protocol import Detection, Detector, EstimatorRefused, MultiViewRefiner, \
    PoseEstimator
from brave6d.evaluation.learned import DETECTION_THRESHOLD

Array = NDArray[np.float64]


#: The options' pixel sizes are those of an image this wide (they scale with the episode's width).
PIXELS_AT_WIDTH = 320


@dataclass(frozen=True)
class LearnedAgentOptions:
    """Thresholds in [0, 1]; sizes in pixels of a 320-wide image (scaled to the episode's); distances in metres."""

    min_score: float = DETECTION_THRESHOLD  # detections below are ignored (as the held-out recall does)
    confident_score: float = 0.5  # the active agent stops once its detection scores this ...
    min_box_px: float = 36.0  # ... and its box (geometric mean of w, h) is at least this large
    approach_box_px: float = 48.0  # a move aims for about this box size
    max_moves: int = 4
    blind_step: float = 0.6  # no detection: move to this fraction of the assumed distance
    return_to_start: bool = True  # submit from the start view (where MSPD's pixels are fewer)
    nearest_m: float | None = None  # nearest approach; None: the nearest capture ring (or 3 diameters)
    orbit_deg: tuple[float, ...] = (35.0, -35.0)  # then look from these azimuth offsets too
    fuse_views: bool = True  # the active agent's submission uses every view that saw the target (below)
    approach: bool = True  # the active agent comes closer while its view is not good enough
    view_choice: str = "best"  # whose estimate is submitted: see VIEW_CHOICES

    def __post_init__(self) -> None:
        if self.view_choice not in VIEW_CHOICES:
            raise BraveError(f"learned agent: view_choice must be one of {', '.join(VIEW_CHOICES)}, "
                             f"got {self.view_choice!r}")


#: How the agent picks the view whose estimate it submits (``LearnedAgentOptions.view_choice``):
#: the best-ranked (``_rank``), the nearest to the target (the closest look: the largest detection box,
#: not the estimate's own distance, which a wrong detection can put anywhere), or the start view.
VIEW_CHOICES = ("best", "nearest", "start")


class LearnedAgent:
    """An :class:`~brave6d.evaluation.agents.Agent` over any
    :class:`~brave6d.evaluation.estimators.Detector` and :class:`~brave6d.evaluation.estimators.PoseEstimator`
    (the built-in ones: the trained networks, :mod:`brave6d.evaluation.estimators.learned`). Their answers
    are checked (:mod:`brave6d.evaluation.estimators.checks`); they see the served image, its K, the
    depth (``use_depth`` only) and the target's CAD model, never the ground truth."""

    def __init__(self, client: Any, detector: Detector, pose_estimator: PoseEstimator, name: str, active: bool,
                 use_depth: bool, options: LearnedAgentOptions = LearnedAgentOptions()) -> None:
        self.client, self.detector, self.pose_estimator, self.name = client, detector, pose_estimator, name
        #: episodes this agent plays ask for images this wide (the pose estimator's ``image_width``, when it has one)
        self.image_width = int(getattr(pose_estimator, "image_width", 0) or 0) or None
        self._models_given: set[int] = set()
        self.active, self.use_depth, self.options = active, use_depth, options
        self._bundles: dict[Any, dict[str, Any]] = {}
        self._reset_state()

    def _reset_state(self) -> None:
        self.obj_id = 0
        self.diameter_m = 0.0
        self.moves = 0
        self.views: list[dict[str, Any]] = []
        self.current: dict[str, Any] | None = None
        self.refused = 0
        self._phase = "approach"
        self._orbit: list[Array] = []
        self._next: Array | None = None
        self._candidates: list[Array] = []
        self._returned_to_best = False

    @property
    def bundle_info(self) -> dict[str, Any]:
        """``GET /bundle`` of the current episode's scene (fetched once per scene)."""
        return scene_bundle(self.client, self._bundles)

    def observe(self, step: Any) -> None:
        if step.action == "reset":
            self._reset_state()
            self.obj_id = int(step.target["obj_id"])
            info = next((o for o in self.bundle_info.get("objects", []) if int(o["obj_id"]) == self.obj_id), {})
            self.diameter_m = float(info.get("diameter_mm", 30.0)) / 1000.0
            self._give_surface()  # RGB-only too: the distance from the mask's area needs the mesh
        elif not step.accepted:  # refused (a collision box): the next candidate pose, if any is left
            self.refused += 1
            self._next = self._candidates.pop(0) if self._candidates else self._after_refusals()
            return
        self.current = self._look(step.observation)
        self.views.append(self.current)
        self._next = self._plan() if self.active else None

    def decide(self) -> Array | None:
        return self._next

    def submit(self) -> Any:
        """The estimate of the view that saw the target best, given in the final view's frame."""
        from brave6d.core.transforms import invert
        from brave6d.evaluation.agents.protocol import Submission
        from brave6d.serve import PoseEstimate

        final = self.current
        if final is None:
            raise BraveError(f"{self.name}: submit before any view was seen")
        best = self._chosen_view()
        view = self.views[best]
        notes: dict[str, Any] = {"views": len(self.views), "moves": self.moves, "refused_poses": self.refused,
                                 "estimated_in_view": best,
                                 "posed_views": [i for i, v in enumerate(self.views) if v["pose"] is not None],
                                 "detection_score_start": self.views[0]["score"], "box_px_start": self.views[0]["size_px"],
                                 "detection_score_final": view["score"], "box_px_final": view["size_px"]}
        pose = view["pose"]
        if pose is None:
            notes["refused"] = view["cause"]
            notes["refusal"] = view["message"]
            return Submission([], notes)
        notes.update(pose.notes)
        cam_T_obj = invert(final["obs"].world_T_cam) @ view["obs"].world_T_cam @ pose.cam_T_obj
        if self.active and self.options.fuse_views:
            cam_T_obj, notes["fused"] = self._fused(final, cam_T_obj)
        return Submission([PoseEstimate(self.obj_id, cam_T_obj, pose.score)], notes)

    def _fused(self, final: dict[str, Any], cam_T_obj: Array) -> tuple[Array, str | None]:
        """``cam_T_obj`` (the best view's estimate in the final view's frame) improved with every view
        that estimated the target (module docstring); and how (None: unchanged)."""
        from brave6d.core.transforms import invert

        from brave6d.evaluation.agents.learned.fusion import triangulate

        final_inv = invert(final["obs"].world_T_cam)
        posed = [(final_inv @ v["obs"].world_T_cam, v) for v in self.views if v["pose"] is not None]
        if len(posed) < 2:
            return cam_T_obj, None
        if self.use_depth:
            near = [(T, v) for T, v in posed
                    if np.linalg.norm((T @ v["pose"].cam_T_obj)[:3, 3] - cam_T_obj[:3, 3]) <= 0.5 * self.diameter_m]
            if len(near) < 2 or any(v["obs"].depth is None for _, v in near) or \
                    not isinstance(self.pose_estimator, MultiViewRefiner):
                return cam_T_obj, None
            fused, refined, _ = self.pose_estimator.refine_views(
                self.obj_id, cam_T_obj, [(T, v["obs"].K, v["obs"].depth, v["detection"].box) for T, v in near])
            return (fused, f"icp over {len(near)} views") if refined else (cam_T_obj, None)
        origins = np.array([T[:3, 3] for T, _ in posed])
        directions = np.array([T[:3, :3] @ v["pose"].cam_T_obj[:3, 3] for T, v in posed])
        point = triangulate(origins, directions)
        distance = float(np.linalg.norm(cam_T_obj[:3, 3]))
        if point is None or not point[2] > 0 or np.linalg.norm(point - cam_T_obj[:3, 3]) > 0.25 * distance:
            return cam_T_obj, None
        out = np.array(cam_T_obj, dtype=np.float64)
        out[:3, 3] = point
        return out, f"triangulated from {len(posed)} views"

    def _chosen_view(self) -> int:
        """The index of the view whose estimate is submitted (``options.view_choice``; a view with a pose
        before one without)."""
        choice = self.options.view_choice
        if choice == "start" and self.views[0]["pose"] is not None:
            return 0
        if choice == "nearest":
            posed = [i for i, v in enumerate(self.views) if v["pose"] is not None]
            if posed:
                return max(posed, key=lambda i: self.views[i]["size_px"])  # the closest look: its largest box
        return max(range(len(self.views)), key=lambda i: self._rank(self.views[i]))

    def _rank(self, view: dict[str, Any]) -> tuple[bool, float, float]:
        """Views with a pose first; then, with depth, the one whose pose explains the most depth
        points of its box (ICP's fit); then the pose's score (detection score x PnP inlier ratio)."""
        pose = view["pose"]
        if pose is None:
            return False, 0.0, 0.0
        return True, (pose.fit or 0.0) if self.use_depth else 0.0, pose.score

    def _give_surface(self) -> None:
        """Hand the pose estimator the target's CAD model from the server (``GET /models``), once per
        object: the built-in's RGB-only distance from the mask's area and its depth ICP need it."""
        from brave6d.evaluation.agents.model import read_model_ply

        if self.obj_id in self._models_given:
            return
        scene = getattr(self.client, "scene", None)
        data = self.client.model(self.obj_id, scene) if scene is not None else self.client.model(self.obj_id)
        vertices_mm, faces, _ = read_model_ply(data)
        if faces is not None and len(faces):
            self.pose_estimator.add_model(self.obj_id, np.asarray(vertices_mm) / 1000.0, faces)
        self._models_given.add(self.obj_id)

    # ------------------------------------------------------------------ perception
    def _look(self, obs: Any) -> dict[str, Any]:
        """Detect and estimate the target in ``obs``; a failure is recorded with its cause."""
        from brave6d.evaluation.estimators.checks import checked_detections, checked_pose

        view: dict[str, Any] = {"obs": obs, "detection": None, "pose": None, "score": 0.0, "size_px": 0.0,
                                "cause": None, "message": None}
        try:
            det = self._best_detection(checked_detections(self.detector.detect(obs.rgb, obs.K, self.obj_id),
                                                          self.detector, self.obj_id))
            view.update(detection=det, score=det.score, size_px=det.size_px)
            view["pose"] = checked_pose(self.pose_estimator.estimate(obs.rgb, obs.depth if self.use_depth else None,
                                                                     obs.K, det), self.pose_estimator)
        except EstimatorRefused as exc:
            view.update(cause=exc.cause, message=str(exc))
        return view

    def _best_detection(self, found: list[Detection]) -> Detection:
        """The highest-scoring detection of at least ``options.min_score`` (the first of equals), or
        refused (``no-detection``)."""
        kept = [d for d in found if d.score >= self.options.min_score]
        if not kept:
            raise EstimatorRefused("no-detection", f"{self.name}: no detection of object {self.obj_id} scoring "
                                                   f">= {self.options.min_score}")
        return max(kept, key=lambda d: d.score)

    # ------------------------------------------------------------------ moves
    def _plan(self) -> Array | None:
        """The next camera pose of the active agent: closer while it needs to, then the orbit's
        looks from the sides, then back to the start view; None when it is done (module docstring)."""
        if self._phase == "approach":
            step = self._approach() if self.options.approach else None
            if step is not None:
                return step
            self._phase, self._orbit = "orbit", self._orbit_poses()
        if self._phase == "orbit":
            if self._orbit:
                self._candidates = []
                return self._orbit.pop(0)
            self._phase = "return"
            if self.options.return_to_start and len(self.views) > 1:
                self._candidates = []
                return np.asarray(self.views[0]["obs"].world_T_cam, dtype=np.float64)
        return None

    def _after_refusals(self) -> Array | None:
        """Where to go once every candidate of a move was refused: give that move up and go on with
        the plan (no more approach; the orbit's next look; back to the start view), so the episode
        still ends at the start view; if the way back itself was refused, at the view that saw the
        target best (None: already there)."""
        if self._phase == "approach":
            self._phase, self._orbit = "orbit", self._orbit_poses()
        if self._phase != "return":
            return self._plan()
        best = self.views[self._chosen_view()]["obs"].world_T_cam
        current = self.current["obs"].world_T_cam if self.current is not None else None
        if current is None or np.allclose(best, current) or self._returned_to_best:
            return None
        self._returned_to_best = True
        return np.asarray(best, dtype=np.float64)

    def _orbit_poses(self) -> list[Array]:
        """Looks at the target from ``orbit_deg`` azimuth offsets at the current distance (none when
        the target was never seen)."""
        view = self.current
        if view is None or view["detection"] is None or not self.options.orbit_deg:
            return []
        target_w, _ = self._target(view)
        eye = view["obs"].world_T_cam[:3, 3]
        v = eye - target_w
        dist = float(np.linalg.norm(v))
        azimuth = math.atan2(float(v[1]), float(v[0]))
        elevation = math.degrees(math.atan2(float(v[2]), float(np.hypot(v[0], v[1]))))
        return [look_candidates(target_w, dist, azimuth + math.radians(a), max(elevation, 0.0))[0]
                for a in self.options.orbit_deg]

    def _approach(self) -> Array | None:
        """The next pose towards the target, or None when the view is good enough or nothing is gained."""
        o, view = self.options, self.current
        if view is None or self.moves >= o.max_moves:
            return None
        k = view["obs"].rgb.shape[1] / PIXELS_AT_WIDTH  # the options' pixels are a 320-wide image's
        if view["detection"] is not None and view["score"] >= o.confident_score and view["size_px"] >= o.min_box_px * k:
            return None
        if view["cause"] == "unknown-object":
            return None  # no move can help
        obs = view["obs"]
        eye = obs.world_T_cam[:3, 3]
        target_w, dist = self._target(view)
        near = max(self._standoff() if o.nearest_m is None else o.nearest_m, 3.0 * self.diameter_m)
        if view["detection"] is not None:
            goal = dist * min(view["size_px"] / (o.approach_box_px * k), 1.0)
        else:
            goal = dist * o.blind_step
        goal = max(goal, near)
        if goal > 0.9 * dist:
            return None  # too little to gain for an adjustment
        self.moves += 1
        v = eye - target_w
        azimuth = math.atan2(float(v[1]), float(v[0]))
        elevation = math.degrees(math.atan2(float(v[2]), float(np.hypot(v[0], v[1]))))
        first, *self._candidates = look_candidates(target_w, goal, azimuth, max(elevation, 0.0))
        return first

    def _target(self, view: dict[str, Any]) -> tuple[Array, float]:
        """Where the target is (world frame) and how far. With a detection: on the ray through its
        box centre, at its pose's depth when that agrees with the box's size (within 2x of
        ``f * 0.7 diameter / size``), else at that size's depth; without one: on the optical axis at
        the served depth (``use_depth``) or the middle capture ring."""
        obs = view["obs"]
        world_T_cam, K = obs.world_T_cam, np.asarray(obs.K, dtype=np.float64)
        det = view["detection"]
        if det is not None:
            u, v = (det.box[0] + det.box[2]) / 2.0 - 0.5, (det.box[1] + det.box[3]) / 2.0 - 0.5
            ray = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
            z = K[0, 0] * 0.7 * self.diameter_m / max(det.size_px, 1.0)
            if view["pose"] is not None and 0.5 * z <= view["pose"].cam_T_obj[2, 3] <= 2.0 * z:
                z = float(view["pose"].cam_T_obj[2, 3])
            p_cam = ray * z
        else:
            p_cam = np.array([0.0, 0.0, self._assumed_distance(obs)])
        p_w = world_T_cam[:3, :3] @ p_cam + world_T_cam[:3, 3]
        return p_w, float(np.linalg.norm(p_cam))

    def _assumed_distance(self, obs: Any) -> float:
        if self.use_depth and obs.depth is not None:
            h, w = obs.depth.shape
            patch = obs.depth[h // 2 - 2:h // 2 + 3, w // 2 - 2:w // 2 + 3]
            valid = patch[np.isfinite(patch) & (patch > 0)]
            if valid.size:
                return float(np.median(valid))
        rings = (self.bundle_info.get("start") or {}).get("distances_m") or [0.2, 0.5]
        return float(np.mean([min(rings), max(rings)]))

    def _standoff(self) -> float:
        rings = (self.bundle_info.get("start") or {}).get("distances_m") or []
        return float(min(rings)) if rings else 0.10


"""The weight-free baseline agent: find the target in the depth image, register its model, submit.

Nothing is learned and nothing is downloaded; every step is classical geometry (Open3D):
:mod:`~brave6d.evaluation.agents.perception` finds the target's cluster above the table,
:mod:`~brave6d.evaluation.agents.registration` fits the model to it (on depth, with the model's
colours against the colour image to tell a near-symmetric object from its flip), a camera policy
(:mod:`~brave6d.evaluation.agents.static`, :mod:`~brave6d.evaluation.agents.active`) decides where to look, and
:mod:`~brave6d.evaluation.agents.fusion` combines the views into the estimate, given in the camera frame
of the view the policy ends in. With no cluster at all the estimate is a guess where the target
was last seen (at first: on the start view's optical axis).

The agent reads from ``GET /bundle`` only what a user of the benchmark is given about the target:
its ``obj_id``, model and diameter, never any ``world_T_obj``. Deterministic: every random choice
is seeded and Open3D runs on one thread while the agent computes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.core.transforms import invert
from brave6d.evaluation.agents.episode import scene_bundle
from brave6d.evaluation.agents.fusion import register_views
from brave6d.evaluation.agents.model import ModelCloud, ModelOptions, read_model_ply, sample_model
from brave6d.evaluation.agents.perception import PerceptionOptions, View, axis_anchor, backproject, perceive
from brave6d.evaluation.agents.policy import CameraPolicy, EpisodeState, PolicyPlan
from brave6d.evaluation.agents.protocol import Submission
from brave6d.evaluation.agents.registration import Registration, RegistrationOptions, register_model, resting_pose

Array = NDArray[np.float64]


@dataclass(frozen=True)
class BaselineOptions:
    """The options of the baseline's parts (the camera policy has its own)."""

    model: ModelOptions = ModelOptions()
    perception: PerceptionOptions = PerceptionOptions()
    registration: RegistrationOptions = RegistrationOptions()


class BaselineAgent:
    """The baseline as an :class:`~brave6d.evaluation.agents.protocol.Agent`: perception and registration
    in every view, ``policy`` for the camera; models are fetched from the server once per object."""

    def __init__(self, client: Any, policy: CameraPolicy, name: str,
                 options: BaselineOptions = BaselineOptions()) -> None:
        self.client = client
        self.policy = policy
        self.name = name
        self.options = options
        self._models: dict[int, ModelCloud] = {}
        self._bundles: dict[str | int | None, dict[str, Any]] = {}
        self._episode: EpisodeState | None = None
        self._plan: PolicyPlan | None = None
        self._next_pose: Array | None = None
        self._final: View | None = None

    @property
    def bundle_info(self) -> dict[str, Any]:
        """``GET /bundle`` of the current episode's scene (fetched once per scene)."""
        return scene_bundle(self.client, self._bundles)

    def model(self, obj_id: int) -> ModelCloud:
        """The target's model cloud from the server (``GET /bundle`` diameter, model PLY)."""
        if obj_id not in self._models:
            info = next((o for o in self.bundle_info["objects"] if int(o["obj_id"]) == obj_id), None)
            if info is None:
                raise BraveError(f"the server knows no object with obj_id {obj_id}")
            scene = getattr(self.client, "scene", None)  # a dataset keeps one model per obj_id across scenes
            verts, faces, colors = read_model_ply(self.client.model(obj_id, scene) if scene is not None
                                                  else self.client.model(obj_id))
            self._models[obj_id] = sample_model(obj_id, verts, faces, float(info["diameter_mm"]),
                                                self.options.model.points, self.options.model.seed, colors)
        return self._models[obj_id]

    def observe(self, step: Any) -> None:
        if step.action == "reset":
            self._start(step)
        else:
            self._advance(step)

    def decide(self) -> Array | None:
        return self._next_pose

    def submit(self) -> Submission:
        """Register the target in the final view (fusing every view that saw it) and estimate."""
        from brave6d.serve import PoseEstimate

        episode, final = self._episode, self._final
        if episode is None or final is None:
            raise BraveError(f"{self.name}: submit before the episode's plan ended")
        obs, seen = final
        start = episode.views[0].perception
        if sum(v.perception.cluster is not None for v in episode.views) > 1:
            registration = register_views(episode.model, episode.views, self.options.registration, final=(obs, seen))
        elif seen.cluster is not None:
            registration = register_model(episode.model, seen.cluster, seen.plane, obs.depth, obs.K,
                                          self.options.registration, seen.min_height, getattr(obs, "rgb", None))
        else:
            registration = None
        if registration is None:  # nothing found: a guess where the target was last seen
            anchor = invert(obs.world_T_cam) @ np.append(episode.target_w, 1.0)
            registration = Registration(resting_pose(episode.model, np.eye(3), anchor[None, :3], seen.plane),
                                        0.0, 0.0, "axis", 0)
        estimate = PoseEstimate(episode.model.obj_id, registration.cam_T_obj,
                                float(np.clip(registration.score, 0.0, 1.0)))
        notes = {"found": seen.cluster is not None, "registration": registration,
                 "registration_method": registration.method, "registration_score": registration.score,
                 "box_px_start": start.cluster.box_px if start.cluster is not None else None,
                 "box_px_final": seen.cluster.box_px if seen.cluster is not None else None}
        return Submission([estimate], notes)

    def _start(self, step: Any) -> None:
        """A new episode: perceive the start view, expecting the target on its optical axis."""
        model = self.model(int(step.target["obj_id"]))
        obs = step.observation
        seen = perceive(obs.depth, obs.K, obs.world_T_cam, model, None, self.options.perception)
        point = seen.cluster.centroid if seen.cluster is not None else axis_anchor(*backproject(obs.depth, obs.K), obs.K)
        target_w = obs.world_T_cam[:3, :3] @ point + obs.world_T_cam[:3, 3]
        self._episode = EpisodeState(model, self.bundle_info, [View(obs, seen)], target_w, self.options.perception)
        self._plan = self.policy.explore(self._episode)
        self._final = None
        self._advance(None)

    def _advance(self, step: Any) -> None:
        """Send ``step`` to the policy's plan; note the next pose it wants, or the view it ends in."""
        if self._plan is None:
            raise BraveError(f"{self.name}: a step arrived outside an episode's plan")
        try:
            self._next_pose = self._plan.send(step)
        except StopIteration as done:
            self._next_pose, self._final, self._plan = None, done.value, None

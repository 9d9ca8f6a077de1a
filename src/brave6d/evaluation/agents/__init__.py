"""Agents that play the benchmark's episodes through ``serve``'s client, and the registry of them.

Public API (imported lazily, so ``import brave6d.evaluation.agents`` stays cheap: no Open3D):

- :class:`Agent` (observe, decide, submit), :class:`Submission`, :func:`run_episode` (the episode
  loop, written once for any agent) and :class:`EpisodeOutcome`.
- :data:`POLICIES`: agent name -> factory ``(client) -> Agent``; the demo and the benchmarks run
  every registered agent. :func:`make_agent` builds one by name.
- The baseline's parts: :class:`BaselineAgent` with a :class:`CameraPolicy`
  (:class:`StaticPolicy`, :class:`ActivePolicy`), :func:`perceive`, :func:`register_model`,
  :func:`register_views`, :func:`sample_model`, :func:`read_model_ply` and their options.
- The static estimator on any RGB-D frame (no server, no world pose): :func:`estimate_pose` with a
  :class:`PixelHint` or :class:`BoxHint`, the model from :func:`prepare_model` (PLY or points, mm or
  m), :class:`FrameOptions`; it returns a :class:`FramePose` or raises :class:`EstimateRefused`
  (``cause`` in :data:`REFUSAL_CAUSES`); :func:`read_depth_png` (16-bit PNG + BOP ``depth_scale`` ->
  metres), :func:`perceive_up` (perception given "up" in the camera frame), :func:`table_plane`.

A new agent: a module in this package implementing :class:`Agent` (or a new :class:`CameraPolicy`
for the baseline), a factory and its entry in :data:`POLICIES` (docs/ARCHITECTURE.md, section 6).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from brave6d.core.errors import BraveError
from brave6d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from brave6d.evaluation.agents.protocol import Agent

ACTIVE_AGENT = "baseline-active"
STATIC_AGENT = "baseline-static"

__all__ = ["ACTIVE_AGENT", "POLICIES", "REFUSAL_CAUSES", "STATIC_AGENT", "ActiveOptions", "ActivePolicy", "Agent",
           "BaselineAgent", "BaselineOptions", "BoxHint", "CameraPolicy", "Cluster", "EpisodeOutcome", "EpisodeState",
           "EstimateRefused", "FrameOptions", "FramePose", "ModelCloud", "ModelOptions", "Perception",
           "PerceptionOptions", "PixelHint", "Plane", "Registration", "RegistrationOptions", "StaticPolicy",
           "Submission", "View", "ViewScene", "estimate_pose", "make_agent", "multiview_icp", "one_thread",
           "perceive", "perceive_near", "perceive_up", "prepare_model", "read_depth_png", "read_model_ply",
           "register_model", "register_scene", "register_views", "run_episode", "sample_model", "standoff_m",
           "table_plane", "view_scene", "view_weights", "voxel_size"]

_LAZY = {
    "Agent": ".protocol", "Submission": ".protocol",
    "run_episode": ".episode", "EpisodeOutcome": ".episode",
    "BaselineAgent": ".baseline", "BaselineOptions": ".baseline",
    "CameraPolicy": ".policy", "EpisodeState": ".policy",
    "StaticPolicy": ".static",
    "ActivePolicy": ".active", "ActiveOptions": ".active", "standoff_m": ".active",
    "ModelCloud": ".model", "ModelOptions": ".model", "sample_model": ".model", "read_model_ply": ".model",
    "Perception": ".perception", "PerceptionOptions": ".perception", "Plane": ".perception",
    "Cluster": ".perception", "View": ".perception", "perceive": ".perception", "perceive_near": ".perception",
    "perceive_up": ".perception",
    "estimate_pose": ".frame", "prepare_model": ".frame", "read_depth_png": ".frame", "table_plane": ".frame",
    "FrameOptions": ".frame", "FramePose": ".frame", "PixelHint": ".frame", "BoxHint": ".frame",
    "EstimateRefused": ".frame", "REFUSAL_CAUSES": ".frame",
    "Registration": ".registration", "RegistrationOptions": ".registration", "ViewScene": ".registration",
    "register_model": ".registration", "register_scene": ".registration", "view_scene": ".registration",
    "voxel_size": ".registration",
    "register_views": ".fusion", "view_weights": ".fusion", "multiview_icp": ".fusion",
    "one_thread": ".pointclouds",
}


def _static_baseline(client: Any) -> Agent:
    from brave6d.evaluation.agents.baseline import BaselineAgent
    from brave6d.evaluation.agents.static import StaticPolicy

    return BaselineAgent(client, StaticPolicy(), STATIC_AGENT)


def _active_baseline(client: Any) -> Agent:
    from brave6d.evaluation.agents.active import ActivePolicy
    from brave6d.evaluation.agents.baseline import BaselineAgent

    return BaselineAgent(client, ActivePolicy(), ACTIVE_AGENT)


#: Agent name (as the episode logs and leaderboards show it) -> factory ``(client) -> Agent``,
#: in the order the demo runs them on each start.
POLICIES: dict[str, Callable[[Any], Agent]] = {
    STATIC_AGENT: _static_baseline,
    ACTIVE_AGENT: _active_baseline,
}


def make_agent(name: str, client: Any) -> Agent:
    """The registered agent ``name`` playing through ``client`` (``serve``'s ``BraveClient``)."""
    factory = POLICIES.get(name)
    if factory is None:
        raise BraveError(f"no agent named {name!r}; registered: {', '.join(POLICIES)}")
    return factory(client)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

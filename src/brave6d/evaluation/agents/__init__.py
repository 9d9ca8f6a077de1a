"""Agents that play the benchmark's episodes through ``serve``'s client, and the registry of them.

Public API (imported lazily, so ``import brave6d.evaluation.agents`` stays cheap: no Open3D):

- :class:`Agent` (observe, decide, submit), :class:`Submission`, :func:`run_episode` (the episode
  loop, written once for any agent) and :class:`EpisodeOutcome`.
- The client they play through, :class:`EpisodeClient` (reset, set_pose, submit, bundle, model;
  steps as :class:`EpisodeStep`): ``serve``'s HTTP ``BraveClient``, :class:`GymEpisodeClient` (over a
  ``BraveEnv``), or ``brave6d.ros_interface``'s ``Ros2EpisodeClient`` / ``Ros1EpisodeClient``, whose
  steps are :class:`TransportStep` with a :class:`TransportView` (:mod:`.transports`).
- :data:`POLICIES`: agent name -> factory ``(client, setup) -> Agent``; the demo and the benchmarks
  run every registered agent. :func:`make_agent` builds one by name; :class:`AgentSetup` carries
  what some agents need beyond the client (the learned agents: a trained model folder), and
  :data:`LEARNED_AGENTS` names those that need one (:mod:`brave6d.evaluation.agents.learned`).
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
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from brave6d.core.errors import BraveError
from brave6d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from brave6d.evaluation.agents.protocol import Agent

ACTIVE_AGENT = "baseline-active"
STATIC_AGENT = "baseline-static"
LEARNED_STATIC_AGENT = "learned-static"
LEARNED_ACTIVE_AGENT = "learned-active"
LEARNED_STATIC_DEPTH_AGENT = "learned-static-depth"
LEARNED_ACTIVE_DEPTH_AGENT = "learned-active-depth"
#: The agents that need a trained model (``AgentSetup.learned_model``): RGB-only, then depth-refined.
LEARNED_AGENTS = (LEARNED_STATIC_AGENT, LEARNED_ACTIVE_AGENT, LEARNED_STATIC_DEPTH_AGENT, LEARNED_ACTIVE_DEPTH_AGENT)
#: The learned active agent with one of its parts alone (what each buys; report section 10), RGB-only
#: then with depth: name -> the base agent and the part (``agents.learned.ablation.ABLATIONS``). They
#: play only when asked for by name (never in :func:`runnable_agents`).
ABLATION_AGENTS = {f"{base}-{part}": (base, part) for base in (LEARNED_ACTIVE_AGENT, LEARNED_ACTIVE_DEPTH_AGENT)
                   for part in ("closeness", "selection", "fusion")}

__all__ = ["ABLATION_AGENTS", "ACTIVE_AGENT", "LEARNED_ACTIVE_AGENT", "LEARNED_ACTIVE_DEPTH_AGENT", "LEARNED_AGENTS",
           "LEARNED_STATIC_AGENT", "LEARNED_STATIC_DEPTH_AGENT", "POLICIES", "AgentSetup", "runnable_agents", "REFUSAL_CAUSES", "STATIC_AGENT", "ActiveOptions", "ActivePolicy", "Agent",
           "BaselineAgent", "BaselineOptions", "BoxHint", "CameraPolicy", "Cluster", "EpisodeOutcome", "EpisodeState",
           "EstimateRefused", "FrameOptions", "FramePose", "ModelCloud", "ModelOptions", "Perception",
           "PerceptionOptions", "PixelHint", "Plane", "Registration", "RegistrationOptions", "StaticPolicy",
           "Submission", "View", "ViewScene", "EpisodeClient", "EpisodeStep", "GymEpisodeClient",
           "TransportStep", "TransportView", "estimate_pose", "make_agent", "multiview_icp", "one_thread",
           "perceive", "perceive_near", "perceive_up", "prepare_model", "read_depth_png", "read_model_ply",
           "register_model", "register_scene", "register_views", "run_episode", "sample_model", "standoff_m",
           "table_plane", "view_scene", "view_weights", "voxel_size"]

_LAZY = {
    "Agent": ".protocol", "Submission": ".protocol",
    "run_episode": ".episode", "EpisodeOutcome": ".episode",
    "EpisodeClient": ".transports", "EpisodeStep": ".transports", "GymEpisodeClient": ".transports",
    "TransportStep": ".transports", "TransportView": ".transports",
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


@dataclass(frozen=True)
class AgentSetup:
    """What agents may need besides the client: ``learned_model``, a folder with a trained
    ``model.pt`` (``brave6d learn train``) for the learned agents; ``device`` for their networks.
    ``detector`` / ``pose_estimator``: what the learned agents play with instead of the trained
    networks: an object implementing :class:`~brave6d.evaluation.estimators.Detector` /
    :class:`~brave6d.evaluation.estimators.PoseEstimator`, ``"MODULE:FACTORY"`` (a callable of no
    arguments that makes one) or a built-in name (``"learned"``, ``"learned-onnx"``: its ONNX export on
    ONNX Runtime, ``"registration"``: pose only);
    None: the trained model's (docs/GUIDE.md, "Your own estimator")."""

    learned_model: Path | None = None
    device: str = "cpu"
    detector: Any = None
    pose_estimator: Any = None

    @property
    def has_estimators(self) -> bool:
        """Whether the learned agents can play: a trained model, or a detector and a pose estimator
        that need none."""
        needs_model = [x for x in (self.detector, self.pose_estimator) if x is None or x in ("learned", "learned-onnx")]
        return self.learned_model is not None or not needs_model


def _static_baseline(client: Any, setup: AgentSetup) -> Agent:
    from brave6d.evaluation.agents.baseline import BaselineAgent
    from brave6d.evaluation.agents.static import StaticPolicy

    return BaselineAgent(client, StaticPolicy(), STATIC_AGENT)


def _active_baseline(client: Any, setup: AgentSetup) -> Agent:
    from brave6d.evaluation.agents.active import ActivePolicy
    from brave6d.evaluation.agents.baseline import BaselineAgent

    return BaselineAgent(client, ActivePolicy(), ACTIVE_AGENT)


@lru_cache(maxsize=4)
def _estimator(model_dir: Path, device: str, onnx: bool = False) -> Any:
    from brave6d.evaluation.learned import LearnedEstimator

    if onnx:
        from brave6d.evaluation.learned import use_onnx

        return use_onnx(LearnedEstimator.load(model_dir), model_dir)
    return LearnedEstimator.load(model_dir, device)


def _implementation(setup: AgentSetup, role: str, name: str, min_score: float) -> Any:
    """The detector or pose estimator (``role``) ``setup`` names for agent ``name``: its object, a
    ``MODULE:FACTORY``, a built-in name, or None: the trained model's."""
    from brave6d.evaluation.estimators.loading import BUILT_IN, check_role, load_factory

    given = getattr(setup, role)
    if given is None or isinstance(given, str) and given in BUILT_IN:
        kind = given or "learned"
        if role not in BUILT_IN[kind]:
            raise BraveError(f"agent {name!r}: {role} {kind!r}: the built-in {kind!r} is only a "
                             f"{' or '.join(BUILT_IN[kind])}")
        if kind == "registration":
            from brave6d.evaluation.estimators import RegistrationPoseEstimator

            return RegistrationPoseEstimator()
        if setup.learned_model is None:
            raise BraveError(f"agent {name!r} needs a trained model: give its folder (brave6d learn train ... --out "
                             "MODEL_DIR) as AgentSetup(learned_model=MODEL_DIR), or to the benchmark script as "
                             "python benchmarks/baselines.py --learned-model MODEL_DIR (or give AgentSetup a "
                             "detector and a pose_estimator of your own)")
        from brave6d.evaluation.estimators import LearnedDetector, LearnedPoseEstimator

        estimator = _estimator(Path(setup.learned_model).resolve(), setup.device, kind == "learned-onnx")
        return LearnedDetector(estimator, min_score) if role == "detector" else LearnedPoseEstimator(estimator)
    if isinstance(given, str):
        return load_factory(given, role)
    check_role(given, role, f"given to agent {name!r}")
    return given


def _learned(name: str, active: bool, use_depth: bool, part: str | None = None) -> Callable[[Any, AgentSetup], Agent]:
    def factory(client: Any, setup: AgentSetup) -> Agent:
        from brave6d.evaluation.agents.learned import LearnedAgent, LearnedAgentOptions
        from brave6d.evaluation.agents.learned.ablation import ABLATIONS

        options = ABLATIONS[part] if part is not None else LearnedAgentOptions()
        return LearnedAgent(client, _implementation(setup, "detector", name, options.min_score),
                            _implementation(setup, "pose_estimator", name, options.min_score), name, active,
                            use_depth, options)

    return factory


#: Agent name (as the episode logs and leaderboards show it) -> factory ``(client, setup) -> Agent``,
#: in the order the demo runs them on each start.
POLICIES: dict[str, Callable[[Any, AgentSetup], Agent]] = {
    STATIC_AGENT: _static_baseline,
    ACTIVE_AGENT: _active_baseline,
    LEARNED_STATIC_AGENT: _learned(LEARNED_STATIC_AGENT, active=False, use_depth=False),
    LEARNED_ACTIVE_AGENT: _learned(LEARNED_ACTIVE_AGENT, active=True, use_depth=False),
    LEARNED_STATIC_DEPTH_AGENT: _learned(LEARNED_STATIC_DEPTH_AGENT, active=False, use_depth=True),
    LEARNED_ACTIVE_DEPTH_AGENT: _learned(LEARNED_ACTIVE_DEPTH_AGENT, active=True, use_depth=True),
    **{name: _learned(name, active=True, use_depth=base == LEARNED_ACTIVE_DEPTH_AGENT, part=part)
       for name, (base, part) in ABLATION_AGENTS.items()},
}


def runnable_agents(setup: AgentSetup | None = None) -> list[str]:
    """The registered agents ``setup`` can build, in registry order (the learned ones need a model, or a
    detector and a pose estimator of the user's)."""
    setup = setup or AgentSetup()
    return [n for n in POLICIES if n not in ABLATION_AGENTS and (n not in LEARNED_AGENTS or setup.has_estimators)]


def make_agent(name: str, client: Any, setup: AgentSetup | None = None) -> Agent:
    """The registered agent ``name`` playing through ``client`` (an :class:`EpisodeClient`: ``serve``'s
    ``BraveClient``, :class:`GymEpisodeClient`, ``brave6d.ros_interface``'s ``Ros2EpisodeClient`` or
    ``Ros1EpisodeClient``)."""
    factory = POLICIES.get(name)
    if factory is None:
        raise BraveError(f"no agent named {name!r}; registered: {', '.join(POLICIES)}")
    return factory(client, setup or AgentSetup())


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

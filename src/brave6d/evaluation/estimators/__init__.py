"""Detectors and pose estimators as agents use them: the interfaces, the built-in implementations,
and a user's own loaded by name (docs/GUIDE.md, "Your own estimator").

Public API (imported lazily: no torch, no Open3D):

- the interfaces (:mod:`~brave6d.evaluation.estimators.protocol`): :class:`Detector`
  (``detect(image, K, obj_id=None) -> list[Detection]``), :class:`PoseEstimator`
  (``add_model``, ``estimate(image, depth_m | None, K, detection) -> EstimatedPose``), the optional
  :class:`MultiViewRefiner`; :class:`Detection`, :class:`EstimatedPose`, :class:`EstimatorRefused`;
- the checks every answer passes before an agent uses it: :func:`checked_detections`, :func:`checked_pose`;
- the built-in implementations: :class:`LearnedDetector`, :class:`LearnedPoseEstimator` (the trained
  networks), :class:`RegistrationPoseEstimator` (weight-free, needs depth);
- :func:`load_factory` (``MODULE:FACTORY``), :data:`BUILT_IN`.

The learned agents (:mod:`brave6d.evaluation.agents.learned`) take any detector and pose estimator
(:class:`brave6d.evaluation.agents.AgentSetup`'s ``detector`` and ``pose_estimator``).
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "Detector": ".protocol", "PoseEstimator": ".protocol", "MultiViewRefiner": ".protocol", "Detection": ".protocol",
    "EstimatedPose": ".protocol", "EstimatorRefused": ".protocol",
    "checked_detections": ".checks", "checked_pose": ".checks",
    "LearnedDetector": ".learned", "LearnedPoseEstimator": ".learned",
    "RegistrationPoseEstimator": ".registration",
    "load_factory": ".loading", "BUILT_IN": ".loading",
}

__all__ = sorted(_LAZY)

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

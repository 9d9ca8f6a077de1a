"""Capture stage: view planning, robot and camera backends (real and simulated), capture runner.

Public API (what other stages may use):
``open_rig`` / ``Rig`` (robot + camera pair), ``run_capture`` / ``CaptureOptions`` (the resumable
runner), ``plan_views`` / ``Plan`` / ``load_plan`` / ``save_plan`` (view planning) and the
``Robot`` / ``Camera`` protocols. The CPU renderer for other stages (the synthetic training
split), loaded lazily (Open3D): ``SimCamera``, ``SceneModel``, ``MeshPart``, ``load_mesh_parts``,
``STATIC_ID_BASE``.
"""

from brave6d.core.lazy import lazy_exports
from brave6d.capture.backends import Rig, open_rig
from brave6d.capture.protocols import Camera, CameraError, Frame, Robot, RobotError
from brave6d.capture.runner import CaptureOptions, CaptureSummary, run_capture

_LAZY = {"SimCamera": ".sim_camera", "SceneModel": ".scene_model", "MeshPart": ".scene_model",
         "load_mesh_parts": ".scene_model", "STATIC_ID_BASE": ".scene_model"}

__all__ = ["Rig", "open_rig", "Camera", "CameraError", "Frame", "Robot", "RobotError", "CaptureOptions",
           "CaptureSummary", "run_capture", *_LAZY]

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

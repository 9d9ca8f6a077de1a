"""Capture stage: view planning, robot and camera backends (real and simulated), capture runner.

Public API (what other stages may use):
``open_rig`` / ``Rig`` (robot + camera pair), ``run_capture`` / ``CaptureOptions`` (the resumable
runner), ``plan_views`` / ``Plan`` / ``load_plan`` / ``save_plan`` (view planning) and the
``Robot`` / ``Camera`` protocols.
"""

from capture.backends import Rig, open_rig
from capture.protocols import Camera, CameraError, Frame, Robot, RobotError
from capture.runner import CaptureOptions, CaptureSummary, run_capture

__all__ = ["Rig", "open_rig", "Camera", "CameraError", "Frame", "Robot", "RobotError", "CaptureOptions",
           "CaptureSummary", "run_capture"]

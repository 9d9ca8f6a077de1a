"""Calibration stage: ChArUco board, camera intrinsics, eye-in-hand calibration, reports.

Public API (everything else is internal):

* board: :class:`CharucoDetection`, :func:`detect_charuco`, :func:`board_corner_points`,
  :func:`render_board` / :class:`BoardTexture`, :func:`export_board` (printable PDF/PNG/SVG);
* capture plan: :func:`plan_calibration_poses`, :func:`plan_for_board`, :class:`PlannedPose`;
* intrinsics: :func:`calibrate_intrinsics`, :func:`evaluate_intrinsics` (factory intrinsics),
  :class:`IntrinsicsResult`;
* hand-eye: :func:`check_handeye_conditioning`, :func:`solve_closed_form` (tsai, park,
  daniilidis), :func:`calibrate_handeye` (closed-form + joint refinement) with
  :class:`HandEyeView`, :class:`HandEyeOptions`, :class:`HandEyeResult`;
* report: :func:`write_report`.

Conventions: 4x4 float64 ``a_T_b`` maps points from frame b to frame a; metres and radians
(the JSON and reports say mm/deg in the key where they use them); camera frame OpenCV.
"""

from brave6d.calibration.board import (
    BoardTexture,
    CharucoDetection,
    board_corner_points,
    detect_charuco,
    export_board,
    render_board,
)
from brave6d.calibration.closed_form import CLOSED_FORM_METHODS, solve_closed_form
from brave6d.calibration.conditioning import (
    ConditioningReport,
    ConditioningThresholds,
    check_handeye_conditioning,
)
from brave6d.calibration.handeye import (
    HandEyeOptions,
    HandEyeView,
    calibrate_handeye,
    estimate_board_pose,
)
from brave6d.calibration.handeye_result import HandEyeResult
from brave6d.calibration.intrinsics import (
    IntrinsicsResult,
    calibrate_intrinsics,
    evaluate_intrinsics,
)
from brave6d.calibration.plan import PlannedPose, plan_calibration_poses, plan_for_board
from brave6d.calibration.report import write_report

__all__ = [
    "CLOSED_FORM_METHODS",
    "BoardTexture",
    "CharucoDetection",
    "ConditioningReport",
    "ConditioningThresholds",
    "HandEyeOptions",
    "HandEyeResult",
    "HandEyeView",
    "IntrinsicsResult",
    "PlannedPose",
    "board_corner_points",
    "calibrate_handeye",
    "calibrate_intrinsics",
    "check_handeye_conditioning",
    "detect_charuco",
    "estimate_board_pose",
    "evaluate_intrinsics",
    "export_board",
    "plan_calibration_poses",
    "plan_for_board",
    "render_board",
    "solve_closed_form",
    "write_report",
]

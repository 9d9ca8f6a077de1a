"""Calibration stage: ChArUco board, camera intrinsics, hand-eye calibration (eye-in-hand and
eye-to-hand), calibration from any folder, reports.

Public API (imported lazily; everything else is internal):

* board: :class:`CharucoDetection`, :func:`detect_charuco`, :func:`board_corner_points`,
  :func:`render_board` / :class:`BoardTexture`, :func:`export_board` (printable PDF/PNG/SVG);
* capture plan: :func:`plan_calibration_poses`, :func:`plan_for_board`, :class:`PlannedPose`;
* intrinsics: :func:`calibrate_intrinsics`, :func:`calibrate_intrinsics_auto` (the CLI's default:
  tangential distortion only when significant), :func:`evaluate_intrinsics` (factory intrinsics),
  :class:`IntrinsicsResult`, :class:`IntrinsicsCovariance` (their full covariance);
* hand-eye: :func:`check_handeye_conditioning`, :func:`solve_closed_form` (tsai, park,
  daniilidis), :func:`calibrate_handeye` (eye-in-hand: closed-form + joint refinement) with
  :class:`HandEyeView`, :class:`HandEyeOptions`, :class:`HandEyeResult`;
  :func:`calibrate_eye_to_hand` / :class:`EyeToHandResult` (static camera, ``base_T_cam``);
  a refusal: :class:`HandEyeRefusedError` with its :class:`UncertaintyBreakdown`
  (:func:`explain_uncertainty`: the dominant cause and each cause's share);
* from any folder (``brave6d calibrate folder``): robot pose files (:func:`read_pose_file`,
  :func:`read_pose_collection`, :class:`PoseFormat`, :class:`PoseFileError`), pairing
  (:func:`pair_images_with_poses`, :class:`PosedImages`, :func:`list_images`), the run
  (:func:`calibrate_folder`, :class:`FolderCalibration`, :func:`write_folder_results`,
  :func:`folder_summary_lines`);
* report: :func:`write_report`.

Conventions: 4x4 float64 ``a_T_b`` maps points from frame b to frame a; metres and radians
(the JSON and reports say mm/deg in the key where they use them); camera frame OpenCV.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "BoardTexture": ".board", "CharucoDetection": ".board", "board_corner_points": ".board",
    "detect_charuco": ".board", "export_board": ".board", "render_board": ".board",
    "CLOSED_FORM_METHODS": ".closed_form", "solve_closed_form": ".closed_form",
    "ConditioningReport": ".conditioning", "ConditioningThresholds": ".conditioning",
    "check_handeye_conditioning": ".conditioning",
    "HandEyeOptions": ".handeye", "HandEyeView": ".handeye", "calibrate_handeye": ".handeye",
    "estimate_board_pose": ".handeye",
    "HandEyeResult": ".handeye_result",
    "EyeToHandResult": ".eye_to_hand", "calibrate_eye_to_hand": ".eye_to_hand",
    "HandEyeRefusedError": ".refusal", "UncertaintyBreakdown": ".refusal", "explain_uncertainty": ".refusal",
    "IntrinsicsResult": ".intrinsics", "calibrate_intrinsics": ".intrinsics", "calibrate_intrinsics_auto": ".intrinsics",
    "evaluate_intrinsics": ".intrinsics",
    "IntrinsicsCovariance": ".intrinsics_covariance",
    "PoseFileError": ".pose_files", "PoseFormat": ".pose_files", "read_pose_collection": ".pose_files",
    "read_pose_file": ".pose_files",
    "PosedImages": ".pairing", "list_images": ".pairing", "pair_images_with_poses": ".pairing",
    "FolderCalibration": ".folder", "calibrate_folder": ".folder", "folder_summary_lines": ".folder",
    "write_folder_results": ".folder",
    "PlannedPose": ".plan", "plan_calibration_poses": ".plan", "plan_for_board": ".plan",
    "write_report": ".report",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

"""Calibrate a scene directory from its board capture: detect, intrinsics, hand-eye, files, report.

Reads ``calibration/board_capture/`` (frames.jsonl, rgb/, camera.json; see
:mod:`brave6d.calibration.board_capture`) and writes what every later stage reads, through
:mod:`brave6d.core.calibration_io`:

* ``calibration/intrinsics.json``: ``camera`` plus :meth:`IntrinsicsResult.to_json` details
  (source ``charuco`` or ``factory``, RMS px, per-view errors, dropped views, 1-sigma);
* ``calibration/handeye.json``: ``tcp_T_cam`` plus :meth:`HandEyeResult.to_json` details
  (method, residuals px/mm/deg, uncertainty, every closed-form result, per-view reports);
* ``calibration/report.md`` and ``report_residuals.png`` (:func:`brave6d.calibration.report.write_report`).

Simulated captures (the spec has ``simulation`` and the capture folder has the simulator's
``sim_truth/``) also get a ``simulation_check`` key in both files and the truth columns in the
report: errors against the simulator's truth, for checking the calibration only. The truth
itself is not written; no stage reads ``simulation_check``.

Every failure is one line naming the board capture folder, the frame or the file, and the cause.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import read_png
from brave6d.core.calibration_io import read_camera_json
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, DataError
from brave6d.core.layout import CaptureLayout, FrameRecord, SceneDir
from brave6d.core.progress import progress
from brave6d.core.spec import SceneSpec
from brave6d.calibration.board import CharucoDetection, board_corner_points, detect_charuco
from brave6d.calibration.handeye import HandEyeOptions, HandEyeView, calibrate_handeye
from brave6d.calibration.handeye_result import HandEyeResult
from brave6d.calibration.intrinsics import (
    IntrinsicsResult,
    calibrate_intrinsics,
    calibrate_intrinsics_auto,
    evaluate_intrinsics,
)
from brave6d.calibration.report import ReportPaths, write_report

__all__ = [
    "BoardFrames",
    "BoardNotFoundError",
    "CalibrationRun",
    "calibrate_scene",
    "detect_board_frames",
    "load_results",
    "refined_error",
    "results_up_to_date",
    "simulation_truth",
    "summary_lines",
]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]

SIMULATION_NOTE = "errors against the simulator's truth, for checking the calibration only; no stage reads this"


class BoardNotFoundError(DataError):
    """The board capture has no frames, or the board was found in none of them."""


@dataclass(frozen=True)
class BoardFrames:
    """The board capture's frames, their ChArUco detections and the camera that took them."""

    layout: CaptureLayout
    records: list[FrameRecord]
    detections: list[CharucoDetection]
    camera: PinholeCamera

    @property
    def names(self) -> list[str]:
        """Frame names used in messages and reports (the image path inside the capture folder)."""
        return [r.rgb for r in self.records]

    @property
    def with_board(self) -> int:
        return sum(d.count > 0 for d in self.detections)


@dataclass(frozen=True)
class CalibrationRun:
    """What :func:`calibrate_scene` produced (or :func:`load_results` found)."""

    frames: int
    with_board: int
    intrinsics: IntrinsicsResult | None
    handeye: HandEyeResult | None
    truth_errors: dict[str, tuple[float, float]] | None
    report: ReportPaths | None


@contextmanager
def _located(where: Path) -> Iterator[None]:
    """Re-raise a library error as one line prefixed with ``where`` (same error type)."""
    try:
        yield
    except BraveError as exc:
        text = " ".join(str(exc).split())
        raise type(exc)(text if text.startswith(str(where)) else f"{where}: {text}") from None


def _capture_camera(layout: CaptureLayout) -> PinholeCamera:
    return read_camera_json(layout.camera_path, "intrinsics")


def detect_board_frames(scene: SceneDir, spec: SceneSpec) -> BoardFrames:
    """Detect the spec's ChArUco board in every frame of the board capture."""
    layout = scene.board_capture
    records = layout.frames()
    if not records:
        raise BoardNotFoundError(f"{layout.frames_path}: no board frames; capture them first with "
                                 f"'brave6d calibrate capture {scene.root}'")
    camera = _capture_camera(layout)
    detections = []
    for record in progress(records, total=len(records), desc="detect board", unit="frame"):
        path = layout.file(record.rgb)
        image = read_png(path, expect="rgb")
        if image.shape[:2] != (camera.height, camera.width):
            raise DataError(f"{path}: image is {image.shape[1]}x{image.shape[0]}, the capture's camera "
                            f"({layout.camera_path}) is {camera.width}x{camera.height}")
        detections.append(detect_charuco(image, spec.board))
    frames = BoardFrames(layout, records, detections, camera)
    if frames.with_board == 0:
        board = spec.board
        raise BoardNotFoundError(
            f"{layout.frames_path}: the board ({board.squares_x} x {board.squares_y} ChArUco, "
            f"{board.dictionary_label}) was detected in none of the {len(records)} board frames "
            f"(e.g. {layout.root / records[0].rgb}); check that it is in view and lit, and that field 'board' "
            "of scene.yaml matches the printed board")
    return frames


def simulation_truth(scene: SceneDir, spec: SceneSpec) -> Array | None:
    """The simulator's true ``tcp_T_cam``, only for a simulated board capture (for the check)."""
    if spec.simulation is None or not scene.board_capture.sim_truth_dir.is_dir():
        return None
    return spec.simulation.true_tcp_T_camera.matrix()


def _true_camera(spec: SceneSpec) -> PinholeCamera:
    cam = spec.camera.pinhole()
    lens = spec.simulation.effects.lens_distortion if spec.simulation is not None else None
    return cam if lens is None else PinholeCamera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                                                  tuple(lens.dist))


def _intrinsics_check(result: IntrinsicsResult, truth: PinholeCamera) -> dict[str, Any]:
    K = result.K
    return {"note": SIMULATION_NOTE, "fx_error_px": K[0, 0] - truth.fx, "fy_error_px": K[1, 1] - truth.fy,
            "cx_error_px": K[0, 2] - truth.cx, "cy_error_px": K[1, 2] - truth.cy}


def calibrate_scene_intrinsics(scene: SceneDir, spec: SceneSpec, frames: BoardFrames, factory: bool = False,
                               distortion: str = "auto") -> IntrinsicsResult:
    """Calibrate (or, ``factory``, only evaluate the capture camera's own) intrinsics; write the file.

    ``distortion``: a model of :data:`~brave6d.calibration.intrinsics.DISTORTION_MODELS` or ``"auto"``
    (:func:`~brave6d.calibration.intrinsics.calibrate_intrinsics_auto`: tangential terms only when significant).
    """
    obj = board_corner_points(spec.board)
    size = (frames.camera.width, frames.camera.height)
    with _located(frames.layout.root):
        if factory:
            result = evaluate_intrinsics(frames.detections, obj, size, frames.camera.K, frames.camera.dist_array,
                                         names=frames.names)
        elif distortion == "auto":
            result = calibrate_intrinsics_auto(frames.detections, obj, size, names=frames.names)
        else:
            result = calibrate_intrinsics(frames.detections, obj, size, distortion=distortion, names=frames.names)
    extra: dict[str, Any] = {}
    if simulation_truth(scene, spec) is not None:
        extra["simulation_check"] = _intrinsics_check(result, _true_camera(spec))
    result.save(scene.intrinsics_path, **extra)
    return result


def _load_intrinsics(scene: SceneDir) -> IntrinsicsResult:
    if not scene.intrinsics_path.is_file():
        raise DataError(f"{scene.intrinsics_path}: file not found; run 'brave6d calibrate intrinsics "
                        f"{scene.root}' first")
    return IntrinsicsResult.load(scene.intrinsics_path)


def calibrate_scene_handeye(scene: SceneDir, spec: SceneSpec, frames: BoardFrames,
                            intrinsics: IntrinsicsResult, options: HandEyeOptions | None = None) -> HandEyeResult:
    """Hand-eye calibration from the frames' robot poses and detections; write ``handeye.json``.
    The intrinsics' uncertainty is propagated with its correlations when their covariance is known."""
    views = [HandEyeView.from_detection(r.base_T_tcp_matrix, d, r.rgb)
             for r, d in zip(frames.records, frames.detections, strict=True)]
    with _located(frames.layout.root):
        result = calibrate_handeye(views, board_corner_points(spec.board), intrinsics.K, intrinsics.dist, options,
                                   intrinsics_std=intrinsics.std or None, intrinsics_cov=intrinsics.covariance)
    details: dict[str, Any] = {"intrinsics_source": intrinsics.source}
    truth = simulation_truth(scene, spec)
    if truth is not None:
        details["simulation_check"] = {
            "note": SIMULATION_NOTE,
            "errors": {m: {"translation_mm": e[0], "rotation_deg": e[1]}
                       for m, e in result.errors_against(truth).items()},
        }
    result.save(scene.handeye_path, **details)
    return result


def calibrate_scene(scene: SceneDir, spec: SceneSpec, *, intrinsics: bool = True, handeye: bool = True,
                    factory_intrinsics: bool = False, distortion: str = "auto",
                    options: HandEyeOptions | None = None) -> CalibrationRun:
    """Detect the board, then calibrate the intrinsics and/or the hand-eye transform, write the
    files and the report. ``handeye`` alone uses the intrinsics already in ``intrinsics.json``;
    ``options``: the hand-eye settings (acceptance limits)."""
    frames = detect_board_frames(scene, spec)
    intr = (calibrate_scene_intrinsics(scene, spec, frames, factory_intrinsics, distortion) if intrinsics
            else _load_intrinsics(scene))
    he = calibrate_scene_handeye(scene, spec, frames, intr, options) if handeye else None
    if he is None and scene.handeye_path.is_file():
        log.warning("%s was made with the previous intrinsics; run 'brave6d calibrate handeye' again",
                    scene.handeye_path)
    truth = simulation_truth(scene, spec)
    report = write_report(scene.calibration_dir, he, intr, truth_tcp_T_cam=truth)
    errors = he.errors_against(truth) if he is not None and truth is not None else None
    return CalibrationRun(len(frames.records), frames.with_board, intr, he, errors, report)


def results_up_to_date(scene: SceneDir) -> bool:
    """True when both result files exist and are newer than the board frames (nothing to redo)."""
    paths = (scene.board_capture.frames_path, scene.intrinsics_path, scene.handeye_path)
    if not all(p.is_file() for p in paths):
        return False
    frames_t, intr_t, he_t = (p.stat().st_mtime for p in paths)
    return frames_t <= intr_t <= he_t


def load_results(scene: SceneDir, spec: SceneSpec) -> CalibrationRun:
    """The results already in ``calibration/`` (for a stage that reuses them)."""
    intr = IntrinsicsResult.load(scene.intrinsics_path)
    he = HandEyeResult.load(scene.handeye_path)
    truth = simulation_truth(scene, spec)
    seen = sum(v.n_corners > 0 for v in intr.views)
    return CalibrationRun(len(intr.views), seen, intr, he, he.errors_against(truth) if truth is not None else None, None)


def summary_lines(run: CalibrationRun) -> list[str]:
    """A short human summary: RMS px, hand-eye residuals and uncertainty, error vs truth."""
    lines = [f"board frames: {run.frames}, board detected in {run.with_board}"]
    intr = run.intrinsics
    if intr is not None:
        used = sum(v.used for v in intr.views)
        lines.append(f"intrinsics ({intr.source}): RMS {intr.rms_px:.3f} px over {used} views; "
                     f"fx {intr.K[0, 0]:.2f} fy {intr.K[1, 1]:.2f} cx {intr.K[0, 2]:.2f} cy {intr.K[1, 2]:.2f} px")
    he = run.handeye
    if he is not None:
        r = he.residuals
        lines.append(f"hand-eye ({he.method}): reprojection RMS {r.reprojection_rms_px:.3f} px "
                     f"({r.reprojection_rms_mm:.3f} mm), AX=XB {r.axxb_rotation_rms_deg:.4f} deg / "
                     f"{r.axxb_translation_rms_mm:.3f} mm, {r.n_views} views")
        if he.uncertainty is not None:
            u = he.uncertainty
            lines.append(f"hand-eye 1-sigma: {u.translation_sigma_norm_mm:.3f} mm, {u.rotation_sigma_norm_deg:.4f} deg")
        lines += [f"warning: {w}" for w in he.warnings[:5]]
    if run.truth_errors:
        parts = [f"{m} {mm:.3f} mm / {deg:.4f} deg" for m, (mm, deg) in run.truth_errors.items()]
        lines.append("error vs simulator truth: " + "; ".join(parts))
    if run.report is not None:
        lines.append(f"report: {run.report.markdown}")
    return lines


def refined_error(run: CalibrationRun) -> tuple[float, float]:
    """(mm, deg) of the final result against the truth, NaN when there is no truth."""
    return (run.truth_errors or {}).get("refined", (math.nan, math.nan))

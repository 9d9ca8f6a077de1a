"""Calibrate from any folder: images of a ChArUco board plus robot poses from files.

``brave6d calibrate folder IMAGES --poses POSES`` runs :func:`calibrate_folder` and
:func:`write_folder_results`:

1. pair each image with its robot pose (:mod:`brave6d.calibration.pairing`,
   :mod:`brave6d.calibration.pose_files`);
2. read the images (grey; OpenCV applies a JPEG's EXIF orientation, as a viewer shows it; every
   image must have the size of the first) and detect the board (:func:`detect_charuco`);
3. intrinsics: calibrated from these views (:func:`calibrate_intrinsics_auto` or a distortion
   model) unless given (a camera JSON, then only measured); their full covariance is kept;
4. hand-eye: eye-in-hand (camera on the tool, ``tcp_T_cam``) or eye-to-hand (static camera,
   board on the tool, ``base_T_cam``: :func:`calibrate_eye_to_hand`). Intrinsics calibrated here are
   refined jointly with the hand-eye transform by default: the robot's motions constrain them as
   well, which makes a real 16-view eye-to-hand set's 1-sigma 0.9 mm instead of 2.4 mm with them
   held (``benchmarks/handeye_folder.py``); given intrinsics are held. Before solving, the
   other set-up is tried in closed form: when it explains the motions far better, the run stops
   and says so (the classic mistake of a static camera calibrated eye-in-hand);
5. files (:func:`write_folder_results`): ``intrinsics.json``, ``handeye.json`` and ``report.md``
   in the output folder, written atomically.

A result whose 1-sigma exceeds the limits raises
:class:`~brave6d.calibration.refusal.HandEyeRefusedError` naming the dominant cause.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError, DegenerateGeometryError
from brave6d.core.png_check import check_image_header, png_problem
from brave6d.core.progress import progress
from brave6d.core.spec import BoardSpec
from brave6d.core.transforms import invert, matrix_to_rpy_deg
from brave6d.calibration.board import CharucoDetection, board_corner_points, detect_charuco
from brave6d.calibration.closed_form import solve_closed_form
from brave6d.calibration.conditioning import ConditioningThresholds
from brave6d.calibration.eye_to_hand import EyeToHandResult, calibrate_eye_to_hand
from brave6d.calibration.handeye import HandEyeOptions, HandEyeView, calibrate_handeye, estimate_board_pose
from brave6d.calibration.handeye_result import HandEyeResult
from brave6d.calibration.intrinsics import (
    IntrinsicsResult,
    calibrate_intrinsics,
    calibrate_intrinsics_auto,
    evaluate_intrinsics,
)
from brave6d.calibration.pairing import PosedImages
from brave6d.calibration.refine import axxb_residuals
from brave6d.calibration.report import ReportPaths, write_report

__all__ = [
    "SETUP_MISMATCH_RATIO",
    "FolderCalibration",
    "calibrate_folder",
    "detect_folder",
    "folder_summary_lines",
    "read_calibration_image",
    "write_folder_results",
]

Array = NDArray[np.float64]
#: The other set-up must explain the motions this many times better (AX = XB rotation RMS) to stop a run.
SETUP_MISMATCH_RATIO = 5.0
_SETUP_MISMATCH_MIN_DEG = 0.5


@dataclass(frozen=True)
class FolderCalibration:
    """What :func:`calibrate_folder` produced: the paired inputs, the detections, the intrinsics
    (with the jointly refined K and dist when they were refined) and the hand-eye result."""

    inputs: PosedImages
    board: BoardSpec
    detections: tuple[CharucoDetection, ...]
    image_size: tuple[int, int]
    intrinsics: IntrinsicsResult
    handeye: HandEyeResult | EyeToHandResult

    @property
    def setup(self) -> str:
        return "eye-to-hand" if isinstance(self.handeye, EyeToHandResult) else "eye-in-hand"

    @property
    def solution(self) -> HandEyeResult:
        """The hand-eye solution (for eye-to-hand, of the inverted problem; see its module)."""
        return self.handeye.solution if isinstance(self.handeye, EyeToHandResult) else self.handeye


def read_calibration_image(path: Path, size: tuple[int, int] | None = None) -> NDArray[np.uint8]:
    """An 8-bit grey image (any format OpenCV reads; EXIF orientation applied); ``size``
    (width, height) when all images must match. Errors name the file."""
    if path.suffix.lower() == ".png":
        problem = png_problem(path, "any", check="header")
        if problem is not None:
            raise DataError(f"{path}: {problem}")
    check_image_header(path)  # any format: the pixel limit from the header, before decoding
    try:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    except cv2.error:
        image = None
    if image is None or image.size == 0:
        raise DataError(f"{path}: cannot be decoded as an image")
    if size is not None and (image.shape[1], image.shape[0]) != size:
        raise DataError(f"{path}: image is {image.shape[1]}x{image.shape[0]}, the first image is {size[0]}x{size[1]}; "
                        "calibrate one camera at one resolution")
    return image


def detect_folder(inputs: PosedImages, board: BoardSpec) -> tuple[list[CharucoDetection], tuple[int, int]]:
    """The board's detection in every image and the image size; raises when it is found in none."""
    detections: list[CharucoDetection] = []
    size: tuple[int, int] | None = None
    for path in progress(inputs.images, total=len(inputs.images), desc="detect board", unit="image"):
        image = read_calibration_image(path, size)
        size = (image.shape[1], image.shape[0])
        detections.append(detect_charuco(image, board))
    assert size is not None
    if not any(d.count for d in detections):
        raise DataError(
            f"{inputs.images[0].parent}: the board ({board.squares_x} x {board.squares_y} ChArUco squares, "
            f"{board.square_length_m * 1000:g} mm squares, {board.marker_length_m * 1000:g} mm markers, "
            f"{board.dictionary_label}) was detected in none of the {len(inputs.images)} images "
            f"(e.g. {inputs.images[0].name}); check --squares-x/--squares-y (squares, not inner corners), "
            "--dictionary (or --dictionary-file) and --legacy-pattern")
    return detections, size


def _intrinsics(detections: Sequence[CharucoDetection], obj: Array, size: tuple[int, int], names: list[str],
                camera: PinholeCamera | None, distortion: str) -> IntrinsicsResult:
    if camera is not None:
        if (camera.width, camera.height) != size:
            raise DataError(f"the given intrinsics are for {camera.width}x{camera.height} images, these are "
                            f"{size[0]}x{size[1]}")
        return evaluate_intrinsics(detections, obj, size, camera.K, camera.dist_array, names=names)
    if distortion == "auto":
        return calibrate_intrinsics_auto(detections, obj, size, names=names)
    return calibrate_intrinsics(detections, obj, size, distortion=distortion, names=names)


def _axxb_rotation_rms(views: Sequence[HandEyeView], obj: Array, K: Array, dist: Array) -> float | None:
    """AX = XB rotation RMS (deg) of the closed-form (Park) answer for these views, None when it
    cannot be computed (too few usable views, degenerate motions)."""
    G, C = [], []
    for v in views:
        if len(v.corner_ids) < 6:
            continue
        pnp = estimate_board_pose(v.corner_ids, v.corners_px, obj, K, dist)
        if pnp is not None:
            G.append(v.base_T_tcp)
            C.append(pnp[0])
    try:
        X = solve_closed_form(G, C, "park", thresholds=ConditioningThresholds.relaxed())
    except (DegenerateGeometryError, ValueError, np.linalg.LinAlgError):
        return None
    rot, _ = axxb_residuals(G, C, X)
    return float(np.sqrt(np.mean(rot**2))) if len(rot) else None


def check_setup(views: Sequence[HandEyeView], obj: Array, K: Array, dist: Array, eye_to_hand: bool) -> None:
    """Raise when the other set-up explains the robot and camera motions far better (see the
    module docstring); ``views`` carry the robot poses as reported."""
    flipped = [replace(v, base_T_tcp=invert(v.base_T_tcp)) for v in views]
    as_in_hand, as_to_hand = _axxb_rotation_rms(views, obj, K, dist), _axxb_rotation_rms(flipped, obj, K, dist)
    if as_in_hand is None or as_to_hand is None:
        return
    chosen, other = (as_to_hand, as_in_hand) if eye_to_hand else (as_in_hand, as_to_hand)
    if chosen > _SETUP_MISMATCH_MIN_DEG and chosen > SETUP_MISMATCH_RATIO * max(other, 1e-9):
        now, then, advice = ("eye-to-hand", "eye-in-hand", "the camera moves with the tool: calibrate without "
                             "--eye-to-hand") if eye_to_hand else (
            "eye-in-hand", "eye-to-hand", "a static camera looking at a board on the tool: calibrate with --eye-to-hand")
        raise DataError(f"the robot and camera motions do not fit {now} (AX = XB rotation RMS {chosen:.2f} deg) but "
                        f"fit {then} ({other:.2f} deg): {advice}")


def calibrate_folder(
    inputs: PosedImages,
    board: BoardSpec,
    *,
    eye_to_hand: bool = False,
    camera: PinholeCamera | None = None,
    distortion: str = "auto",
    refine_intrinsics: bool | None = None,
    options: HandEyeOptions | None = None,
) -> FolderCalibration:
    """Detect, calibrate the intrinsics (unless ``camera`` gives them) and the hand-eye transform
    (see the module docstring). ``refine_intrinsics``: None = refine them jointly when they were
    calibrated here. Raises :class:`~brave6d.core.errors.BraveError` naming the cause."""
    detections, size = detect_folder(inputs, board)
    obj = board_corner_points(board)
    names = inputs.names
    intr = _intrinsics(detections, obj, size, names, camera, distortion)
    refine = (camera is None) if refine_intrinsics is None else refine_intrinsics
    opts = options or HandEyeOptions()
    if refine:
        free = intr.covariance.names if intr.covariance is not None else tuple(
            n for n, s in intr.std.items() if s > 0) or ("fx", "fy", "cx", "cy")
        opts = replace(opts, refine_intrinsics=tuple(free))
    views = [HandEyeView.from_detection(G, d, n) for G, d, n in zip(inputs.poses, detections, names, strict=True)]
    check_setup(views, obj, intr.K, intr.dist, eye_to_hand)
    held = {} if refine else {"intrinsics_std": intr.std or None, "intrinsics_cov": intr.covariance}
    solve = calibrate_eye_to_hand if eye_to_hand else calibrate_handeye
    result = solve(views, obj, intr.K, intr.dist, opts, **held)
    solution = result.solution if isinstance(result, EyeToHandResult) else result
    if refine:
        std = solution.intrinsics_std or {}
        note = ("K and dist refined jointly with the hand-eye transform (robot poses); 1-sigma from that solve: "
                + ", ".join(f"{k} {v:.4g}" for k, v in std.items()) + "; 'std' and 'covariance' are the board views' alone")
        intr = replace(intr, K=solution.K, dist=solution.dist, notes=(*intr.notes, note))
    return FolderCalibration(inputs, board, tuple(detections), size, intr, result)


def write_folder_results(out_dir: Path | str, run: FolderCalibration) -> dict[str, Path]:
    """Write ``intrinsics.json``, ``handeye.json`` (``tcp_T_cam``, or for eye-to-hand ``base_T_cam``),
    ``report.md`` and ``report_residuals.png`` into ``out_dir``; returns their paths."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    sources: dict[str, Any] = {
        "images": str(run.inputs.images[0].parent), "poses": str(run.inputs.source), "matching": run.inputs.matching,
        "board": run.board.model_dump(mode="json", exclude={"pose"}), "setup": run.setup,
    }
    files = {"intrinsics": run.intrinsics.save(out / "intrinsics.json", inputs=sources),
             "handeye": run.handeye.save(out / "handeye.json", inputs=sources)}
    report: ReportPaths = write_report(out, run.solution, run.intrinsics, setup=run.setup)
    files["report"] = report.markdown
    return files


def folder_summary_lines(run: FolderCalibration) -> list[str]:
    """A short human summary of a folder calibration."""
    intr, he = run.intrinsics, run.solution
    seen = sum(d.count > 0 for d in run.detections)
    name = "base_T_cam" if run.setup == "eye-to-hand" else "tcp_T_cam"
    X = he.tcp_T_cam
    rpy = matrix_to_rpy_deg(X[:3, :3])
    lines = [run.inputs.description,
             f"board detected in {seen} of {len(run.detections)} images ({run.image_size[0]}x{run.image_size[1]})",
             f"intrinsics ({intr.source}, {intr.distortion_model}): RMS {intr.rms_px:.3f} px; fx {intr.K[0, 0]:.2f} "
             f"fy {intr.K[1, 1]:.2f} cx {intr.K[0, 2]:.2f} cy {intr.K[1, 2]:.2f} px"]
    r = he.residuals
    lines.append(f"{run.setup} {name}: translation {np.round(1000.0 * X[:3, 3], 2).tolist()} mm, rotation (rpy) "
                 f"{np.round(rpy, 3).tolist()} deg; reprojection RMS {r.reprojection_rms_px:.3f} px over {r.n_views} views")
    if he.uncertainty is not None:
        u = he.uncertainty
        intr_mm = 1000.0 * math.sqrt(max(float(np.trace(u.covariance_intrinsics[3:, 3:])), 0.0))
        lines.append(f"1-sigma: {u.translation_sigma_norm_mm:.3f} mm / {u.rotation_sigma_norm_deg:.4f} deg "
                     f"(intrinsics' share of the translation: {intr_mm:.3f} mm)")
    lines += [f"warning: {w}" for w in he.warnings[:5]]
    return lines

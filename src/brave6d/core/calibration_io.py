"""Read and write the calibration results every later stage uses.

``calibration/intrinsics.json`` holds ``{"camera": PinholeCamera.to_json(), ...}`` and
``calibration/handeye.json`` holds ``{"tcp_T_cam": 4x4, ...}`` (a camera on the tool), or, for a
static camera calibrated eye-to-hand, ``{"setup": "eye-to-hand", "base_T_cam": 4x4, ...}`` and no
``tcp_T_cam``; other keys (residuals, method, uncertainty) are calibration's own. Stages read only through these functions, so they depend on
the kernel, not on calibration's internals, and never on the simulator's truth.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.core.camera import CameraError, PinholeCamera
from brave6d.core.errors import DataError, NonRigidTransformError
from brave6d.core.layout import FrameRecord, SceneDir
from brave6d.core.transforms import check_rigid


def write_intrinsics(scene: SceneDir, camera: PinholeCamera, **details: Any) -> Path:
    """Write ``calibration/intrinsics.json`` (``details``: RMS, per-view errors, method, ...)."""
    return write_intrinsics_file(scene.intrinsics_path, camera, **details)


def write_intrinsics_file(path: Path | str, camera: PinholeCamera, **details: Any) -> Path:
    """The intrinsics file's one writer: ``{"camera": PinholeCamera.to_json(), **details}``, atomically."""
    return atomic_write_json(path, {"camera": camera.to_json(), **details})


def read_camera_json(path: Path, key: str) -> PinholeCamera:
    """The :class:`PinholeCamera` stored under ``key`` of the JSON file ``path``; errors name both.

    e.g. ``calibration/intrinsics.json: field 'camera.K[0][2]': must be finite, got nan``.
    """
    data = read_json(path)
    if not isinstance(data, dict) or key not in data:
        raise DataError(f"{path}: field '{key}' is missing")
    try:
        return PinholeCamera.from_json(data[key])
    except CameraError as exc:
        raise DataError(f"{path}: field '{'.'.join(filter(None, (key, exc.field)))}': {exc.problem}") from None


def read_intrinsics(scene: SceneDir) -> PinholeCamera:
    """The calibrated intrinsics (with distortion); errors name the file."""
    return read_camera_json(scene.intrinsics_path, "camera")


def write_handeye(scene: SceneDir, tcp_T_cam: NDArray[np.float64], **details: Any) -> Path:
    """Write ``calibration/handeye.json`` (``details``: method, residuals, uncertainty, ...)."""
    return write_handeye_file(scene.handeye_path, tcp_T_cam, **details)


def write_handeye_file(path: Path | str, tcp_T_cam: NDArray[np.float64], **details: Any) -> Path:
    """The hand-eye file's one writer: ``{"tcp_T_cam": 4x4 (checked rigid), **details}``, atomically."""
    T = check_rigid(tcp_T_cam, "tcp_T_cam")
    return atomic_write_json(path, {"tcp_T_cam": T.tolist(), **details})


def write_eye_to_hand_file(path: Path | str, base_T_cam: NDArray[np.float64], **details: Any) -> Path:
    """The hand-eye file of a static camera: ``{"setup": "eye-to-hand", "base_T_cam": 4x4 (checked
    rigid), **details}``, atomically."""
    T = check_rigid(base_T_cam, "base_T_cam")
    return atomic_write_json(path, {**details, "setup": "eye-to-hand", "base_T_cam": T.tolist()})


def read_handeye(scene: SceneDir) -> NDArray[np.float64]:
    """The calibrated ``tcp_T_cam``; errors name the file (and refuse a static camera's file)."""
    data = read_json(scene.handeye_path)
    if isinstance(data, dict) and data.get("setup") == "eye-to-hand":
        raise DataError(f"{scene.handeye_path}: an eye-to-hand calibration (a static camera, field 'base_T_cam'); "
                        "scenes are captured with the camera on the tool: calibrate eye-in-hand (tcp_T_cam)")
    if "tcp_T_cam" not in data:
        raise DataError(f"{scene.handeye_path}: field 'tcp_T_cam' is missing")
    try:
        return check_rigid(data["tcp_T_cam"], f"{scene.handeye_path}: tcp_T_cam")
    except NonRigidTransformError as exc:
        raise DataError(str(exc)) from None


def camera_poses(scene: SceneDir, records: list[FrameRecord] | None = None) -> list[tuple[FrameRecord, NDArray[np.float64]]]:
    """``(record, base_T_cam)`` for every captured frame: ``base_T_tcp @ tcp_T_cam`` (calibrated)."""
    tcp_T_cam = read_handeye(scene)
    frames = scene.frames() if records is None else records
    return [(r, r.base_T_tcp_matrix @ tcp_T_cam) for r in frames]

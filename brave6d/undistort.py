"""Undistort the captured frames once, with the calibrated intrinsics, for every later stage.

3DGS training, BOP export and the render server all assume a pinhole camera. The capture keeps
the raw (distorted) images; this module writes ``<scene>/undistorted/`` with RGB (bilinear) and
depth (nearest, so depths are never blended across edges) remapped to the same K without
distortion. It is redone only when the intrinsics or the frames change (a stamp records both).
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2

from brave6d.atomic import atomic_write_json, read_json, read_png, write_png
from brave6d.calibration_io import read_intrinsics
from brave6d.camera import PinholeCamera
from brave6d.layout import FrameRecord, SceneDir
from brave6d.progress import progress

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class UndistortedFrames:
    """The undistorted copy of a capture: pinhole camera and per-frame image paths."""

    root: Path
    camera: PinholeCamera
    records: list[FrameRecord]

    def rgb_path(self, record: FrameRecord) -> Path:
        return self.root / "rgb" / Path(record.rgb).name

    def depth_path(self, record: FrameRecord) -> Path | None:
        return self.root / "depth" / Path(record.depth).name if record.depth else None


def _stamp(camera: PinholeCamera, records: list[FrameRecord]) -> str:
    payload = json.dumps({"camera": camera.to_json(), "frames": [(r.index, r.rgb, r.depth) for r in records]})
    return hashlib.sha256(payload.encode()).hexdigest()


def ensure_undistorted(scene: SceneDir) -> UndistortedFrames:
    """Write (or reuse) ``<scene>/undistorted/`` for all captured frames."""
    raw = read_intrinsics(scene)
    records = scene.frames()
    pinhole = raw.without_distortion()
    root = scene.root / "undistorted"
    stamp_path = root / "stamp.json"
    stamp = _stamp(raw, records)
    result = UndistortedFrames(root, pinhole, records)
    if stamp_path.exists() and read_json(stamp_path).get("stamp") == stamp:
        return result
    log.info("undistorting %d frames with the calibrated intrinsics into %s", len(records), root)
    size, size_of = (raw.width, raw.height), f"the camera in {scene.intrinsics_path}"
    for record in progress(records, total=len(records), desc="undistort", unit="frame"):
        rgb = read_png(scene.capture_dir / record.rgb, "rgb", size, size_of)
        write_png(result.rgb_path(record), raw.undistort_image(rgb, cv2.INTER_LINEAR))
        depth_path = result.depth_path(record)
        if depth_path is not None:
            depth = read_png(scene.capture_dir / str(record.depth), "depth", size, size_of)
            write_png(depth_path, raw.undistort_image(depth, cv2.INTER_NEAREST))
    atomic_write_json(root / "camera.json", {"intrinsics": pinhole.to_json(), "source": str(scene.intrinsics_path)})
    atomic_write_json(stamp_path, {"stamp": stamp})
    return result

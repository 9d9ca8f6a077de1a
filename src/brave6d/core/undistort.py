"""Undistort the captured frames once, with the calibrated intrinsics, for every later stage.

3DGS training, BOP export and the render server all assume a pinhole camera. The capture keeps
the raw (distorted) images; this module writes ``<scene>/undistorted/`` with RGB (bilinear) and
depth (nearest, so depths are never blended across edges) remapped to the same K without
distortion.

The cache is keyed on content: ``undistorted/index.json`` records, for every undistorted file,
the SHA-256 of the raw file it was made from and a hash of the intrinsics. Each call hashes the
raw files (cheap next to undistorting them) and redoes exactly the files whose raw content or
intrinsics changed, or that are missing; so a ``capture run --force`` that rewrites
``rgb/000003.png`` with new content redoes that frame only, and an unchanged frame is never
rewritten. Files of frames no longer in the capture are removed.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from brave6d.core.atomic import atomic_write_json, file_sha256, read_json, read_png, write_png
from brave6d.core.calibration_io import read_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.layout import FrameRecord, SceneDir
from brave6d.core.progress import progress

log = logging.getLogger(__name__)

INDEX_VERSION = 2
_INDEX = "index.json"
_OLD_STAMP = "stamp.json"  # version 1: one hash of the intrinsics and the file names


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


@dataclass(frozen=True)
class _Job:
    """One undistorted file to keep up to date: its raw source and how to remap it."""

    record: FrameRecord
    source: Path
    target: Path
    kind: str  # "rgb" (bilinear) or "depth" (nearest)


def camera_key(camera: PinholeCamera) -> str:
    """Hash of the intrinsics the undistortion used (a change redoes every file)."""
    return hashlib.sha256(json.dumps(camera.to_json(), sort_keys=True).encode()).hexdigest()


def _jobs(scene: SceneDir, frames: UndistortedFrames) -> list[_Job]:
    """Every undistorted file the capture calls for, RGB and depth, in frame order."""
    jobs = []
    for record in frames.records:
        jobs.append(_Job(record, scene.capture.file(record.rgb), frames.rgb_path(record), "rgb"))
        depth_target = frames.depth_path(record)
        if depth_target is not None:
            jobs.append(_Job(record, scene.capture.file(str(record.depth)), depth_target, "depth"))
    return jobs


def _read_index(root: Path, camera: str) -> dict[str, str]:
    """``{relative undistorted path: raw SHA-256}`` made with ``camera``; empty when stale or unreadable."""
    path = root / _INDEX
    if not path.is_file():
        return {}
    try:
        saved: Any = read_json(path)
    except DataError as exc:
        log.warning("%s; undistorting every frame again", exc)
        return {}
    if not isinstance(saved, dict) or saved.get("version") != INDEX_VERSION or saved.get("camera") != camera:
        return {}
    files = saved.get("files")
    return {str(k): str(v) for k, v in files.items()} if isinstance(files, dict) else {}


def _write_index(root: Path, camera: str, files: dict[str, str]) -> None:
    atomic_write_json(root / _INDEX, {"version": INDEX_VERSION, "camera": camera, "files": files})


def _undistort_file(raw: PinholeCamera, job: _Job, size_of: str) -> None:
    """Write ``job.target`` from its raw source; errors name the frame and the file (``size_of``: where
    the expected image size comes from)."""
    try:
        image = read_png(job.source, job.kind, (raw.width, raw.height), size_of)
    except DataError as exc:
        raise DataError(f"frame {job.record.index} ({job.record.view_id}): {exc}") from None
    interpolation = cv2.INTER_LINEAR if job.kind == "rgb" else cv2.INTER_NEAREST
    write_png(job.target, raw.undistort_image(image, interpolation))


def _remove_strays(root: Path, keep: set[str]) -> None:
    """Delete undistorted files no frame calls for any more (this folder is a cache)."""
    for folder in ("rgb", "depth"):
        for path in sorted((root / folder).glob("*")) if (root / folder).is_dir() else []:
            if path.is_file() and f"{folder}/{path.name}" not in keep:
                path.unlink(missing_ok=True)


def ensure_undistorted(scene: SceneDir) -> UndistortedFrames:
    """Write (or reuse) ``<scene>/undistorted/`` for all captured frames; see the module docstring.

    A missing or corrupt raw frame raises :class:`DataError` naming the frame and the file; the
    files undistorted before it are recorded, so the next call does not redo them.
    """
    raw = read_intrinsics(scene)
    records = scene.frames()
    root = scene.undistorted_dir
    result = UndistortedFrames(root, raw.without_distortion(), records)
    camera = camera_key(raw)
    index = _read_index(root, camera)
    jobs = _jobs(scene, result)
    done: dict[str, str] = {}
    todo: list[tuple[_Job, str]] = []
    for job in jobs:
        digest = file_sha256(job.source) if job.source.is_file() else ""
        rel = f"{job.target.parent.name}/{job.target.name}"
        if digest and index.get(rel) == digest and job.target.is_file():
            done[rel] = digest
        else:
            todo.append((job, digest))
    if todo or set(index) != set(done):
        try:
            _redo(raw, root, todo, done, f"the camera in {scene.intrinsics_path}")
        finally:
            _write_index(root, camera, done)
    if todo or not (root / "camera.json").is_file():
        atomic_write_json(root / "camera.json", {"intrinsics": result.camera.to_json(),
                                                 "source": str(scene.intrinsics_path)})
    _remove_strays(root, {f"{j.target.parent.name}/{j.target.name}" for j in jobs})
    (root / _OLD_STAMP).unlink(missing_ok=True)
    return result


def _redo(raw: PinholeCamera, root: Path, todo: list[tuple[_Job, str]], done: dict[str, str], size_of: str) -> None:
    """Undistort the out-of-date files, adding each to ``done`` once it is written."""
    frames = len({job.record.index for job, _ in todo})
    if todo:
        log.info("undistorting %d file(s) of %d frame(s) with the calibrated intrinsics into %s",
                 len(todo), frames, root)
    for job, digest in progress(todo, total=len(todo), desc="undistort", unit="file", disable=len(todo) < 2):
        job.target.unlink(missing_ok=True)  # never leave a stale copy behind a failure
        _undistort_file(raw, job, size_of)
        done[f"{job.target.parent.name}/{job.target.name}"] = digest or file_sha256(job.source)

"""``import_capture``: a capture made elsewhere -> a scene directory the pipeline uses as its own.

What the scene directory gets (docs/GUIDE.md, "Import a capture made elsewhere"):

- ``capture/rgb/NNNNNN.png`` and ``capture/frames.jsonl``: one frame record per imported image,
  ``base_T_tcp`` = the camera's pose in the new world (metres, +z up), ``view_id`` = the source
  image's name without extension (made folder-safe), the source name in ``source_image``, no depth,
  joints zero (no robot), one distance level (the distance to the scene's centre);
- ``calibration/handeye.json``: the identity (the "robot pose" is the camera pose);
- ``calibration/intrinsics.json``: the source's camera as OpenCV's K + distortion when one shared
  radial-tangential camera describes every frame (the images are then copied as they are and
  undistorted by the pipeline like a captured scene's), else the pinhole camera every frame was
  resampled into at import (fisheye lenses, frames with different intrinsics);
- ``scene.yaml``: a spec with the capture's geometry (target = the origin, the camera distances and
  elevations, a workspace around the cameras and points), no objects; ``annotation/objects.json``
  with no objects (``brave6d annotate`` adds them), so ``export`` and ``serve`` work;
- ``capture/import.json`` and ``capture/imported_points.ply`` (:mod:`.scene_files`).

The cameras must see the scene (:mod:`brave6d.training.pose_check`), checked before anything is
written; the folder is built beside ``scene_dir`` and swapped in whole.
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import move_aside, staged_folder, write_png
from brave6d.core.calibration_io import write_handeye, write_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir, write_spec
from brave6d.core.progress import progress
from brave6d.core.spec import SceneSpec
from brave6d.core.transforms import ROTATION_TOLERANCE
from brave6d.training.importing.image_io import Resampler, read_frame_image
from brave6d.training.importing.scene_files import write_import_record, write_imported_points
from brave6d.training.importing.source import (MAX_COORDINATE, ImportedCapture, SourceCamera, SourceFrame,
                                                bounded_rows, check_pose)
from brave6d.training.importing.world import ScaleChoice, UpChoice, WorldChange, world_change
from brave6d.training.pose_check import MIN_VISIBLE_SHARE, PoseCheck, check_camera_poses

log = logging.getLogger(__name__)

FORMATS = ("auto", "colmap", "transforms")
#: Fewer sparse points than this and the pose check uses the scene's centre instead.
MIN_REFERENCE_POINTS = 10


@dataclass(frozen=True)
class ImportOptions:
    """How to import: the source's format and images folder, the world (scale, up), the checks."""

    scale: ScaleChoice | None = None  # None: ScaleChoice.default() (the source's units kept as metres)
    up: UpChoice | None = None  # None: UpChoice(None), auto (photos taken upright)
    format: str = "auto"
    images: Path | None = None  # COLMAP: the images folder (default: found beside the model)
    downscale: int = 1  # integer factor the images are resampled by (area averaging)
    name: str | None = None  # the scene's name (default: the scene folder's name, made folder-safe)
    min_visible_share: float = MIN_VISIBLE_SHARE
    pose_check: bool = True
    force: bool = False  # move an existing, non-empty scene folder aside instead of refusing


@dataclass
class ImportResult:
    """What was imported; ``record`` is what ``capture/import.json`` holds."""

    scene: SceneDir
    frames: int
    missing: list[str]
    camera: PinholeCamera
    world: WorldChange
    pose_check: PoseCheck | None
    moved_aside: Path | None
    record: dict[str, Any] = field(default_factory=dict)


def read_source(source: Path | str, fmt: str = "auto", images: Path | None = None) -> ImportedCapture:
    """Read a COLMAP model or a ``transforms.json`` (``fmt``: ``auto`` tells them apart)."""
    from brave6d.training.importing.colmap_source import read_colmap
    from brave6d.training.importing.transforms_source import read_transforms

    path = Path(source)
    if not path.exists():
        raise DataError(f"{path}: not found")
    if fmt not in FORMATS:
        raise DataError(f"unknown source format {fmt!r}; choose {', '.join(FORMATS)}")
    if fmt == "auto":
        has_json = path.suffix == ".json" or (path / "transforms.json").is_file()
        if has_json and path.is_dir() and _has_colmap_model(path):
            raise DataError(f"{path}: holds both a transforms.json and a COLMAP model; choose with --format "
                            "transforms or --format colmap")
        fmt = "transforms" if has_json else "colmap"
    if fmt == "transforms":
        if images is not None:
            raise DataError("--images is for COLMAP models; a transforms.json names its images itself")
        return read_transforms(path)
    return read_colmap(path, images)


def _has_colmap_model(path: Path) -> bool:
    from brave6d.training.importing.colmap_source import find_model

    try:
        find_model(path)
    except DataError:
        return False
    return True


def import_capture(source: Path | str, scene_dir: Path | str, options: ImportOptions) -> ImportResult:
    """Import ``source`` into ``scene_dir`` (see the module docstring); returns what was done."""
    if options.downscale < 1:
        raise DataError(f"--downscale must be a whole number >= 1, got {options.downscale}")
    scene = SceneDir(scene_dir)
    _check_target(scene, options.force)
    capture = read_source(source, options.format, options.images)
    if not capture.frames:
        shown = ", ".join(capture.missing[:8]) + (f" and {len(capture.missing) - 8} more" if len(capture.missing) > 8 else "")
        raise DataError(f"{capture.source}: no frame has an image file" + (f" (missing: {shown})" if shown else ""))
    scale = options.scale if options.scale is not None else ScaleChoice.default()
    up = options.up if options.up is not None else UpChoice(None)
    if options.scale is None:
        log.info("no --scale or --scale-from-distance: the source's units are kept (1 m per unit; the record says "
                 "what depends on it)")
    names = [f.name for f in capture.frames]
    duplicates = sorted(n for n, c in Counter(names).items() if c > 1)
    if duplicates:
        raise DataError(f"{capture.source}: frames listed twice: {', '.join(duplicates[:8])}")
    change = world_change({f.name: f.world_T_cam for f in capture.frames}, capture.points, scale, up)
    plan = _camera_plan(capture.frames, options.downscale)
    poses = [change.pose(f.world_T_cam) for f in capture.frames]
    for frame, pose in zip(capture.frames, poses):
        check_pose(pose, f"{capture.source}: frame {frame.name!r} after the world change ({change.scale_from})",
                   "metres")
    points, colors = change.points(capture.points), capture.colors
    keep = bounded_rows(points)
    if not keep.all():
        log.warning("dropped %d sparse points beyond %g m after the world change", int((~keep).sum()), MAX_COORDINATE)
        points, colors = points[keep], colors[keep]
    check = None
    reference = _reference(capture, change, points)
    if options.pose_check and reference is not None:
        check = check_camera_poses(plan.camera, list(zip(names, poses)), reference[0], reference[1],
                                   options.min_visible_share, how_to_skip="pass --skip-pose-check to import anyway")
        log.info("%s", check.summary())
    elif options.pose_check:
        log.warning("pose check skipped: the source has no sparse points and the cameras' optical axes do not meet")
    spec = _scene_spec(_scene_name(scene, options.name), capture, plan.camera, poses, points, change)
    moved = None
    with staged_folder(scene.root) as staging:
        out = SceneDir(staging)
        exif = _write_frames(out, capture.frames, poses, plan)
        write_intrinsics(out, plan.camera, method="imported", source_cameras=[c.to_json() for c in plan.sources],
                         images=plan.how)
        write_handeye(out, np.eye(4), method="imported: a capture made elsewhere has no robot; the frame records' "
                      "base_T_tcp is the camera's pose (world_T_cam)")
        write_spec(out, spec)
        _write_empty_annotation(out, capture)
        if len(points):
            write_imported_points(out, points, colors)
        record = _record(capture, options, plan, change, check, reference, exif, len(points))
        write_import_record(out, record)
        if _has_content(scene.root):
            moved = move_aside(scene.root)
            log.warning("moved the previous %s aside to %s", scene.root, moved)
    return ImportResult(scene, len(capture.frames), list(capture.missing), plan.camera, change, check, moved, record)


# ----------------------------------------------------------------------------- checks and questions
def _has_content(folder: Path) -> bool:
    return folder.exists() and (not folder.is_dir() or any(folder.iterdir()))


def _check_target(scene: SceneDir, force: bool) -> None:
    if _has_content(scene.root) and not force:
        raise DataError(f"{scene.root}: exists and is not empty; pick a new folder, or pass --force to move it "
                        "aside (nothing is deleted)")


def _reference(capture: ImportedCapture, change: WorldChange, points: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], str] | None:
    """What the cameras must see: the sparse points, else a box the source names, else the centre."""
    if len(points) >= MIN_REFERENCE_POINTS:
        return points, f"the {len(points)} sparse points ({capture.points_from})"
    if capture.scene_box is not None:
        centre = change.points((capture.scene_box[0] + capture.scene_box[1]) / 2.0)
        return centre, "the centre of instant-ngp's unit cube (scale, offset)"
    if change.centre_from.startswith("where the cameras' optical axes meet"):
        return np.zeros((1, 3)), "the point where the cameras' optical axes meet"
    return None


# ----------------------------------------------------------------------------- cameras and images
@dataclass(frozen=True)
class CameraPlan:
    """The scene's camera and how each frame's image becomes an image of it."""

    camera: PinholeCamera  # what calibration/intrinsics.json gets (at the written size)
    full_camera: PinholeCamera  # the same before --downscale
    sources: tuple[SourceCamera, ...]
    resample: bool  # True: every image is remapped into ``camera`` (pinhole); False: copied (+ downscaled)
    downscale: int
    how: str


def _camera_plan(frames: list[SourceFrame], downscale: int) -> CameraPlan:
    """One shared OpenCV-expressible camera: copy the images; else resample into a pinhole camera."""
    distinct: list[SourceCamera] = []
    for f in frames:
        if not any(f.camera.same_as(c) for c in distinct):
            distinct.append(f.camera)
    shared = distinct[0].opencv() if len(distinct) == 1 else None
    if shared is not None:
        camera = shared if downscale == 1 else shared.scaled(*_scaled(shared, downscale))
        how = ("copied as they are (one shared camera, OpenCV's distortion model: undistorted by the pipeline)"
               + (f", resampled to 1/{downscale} (area averaging)" if downscale > 1 else ""))
        return CameraPlan(camera, shared, tuple(distinct), False, downscale, how)
    counts = Counter(next(i for i, c in enumerate(distinct) if f.camera.same_as(c)) for f in frames)
    base = distinct[counts.most_common(1)[0][0]].pinhole()
    camera = base if downscale == 1 else base.scaled(*_scaled(base, downscale))
    why = "a fisheye model" if len(distinct) == 1 else f"{len(distinct)} different cameras"
    how = (f"resampled at import ({why}) into one pinhole camera without distortion (the most common camera's "
           f"focal lengths and principal point{f', at 1/{downscale} size' if downscale > 1 else ''}; bilinear)")
    return CameraPlan(camera, base, tuple(distinct), True, downscale, how)


def _scaled(camera: PinholeCamera, downscale: int) -> tuple[int, int]:
    return max(1, round(camera.width / downscale)), max(1, round(camera.height / downscale))


def _write_frames(scene: SceneDir, frames: list[SourceFrame], poses: list[NDArray[np.float64]],
                  plan: CameraPlan) -> list[str]:
    """Write every frame's PNG and record; returns the frames whose EXIF orientation was applied."""
    resampler = Resampler(_full_size(plan)) if plan.resample else None
    frame_log = FrameLog(scene.frames_path)
    view_ids = _view_ids([f.name for f in frames])
    turned = []
    for i, (frame, pose, view_id) in enumerate(progress(list(zip(frames, poses, view_ids)), desc="import",
                                                        unit="frame")):
        img = read_frame_image(frame.image, (frame.camera.width, frame.camera.height), frame.name)
        if img.exif_turned:
            turned.append(frame.name)
        if img.note:
            log.warning("frame %s: %s", frame.name, img.note)
        rgb = img.rgb if resampler is None else resampler(img.rgb, frame.camera)
        if plan.downscale > 1:
            rgb = _area(rgb, plan.camera)
        rel = f"rgb/{i:06d}.png"
        write_png(scene.capture.file(rel), rgb)
        distance = float(np.linalg.norm(pose[:3, 3]))
        frame_log.append(FrameRecord(index=i, view_id=view_id, distance_level=0, distance_m=max(distance, 1e-6),
                                     rgb=rel, depth=None, base_T_tcp=pose.tolist(), joints=[0.0] * 6,
                                     timestamp=float(i), source_image=frame.name))
    return turned


def _full_size(plan: CameraPlan) -> PinholeCamera:
    """The scene's camera at the source's size (before ``--downscale``)."""
    return plan.full_camera


def _area(image: NDArray[np.uint8], camera: PinholeCamera) -> NDArray[np.uint8]:
    return cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_AREA)


def _view_ids(names: list[str]) -> list[str]:
    """Folder-safe, unique view ids from the source names (the file name without its extension)."""
    out, seen = [], set()
    for i, name in enumerate(names):
        stem = Path(name).stem or f"frame{i:06d}"
        base = re.sub(r"[^A-Za-z0-9_.+-]", "_", stem)[:90]
        if not re.match(r"[A-Za-z0-9_]", base):
            base = "_" + base
        view, n = base, 1
        while view in seen:
            n += 1
            view = f"{base}_{n}"
        seen.add(view)
        out.append(view)
    return out


# ----------------------------------------------------------------------------- the spec and the record
def _scene_name(scene: SceneDir, name: str | None) -> str:
    from brave6d.core.names import check_folder_name

    if name is not None:
        return check_folder_name(name, "--name")
    base = re.sub(r"[^A-Za-z0-9_.+-]", "_", scene.root.resolve().name)[:100] or "imported"
    return base if re.match(r"[A-Za-z0-9_]", base) else "_" + base[:99]


def _scene_spec(name: str, capture: ImportedCapture, camera: PinholeCamera, poses: list[NDArray[np.float64]],
                points: NDArray[np.float64], change: WorldChange) -> SceneSpec:
    """A spec with the capture's geometry and no objects (module docstring)."""
    centres = np.array([T[:3, 3] for T in poses])
    distances = np.linalg.norm(centres, axis=1)
    elevations = np.degrees(np.arcsin(np.clip(centres[:, 2] / np.maximum(distances, 1e-12), -1.0, 1.0)))
    lo_el = float(np.clip(np.floor(elevations.min()), 0.0, 89.0))
    hi_el = float(np.clip(np.ceil(elevations.max()), lo_el + 1.0, 90.0))
    extent = np.vstack([centres, np.percentile(points, [2, 98], axis=0)]) if len(points) >= MIN_REFERENCE_POINTS else centres
    lo, hi = extent.min(axis=0), extent.max(axis=0)
    pad = 0.1 * max(float(np.max(hi - lo)), 0.05)
    data = {
        "name": name,
        "description": (f"imported from a {capture.format} capture ({len(poses)} frames); scale: {change.scale_from}; "
                        f"up: {change.up_from.split(':')[0]}; see capture/import.json"),
        "capture": {"target": [0.0, 0.0, 0.0], "distances_m": [round(float(np.median(distances)), 4)],
                    "views_per_distance": min(len(poses), 10000), "min_elevation_deg": lo_el,
                    "max_elevation_deg": hi_el, "depth": False},
        "workspace": {"min": (lo - pad).tolist(), "max": (hi + pad).tolist()},
        "camera": {"model": "imported", "width": int(np.clip(camera.width, 16, 8192)),
                   "height": int(np.clip(camera.height, 16, 8192)), "fx": camera.fx, "fy": camera.fy,
                   "cx": camera.cx, "cy": camera.cy, "dist": list(camera.dist)},
    }
    return SceneSpec.model_validate(data)


def _write_empty_annotation(scene: SceneDir, capture: ImportedCapture) -> None:
    """``annotation/objects.json`` with no objects: the scene exports and serves; annotate it to add them."""
    from brave6d.annotation import Annotation, write_annotation

    write_annotation(scene, Annotation((), (), {}, source={"kind": "none", "note": (
        f"a {capture.format} capture imported by brave6d import; no objects annotated yet")}))


def _record(capture: ImportedCapture, options: ImportOptions, plan: CameraPlan, change: WorldChange,
            check: PoseCheck | None, reference: tuple[NDArray[np.float64], str] | None, exif: list[str],
            n_points: int) -> dict[str, Any]:
    return {
        "source": {"format": capture.format, "path": str(capture.source), **capture.details},
        "frames": len(capture.frames),
        "missing": list(capture.missing),
        "exif_orientation_applied": exif,
        "camera": {"images": plan.how, "downscale": plan.downscale, "sources": [c.to_json() for c in plan.sources]},
        "world": change.to_json(),
        "points": {"count": n_points, "from": capture.points_from},
        "pose_check": _check_record(check, reference, options.pose_check),
        "rotations": _rotation_record(capture.frames),
    }


def _rotation_record(frames: list[SourceFrame]) -> dict[str, Any]:
    """The largest correction the projection onto the nearest rotation made, and its frame."""
    worst = max(frames, key=lambda f: f.rotation_correction)
    return {"rule": "each rotation projected onto the nearest rotation (SVD) when max |R^T R - I| <= tolerance",
            "tolerance": ROTATION_TOLERANCE, "largest_correction": worst.rotation_correction,
            "largest_correction_frame": worst.name, "correction": "max |R_projected - R| over the entries"}


def _check_record(check: PoseCheck | None, reference: tuple[NDArray[np.float64], str] | None,
                  asked: bool) -> dict[str, Any] | str:
    if not asked:
        return "skipped (--skip-pose-check)"
    if check is None:
        return "skipped: no sparse points, no scene box, and the optical axes do not meet"
    return {"reference": check.reference, "min_share": check.min_share, "summary": check.summary(),
            "least_share": min(f.visible for f in check.frames)}

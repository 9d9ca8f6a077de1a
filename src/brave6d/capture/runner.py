"""The capture runner: drive any Robot/Camera pair through a plan and write every frame.

Each frame is written image-first, record-last: the RGB and depth PNGs are written atomically,
then one line is appended to ``frames.jsonl``. The record is the commit point, so a crash at
any moment leaves every finished frame intact and at most some orphan images, which the resumed
run simply overwrites. On Ctrl-C, a crash or a robot fault the arm is stopped first; a robot or
camera fault ends in one error line saying how many frames are kept and that ``--resume`` continues.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import atomic_write_json, depth_m_to_mm_u16, move_aside, read_json, write_png
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, DataError
from brave6d.core.layout import CaptureLayout, FrameLog, FrameRecord
from brave6d.core.progress import progress_bar
from brave6d.capture.protocols import Camera, CameraError, Frame, Robot, RobotError

log = logging.getLogger(__name__)


class CaptureExistsError(BraveError):
    """The capture folder already holds frames and neither --resume nor --force was given."""


class PlannedView(Protocol):
    """What the runner needs of one planned view (``brave6d.capture.planning`` provides it)."""

    view_id: int | str
    distance_level: int
    distance_m: float
    base_T_tcp: NDArray[np.float64]
    joints: NDArray[np.float64]


@dataclass(frozen=True)
class CaptureOptions:
    """How to run a capture."""

    settle_time_s: float = 0.2
    save_depth: bool = True
    resume: bool = False
    force: bool = False


@dataclass(frozen=True)
class CaptureSummary:
    """What a run did: frames written now, frames kept from before, wall and robot time."""

    written: int
    resumed_from: int
    total: int
    wall_seconds: float
    robot_seconds: float


def prepare_capture_folder(layout: CaptureLayout, n_planned: int, options: CaptureOptions) -> list[FrameRecord]:
    """Check what the folder holds and decide: resume, refuse, or move the old capture aside.

    Returns the records to keep. ``--force`` never deletes: the old folder is renamed to
    ``<name>.old-<timestamp>`` so no data is lost by a mistaken command.
    """
    existing = FrameLog(layout.frames_path).read() if layout.frames_path.exists() else []
    if existing and options.force:
        aside = move_aside(layout.root)
        log.warning("moved the previous capture (%d frames) to %s", len(existing), aside)
        return []
    if existing and not options.resume:
        state = "complete" if len(existing) >= n_planned else f"partial ({len(existing)} of {n_planned} frames)"
        raise CaptureExistsError(
            f"{layout.frames_path}: a {state} capture exists; pass --resume to continue it "
            f"or --force to move it aside and start again")
    return existing


def _check_camera_json(layout: CaptureLayout, intrinsics: PinholeCamera, resuming: bool,
                       info: dict | None = None) -> None:
    """Write camera.json; when resuming, the camera must be the one used so far."""
    data: dict = {"intrinsics": intrinsics.to_json()}
    if info is not None:
        data["device"] = info
    if resuming and layout.camera_path.exists():
        before = read_json(layout.camera_path).get("intrinsics")
        if before is not None and PinholeCamera.from_json(before) != intrinsics:
            raise DataError(f"{layout.camera_path}: the camera's intrinsics differ from those of the frames "
                            "captured so far; resume with the same camera or start again with --force")
        return
    atomic_write_json(layout.camera_path, data)


def run_capture(
    layout: CaptureLayout,
    views: Sequence[PlannedView],
    robot: Robot,
    camera: Camera,
    options: CaptureOptions = CaptureOptions(),
    desc: str = "capture",
) -> CaptureSummary:
    """Capture every view of ``views`` not captured yet; see the module docstring."""
    kept = prepare_capture_folder(layout, len(views), options)
    layout.root.mkdir(parents=True, exist_ok=True)
    camera_info = getattr(camera, "camera_info", None)  # real cameras: serial, locked settings, ...
    _check_camera_json(layout, camera.intrinsics, resuming=bool(kept),
                       info=camera_info() if callable(camera_info) else None)
    done_ids = {r.view_id for r in kept}
    unknown = done_ids - {str(v.view_id) for v in views}
    if unknown:
        raise DataError(f"{layout.frames_path}: frames {sorted(unknown)[:5]} are not in the plan; "
                        "the plan changed since the capture started (use --force to start again)")
    todo = [(i, v) for i, v in enumerate(views) if str(v.view_id) not in done_ids]
    frame_log = FrameLog(layout.frames_path)
    start_wall, start_robot = time.perf_counter(), robot.now()
    written = 0
    bar = progress_bar(total=len(views), desc=desc, unit="frame", initial=len(kept))
    try:
        for index, view in todo:
            record = _capture_one(layout, index, view, robot, camera, options)
            frame_log.append(record)
            written += 1
            bar.update(1)
    except (RobotError, CameraError) as exc:  # the rig faulted: one line that says what is kept
        robot.stop()
        raise type(exc)(f"{exc} (capture stopped: {len(kept) + written} of {len(views)} frames kept in "
                        f"{layout.frames_path}; run it again with --resume to continue)") from None
    except BaseException as exc:
        robot.stop()
        log.error("capture stopped after %d new frames (%d kept in %s): %s", written,
                  len(kept) + written, layout.frames_path, exc)
        raise
    finally:
        bar.close()
    return CaptureSummary(written=written, resumed_from=len(kept), total=len(kept) + written,
                          wall_seconds=time.perf_counter() - start_wall, robot_seconds=robot.now() - start_robot)


def _capture_one(layout: CaptureLayout, index: int, view: PlannedView, robot: Robot, camera: Camera,
                 options: CaptureOptions) -> FrameRecord:
    robot.move_joints(np.asarray(view.joints, dtype=np.float64))
    robot.wait_until_steady(options.settle_time_s)
    frame = camera.capture()
    base_T_tcp = robot.tcp_pose()
    joints = robot.joints()
    name = f"{index:06d}.png"
    write_png(layout.rgb_dir / name, _checked_rgb(frame, camera.intrinsics, index))
    depth_name = None
    if options.save_depth and frame.depth_m is not None:
        depth_name = f"depth/{name}"
        write_png(layout.depth_dir / name, depth_m_to_mm_u16(frame.depth_m))
    _write_sim_truth(layout, index, frame)
    return FrameRecord(
        index=index, view_id=str(view.view_id), distance_level=view.distance_level, distance_m=view.distance_m,
        rgb=f"rgb/{name}", depth=depth_name, base_T_tcp=np.asarray(base_T_tcp).tolist(),
        joints=np.asarray(joints, dtype=float).tolist(), timestamp=float(frame.timestamp),
    )


def _checked_rgb(frame: Frame, intrinsics: PinholeCamera, index: int) -> NDArray[np.uint8]:
    rgb = frame.rgb
    if rgb.dtype != np.uint8 or rgb.shape != (intrinsics.height, intrinsics.width, 3):
        raise DataError(f"frame {index}: camera returned {rgb.dtype} {rgb.shape}, expected uint8 "
                        f"({intrinsics.height}, {intrinsics.width}, 3)")
    return rgb


def _write_sim_truth(layout: CaptureLayout, index: int, frame: Frame) -> None:
    """Simulator ground truth for tests (object ids, true pose); real cameras have none."""
    ids = frame.extras.get("object_ids")
    if ids is not None:
        write_png(layout.sim_object_ids_path(index), np.asarray(ids, dtype=np.uint16))
    true_pose = frame.extras.get("world_T_cam_true")
    if true_pose is not None:
        atomic_write_json(layout.sim_pose_path(index),
                          {"world_T_cam_true": np.asarray(true_pose).tolist(),
                           "effects": list(frame.extras.get("effects", []))})


def frame_paths(layout: CaptureLayout, record: FrameRecord) -> tuple[Path, Path | None]:
    """Absolute RGB and depth paths of a record."""
    return layout.file(record.rgb), layout.file(record.depth) if record.depth else None

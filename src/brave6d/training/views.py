"""Training data: undistorted frames, calibrated camera poses and the holdout split.

Images come from :func:`brave6d.core.undistort.ensure_undistorted` (undistorted once, with the
calibrated intrinsics) and poses from :func:`brave6d.core.calibration_io.camera_poses` (robot pose
times the *calibrated* hand-eye transform, never the simulator's truth). A CPU preset may
resample the images by an integer factor; the intrinsics are scaled to match.

The holdout is :func:`brave6d.training.holdout.holdout_split` (the paper's protocol), made over all
recorded frames, so skipping a bad frame never moves another frame between the sets.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from brave6d.core.atomic import read_png
from brave6d.core.calibration_io import camera_poses, read_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.layout import FrameRecord, SceneDir
from brave6d.core.transforms import invert
from brave6d.training.holdout import holdout_split
from brave6d.training.scene_frame import SceneFrame, scene_radius

log = logging.getLogger(__name__)


@dataclass
class View:
    """One frame ready for training: pose, level and the (resampled) RGB image (uint8 [H, W, 3])."""

    index: int
    view_id: str
    distance_level: int
    distance_m: float
    base_T_cam: NDArray[np.float64]
    image: NDArray[np.uint8]
    rgb_path: Path | None = None
    depth_path: Path | None = None

    @property
    def viewmat(self) -> NDArray[np.float64]:
        """World-to-camera transform (``cam_T_base``)."""
        return invert(self.base_T_cam)


@dataclass(frozen=True)
class SkippedFrame:
    index: int
    view_id: str
    reason: str


@dataclass
class TrainingData:
    """Train and holdout views sharing one pinhole ``camera`` (at training resolution)."""

    camera: PinholeCamera
    train: list[View]
    test: list[View]
    skipped: list[SkippedFrame] = field(default_factory=list)
    full_camera: PinholeCamera | None = None  # the undistorted camera at capture resolution
    undistorted_root: Path | None = None
    downscale: int = 1
    undistortion: str = "none"  # how images were undistorted (for metrics.json)
    depth_camera: PinholeCamera | None = None  # set when depth files are still distorted (raw)
    valid_mask: NDArray[np.bool_] | None = None  # [H, W] pixels undistortion filled; None: all
    #: set: the poses are in this training frame (:mod:`brave6d.training.scene_frame`, extent 1); None: the world's
    frame: SceneFrame | None = None

    def valid_tensor(self, device: torch.device | str) -> Tensor | None:
        """:attr:`valid_mask` as a bool tensor on ``device`` (None: every pixel is valid)."""
        return None if self.valid_mask is None else torch.from_numpy(self.valid_mask).to(device)

    @property
    def views(self) -> list[View]:
        return sorted(self.train + self.test, key=lambda v: v.index)

    @property
    def K(self) -> NDArray[np.float64]:
        return self.camera.K

    def scene_extent(self) -> float:
        """Inria's scene radius (:func:`brave6d.training.scene_frame.scene_radius`): 1.1 x the largest
        distance of a camera centre from their mean; exactly 1 in a training frame. Every length the
        trainer uses is a multiple of it."""
        if self.frame is not None:
            return 1.0
        return scene_radius([v.base_T_cam[:3, 3] for v in self.views])

    def training_frame(self) -> SceneFrame:
        """The training frame of these cameras (train and holdout views), in their world."""
        return SceneFrame.of_cameras([v.base_T_cam[:3, 3] for v in self.views])

    def in_frame(self, frame: SceneFrame) -> TrainingData:
        """These views with every pose in ``frame`` (images, camera and split unchanged): the training
        frame's data, whose extent is 1 by definition and whose depth targets are divided by ``frame.unit``."""
        if self.frame is not None:
            raise ValueError("in_frame: the views are already in a training frame")

        def moved(v: View) -> View:
            return replace(v, base_T_cam=frame.pose(v.base_T_cam))

        return replace(self, train=[moved(v) for v in self.train], test=[moved(v) for v in self.test], frame=frame)

    @property
    def length_unit(self) -> float:
        """World units (metres for a capture) per unit of these poses: what a depth in metres is divided by."""
        return 1.0 if self.frame is None else self.frame.unit

    def fingerprint(self) -> list[str]:
        """Identifies the split (a resumed run must train on the same views)."""
        return [v.view_id for v in self.train]


def image_tensor(view: View, device: torch.device | str = "cpu") -> Tensor:
    """The view's image as float32 [H, W, 3] in [0, 1]."""
    return torch.from_numpy(view.image).to(device=device, dtype=torch.float32) / 255.0


# ----------------------------------------------------------------------------- loading
def resample(image: NDArray[np.uint8], width: int, height: int) -> NDArray[np.uint8]:
    """Area-average resampling (the anti-aliased downscale used for training images)."""
    if image.shape[1] == width and image.shape[0] == height:
        return image
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def load_scene(scene: SceneDir, downscale: int = 1, skip_bad_frames: bool = False) -> TrainingData:
    """Load a captured and calibrated scene for training (see the module docstring).

    A missing or corrupt frame raises :class:`DataError` naming it; with ``skip_bad_frames`` it
    is left out and listed in ``skipped``.
    """
    from brave6d.core.undistort import ensure_undistorted

    if not scene.frames_path.exists():
        raise DataError(f"{scene.frames_path}: no captured frames (run the capture first)")
    records = scene.frames()
    if not records:
        raise DataError(f"{scene.frames_path}: the capture holds no frames")
    poses = {r.index: T for r, T in camera_poses(scene, records)}
    raw_camera = read_intrinsics(scene)
    try:
        und = ensure_undistorted(scene)
        full = und.camera
        loader = _file_loader(und.rgb_path, und.depth_path)
        root: Path | None = und.root
        depth_camera = None
        how = f"undistorted once with the calibrated intrinsics into {und.root} (bilinear)"
    except DataError as exc:
        if not skip_bad_frames:
            raise DataError(f"{exc} (pass --skip-bad-frames to train without the bad frames)") from None
        log.warning("undistorting the capture failed (%s); --skip-bad-frames: undistorting the readable "
                    "frames in memory instead", exc)
        full = raw_camera.without_distortion()
        loader = _memory_loader(scene, raw_camera)
        root = None
        depth_camera = raw_camera
        how = "undistorted once in memory with the calibrated intrinsics (bilinear)"
    width, height = _scaled_size(full, downscale)
    camera = full.scaled(width, height)
    _, test_idx = holdout_split(records)
    test_set = set(test_idx)
    train: list[View] = []
    test: list[View] = []
    skipped: list[SkippedFrame] = []
    for r in records:
        try:
            image, rgb_path, depth_path = loader(r)
            if image.shape[:2] != (full.height, full.width):
                raise DataError(f"{rgb_path}: image is {image.shape[1]}x{image.shape[0]}, "
                                f"the camera is {full.width}x{full.height}")
        except DataError as exc:
            message = f"frame {r.index} ({r.view_id}): {exc}"
            if not skip_bad_frames:
                raise DataError(message + " (pass --skip-bad-frames to train without it)") from None
            log.warning("skipping %s", message)
            skipped.append(SkippedFrame(r.index, r.view_id, str(exc)))
            continue
        view = View(r.index, r.view_id, r.distance_level, r.distance_m, poses[r.index],
                    resample(image, width, height), rgb_path, depth_path)
        (test if r.index in test_set else train).append(view)
    if not train:
        raise DataError(f"{scene.frames_path}: no usable training frames")
    if downscale > 1:
        how += f"; resampled to {width}x{height} (1/{downscale}, area averaging)"
    valid = valid_pixels(raw_camera, width, height)
    if valid is not None:
        how += f"; {int((~valid).sum())} border pixels without raw data are left out of the loss and the metrics"
    log.info("training data: %d train / %d holdout views, %d skipped, %s", len(train), len(test), len(skipped), how)
    return TrainingData(camera, train, test, skipped, full, root, downscale, how, depth_camera, valid)


def valid_pixels(raw: PinholeCamera, width: int, height: int) -> NDArray[np.bool_] | None:
    """Pixels of the undistorted image (resampled to ``width`` x ``height``) fully inside the raw image.

    Undistorting a lens with distortion leaves black border pixels that no raw pixel maps to; a
    resampled pixel counts as valid only if every capture pixel it averages is. None when the
    camera has no distortion (every pixel is valid).
    """
    if not raw.has_distortion:
        return None
    inside = raw.undistort_image(np.full((raw.height, raw.width), 255, np.uint8), cv2.INTER_LINEAR)
    valid = resample(inside, width, height) >= 255
    return None if bool(valid.all()) else valid


def _scaled_size(camera: PinholeCamera, downscale: int) -> tuple[int, int]:
    return max(1, round(camera.width / downscale)), max(1, round(camera.height / downscale))


def _file_loader(rgb_path_of, depth_path_of):  # type: ignore[no-untyped-def]
    def load(r: FrameRecord) -> tuple[NDArray[np.uint8], Path, Path | None]:
        path = rgb_path_of(r)
        return read_png(path, "rgb"), path, depth_path_of(r)

    return load


def _memory_loader(scene: SceneDir, raw: PinholeCamera):  # type: ignore[no-untyped-def]
    def load(r: FrameRecord) -> tuple[NDArray[np.uint8], Path, Path | None]:
        path = scene.capture.file(r.rgb)
        image = read_png(path, "rgb")
        if image.shape[:2] != (raw.height, raw.width):
            raise DataError(f"{path}: image is {image.shape[1]}x{image.shape[0]}, the camera is {raw.width}x{raw.height}")
        depth = scene.capture.file(r.depth) if r.depth else None
        return raw.undistort_image(image, cv2.INTER_LINEAR), path, None if depth is None else depth

    return load


def load_depth_m(view: View, raw_distorted: PinholeCamera | None = None) -> NDArray[np.float32] | None:
    """The view's undistorted depth image in metres at capture resolution (0 = no data), or None.

    ``raw_distorted`` (``TrainingData.depth_camera``): the depth file is a raw capture file;
    undistort it with this camera (nearest neighbour).
    """
    from brave6d.core.atomic import depth_mm_u16_to_m

    if view.depth_path is None or not Path(view.depth_path).is_file():
        return None
    try:
        depth = read_png(view.depth_path, "depth")
    except DataError as exc:
        log.warning("frame %d (%s): depth unreadable, ignored (%s)", view.index, view.view_id, exc)
        return None
    if raw_distorted is not None and raw_distorted.has_distortion:
        depth = raw_distorted.undistort_image(depth, cv2.INTER_NEAREST)
    return depth_mm_u16_to_m(depth)

"""A BOP split as the BOP toolkit defines it, read for training and estimation: the one reader of
a split's images (``train_pbr``, ``test``, a held-out split), whoever wrote them (``brave6d synth``,
the BOP export, BlenderProc).

Per scene folder ``{split}/{scene_id:06d}/`` (bop_toolkit ``docs/bop_datasets_format.md``):

- ``rgb/{im_id:06d}.png`` or ``.jpg`` (BlenderProc's BOP-challenge scripts write JPEG); a folder
  with ``gray/`` and no ``rgb/`` (ITODD) is refused naming it: the estimators need colour;
- ``depth/{im_id:06d}.png`` (uint16), in units of the image's ``depth_scale`` mm from
  ``scene_camera.json`` (1: mm, as brave6d writes; 0.1: tenths of a mm, as BlenderProc writes).
  A depth image is read only scaled by its ``depth_scale``: an image with depth and no
  ``depth_scale`` is refused in one line naming the file and field, never read as mm;
- ``scene_camera.json`` (``cam_K`` per image), ``scene_gt.json``, ``scene_gt_info.json`` (the
  typed readers of :mod:`brave6d.annotation.bop_format`, bounded by the project's JSON reader) and
  ``mask_visib/{im_id:06d}_{gt_id:06d}.png``.

Images are decoded by :func:`brave6d.core.atomic.read_png` (OpenCV, after the header's pixel limit
is checked: PNG or JPEG alike). The models (``models/``, ``models_info.json`` with its symmetries)
are read by :func:`brave6d.evaluation.metrics.load_models`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from brave6d.annotation.bop_format import (
    GtInfo,
    GtPose,
    SceneCamera,
    read_scene_camera,
    read_scene_gt,
    read_scene_gt_info,
    read_test_targets,
)
from brave6d.core.errors import DataError

#: Colour image suffixes a split's ``rgb/`` may hold, in the order they are looked for.
RGB_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class SplitImage:
    """One image of a BOP split: where its files are, its camera (``cam_K`` in the project's
    convention, ``depth_scale`` mm per depth unit), its ground truth and GT info in ``gt_id`` order."""

    scene_dir: Path
    scene_id: int
    im_id: int
    rgb_path: Path
    camera: SceneCamera
    gts: tuple[GtPose, ...]
    infos: tuple[GtInfo, ...]

    @property
    def depth_path(self) -> Path:
        return self.scene_dir / "depth" / f"{self.im_id:06d}.png"

    @property
    def has_depth(self) -> bool:
        return self.depth_path.is_file()

    def mask_visib_path(self, gt_id: int) -> Path:
        return self.scene_dir / "mask_visib" / f"{self.im_id:06d}_{gt_id:06d}.png"

    def read_rgb(self) -> NDArray[np.uint8]:
        """The colour image, RGB uint8 (H, W, 3), PNG or JPEG."""
        return read_split_rgb(self.rgb_path)

    def read_depth_mm(self) -> NDArray[np.float64]:
        """The depth image in millimetres: its values times the image's ``depth_scale``."""
        return read_depth_mm(self.depth_path, self.camera.depth_scale)


def read_split_rgb(path: Path | str) -> NDArray[np.uint8]:
    """A split's colour image (PNG or JPEG) as RGB uint8 (H, W, 3); a grey image is refused naming the file."""
    from brave6d.core.atomic import read_png

    return read_png(path, expect="rgb")


def read_depth_mm(path: Path | str, depth_scale: float) -> NDArray[np.float64]:
    """A uint16 depth PNG in millimetres (``value * depth_scale``; 0 stays 0, no data)."""
    from brave6d.core.atomic import read_png

    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise DataError(f"{path}: depth_scale must be a positive number of mm per unit, got {depth_scale}")
    return read_png(path, expect="depth").astype(np.float64) * float(depth_scale)


def rgb_file(scene_dir: Path, im_id: int) -> Path:
    """``rgb/{im_id:06d}.png`` or ``.jpg`` of a scene folder; a grey-only split (``gray/``) or a
    missing image is refused naming the folder."""
    rgb_dir = scene_dir / "rgb"
    if not rgb_dir.is_dir():
        if (scene_dir / "gray").is_dir():
            raise DataError(f"{scene_dir / 'gray'}: grey images (gray/) are not read: the estimators need colour "
                            "images in rgb/")
        raise DataError(f"{rgb_dir}: no rgb/ folder (colour images, PNG or JPEG)")
    path = find_rgb_file(scene_dir, im_id)
    if path is None:
        raise DataError(f"{rgb_dir}: no colour image {im_id:06d} ({' or '.join(RGB_SUFFIXES)})")
    return path


def find_rgb_file(scene_dir: Path | str, im_id: int) -> Path | None:
    """``rgb/{im_id:06d}.png`` (or ``.jpg``, ``.jpeg``) of a scene folder, None when there is none."""
    for suffix in RGB_SUFFIXES:
        path = Path(scene_dir) / "rgb" / f"{im_id:06d}{suffix}"
        if path.is_file():
            return path
    return None


def split_scene_folders(split_dir: Path | str, hint: str = "") -> list[Path]:
    """The six-digit scene folders of a split folder, in order (``hint``: added to the message when there is none)."""
    d = Path(split_dir)
    if not d.is_dir():
        raise DataError(f"{d}: split folder not found")
    scenes = sorted(p for p in d.iterdir() if p.is_dir() and re.fullmatch(r"\d{6}", p.name))
    if not scenes:
        raise DataError(f"{d}: no scene folders (000000, 000001, ...){hint}")
    return scenes


def read_split_scene(scene_dir: Path | str) -> list[SplitImage]:
    """Every image of one scene folder, in image-id order (module docstring). The three JSON files
    must list the same images; an image with a depth image must have ``depth_scale``."""
    d = Path(scene_dir)
    scene_id = int(d.name)
    has_depth = (d / "depth").is_dir()
    cams = read_scene_camera(d / "scene_camera.json", require_depth_scale=has_depth)
    gts = read_scene_gt(d / "scene_gt.json")
    infos = read_scene_gt_info(d / "scene_gt_info.json")
    images = []
    for im_id in sorted(gts):
        if im_id not in cams:
            raise DataError(f"{d / 'scene_camera.json'}: no entry for image {im_id} of scene_gt.json")
        if im_id not in infos or len(infos[im_id]) != len(gts[im_id]):
            raise DataError(f"{d / 'scene_gt_info.json'}: image {im_id}: {len(infos.get(im_id, []))} entries, "
                            f"scene_gt.json has {len(gts[im_id])}")
        images.append(SplitImage(d, scene_id, im_id, rgb_file(d, im_id), cams[im_id], tuple(gts[im_id]),
                                 tuple(infos[im_id])))
    return images


def read_bop_split(split_dir: Path | str) -> list[SplitImage]:
    """Every image of every scene folder of a split, in (scene, image) order."""
    return [image for scene in split_scene_folders(split_dir) for image in read_split_scene(scene)]


def read_split_targets(split_dir: Path | str, targets_file: Path | str) -> tuple[list[SplitImage],
                                                                                 dict[tuple[int, int], dict[int, int]]]:
    """The images a targets file (``test_targets_bop19.json``) lists, in (scene, image) order, and its
    targets: for a test split without ``scene_gt.json`` (the images' ``gts`` and ``infos`` are empty).
    Each listed image needs its scene folder, its ``scene_camera.json`` entry and its colour image;
    a missing one is refused naming it."""
    d = Path(split_dir)
    targets = read_test_targets(targets_file)
    if not targets:
        raise DataError(f"{targets_file}: lists no targets")
    folders = {int(f.name): f for f in split_scene_folders(d)}
    cameras: dict[int, dict[int, SceneCamera]] = {}
    images = []
    for scene_id, im_id in sorted(targets):
        folder = folders.get(scene_id)
        if folder is None:
            raise DataError(f"{targets_file}: scene {scene_id} has no folder {d / f'{scene_id:06d}'}")
        if scene_id not in cameras:
            cameras[scene_id] = read_scene_camera(folder / "scene_camera.json",
                                                  require_depth_scale=(folder / "depth").is_dir())
        camera = cameras[scene_id].get(im_id)
        if camera is None:
            raise DataError(f"{folder / 'scene_camera.json'}: no entry for image {im_id} of {targets_file}")
        images.append(SplitImage(folder, scene_id, im_id, rgb_file(folder, im_id), camera, (), ()))
    return images, targets

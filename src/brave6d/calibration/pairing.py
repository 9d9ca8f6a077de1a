"""Pair a folder of calibration images with their robot poses (one pose per image).

Images: the files of the folder (not its subfolders) ending in one of :data:`IMAGE_EXTENSIONS`,
in natural order (``2.png`` before ``10.png``). Poses (:mod:`brave6d.calibration.pose_files`): a
folder of pose files, one per image, or one file with every pose. Matching (:data:`MATCH_MODES`):

* ``stem``: image ``0.png`` takes the pose named ``0`` (``poses/0.yaml``, a line ``0 ...`` or a key
  ``0:``); every image needs a pose and every pose an image, else the error lists both sides;
* ``order``: the i-th image in natural order takes the i-th pose (pose files in natural order, a
  file's poses in file order); the counts must be equal;
* ``auto`` (default): ``stem`` for a folder of pose files or a file that names its poses,
  ``order`` for a file that lists them.

:attr:`PosedImages.description` says which matching was used, so a run's output states it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError
from brave6d.calibration.pose_files import POSE_EXTENSIONS, PoseFormat, read_pose_collection, read_pose_file

__all__ = ["IMAGE_EXTENSIONS", "MATCH_MODES", "MAX_TRANSLATION_M", "PosedImages", "list_images", "natural_key",
           "pair_images_with_poses"]

Array = NDArray[np.float64]
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
MATCH_MODES = ("auto", "stem", "order")
#: A robot pose further than this from the base is taken for a unit mistake (millimetres as metres).
MAX_TRANSLATION_M = 20.0


@dataclass(frozen=True)
class PosedImages:
    """Images and their robot poses ``base_T_tcp`` (metres), paired; ``matching``: ``stem`` or ``order``."""

    images: tuple[Path, ...]
    poses: tuple[Array, ...]
    matching: str
    source: Path

    @property
    def names(self) -> list[str]:
        """The image file names (used in messages and reports)."""
        return [p.name for p in self.images]

    @property
    def description(self) -> str:
        """How the images were paired, e.g. ``16 images paired with the poses of poses/ by file stem``."""
        first = self.images[0]
        how = (f"by file stem (image {first.name} <- pose {first.stem})" if self.matching == "stem"
               else f"by sorted order (natural order: 2 before 10; {first.name} <- the first pose)")
        return f"{len(self.images)} images paired with the robot poses of {self.source} {how}"


def natural_key(name: str) -> tuple[tuple[int, int | str], ...]:
    """Sort key that orders the digit runs of ``name`` as numbers (``img2`` before ``img10``)."""
    return tuple((0, int(part)) if part.isdigit() else (1, part.lower()) for part in re.split(r"(\d+)", name) if part)


def list_images(folder: Path | str) -> list[Path]:
    """The images of ``folder`` in natural order; raises when there is none."""
    root = Path(folder)
    if not root.is_dir():
        raise DataError(f"{root}: not a folder of images")
    images = sorted((p for p in root.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS),
                    key=lambda p: natural_key(p.name))
    if not images:
        raise DataError(f"{root}: no images ({', '.join(IMAGE_EXTENSIONS)})")
    stems = [p.stem for p in images]
    repeated = sorted({s for s in stems if stems.count(s) > 1})
    if repeated:
        raise DataError(f"{root}: several images share a name: {', '.join(repeated[:5])} (e.g. 0.png and 0.jpg)")
    return images


def _pose_files(folder: Path) -> dict[str, Path]:
    files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in POSE_EXTENSIONS),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise DataError(f"{folder}: no pose files ({', '.join(POSE_EXTENSIONS)})")
    by_stem: dict[str, Path] = {}
    for f in files:
        if f.stem in by_stem:
            raise DataError(f"{folder}: two pose files for {f.stem!r}: {by_stem[f.stem].name} and {f.name}")
        by_stem[f.stem] = f
    return by_stem


def _listed(names: list[str]) -> str:
    return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")


def _by_stem(images: list[Path], poses: dict[str, Array], source: Path) -> list[Array]:
    stems = {p.stem for p in images}
    lonely_images = [p.name for p in images if p.stem not in poses]
    lonely_poses = sorted((k for k in poses if k not in stems), key=natural_key)
    if lonely_images or lonely_poses:
        parts = []
        if lonely_images:
            parts.append(f"images without a pose: {_listed(lonely_images)}")
        if lonely_poses:
            parts.append(f"poses without an image: {_listed(lonely_poses)}")
        hint = ("; to pair them by sorted order instead, say --match order" if len(images) == len(poses) else "")
        raise DataError(f"{source}: images and poses do not match by file stem ({'; '.join(parts)}){hint}")
    return [poses[p.stem] for p in images]


def _check_units(images: list[Path], poses: list[Array], source: Path) -> None:
    for image, T in zip(images, poses, strict=True):
        distance = float(np.linalg.norm(T[:3, 3]))
        if distance > MAX_TRANSLATION_M:
            raise DataError(f"{source}: the pose of {image.name} is {distance:.1f} m from the robot base (more than "
                            f"{MAX_TRANSLATION_M:g} m): are the translations in millimetres? say --pose-unit mm")


def pair_images_with_poses(images_dir: Path | str, poses: Path | str, fmt: PoseFormat | None = None,
                           match: str = "auto") -> PosedImages:
    """Pair the images of ``images_dir`` with the robot poses of ``poses`` (a folder or a file; see
    the module docstring). Raises :class:`~brave6d.core.errors.DataError` naming the files."""
    if match not in MATCH_MODES:
        raise ValueError(f"match must be one of {MATCH_MODES}, got {match!r}")
    images = list_images(images_dir)
    source = Path(poses)
    if source.is_dir():
        files = _pose_files(source)
        mode = "stem" if match == "auto" else match
        if mode == "stem":
            stems = {p.stem for p in images}
            if stems != set(files):  # report the mismatch before reading any pose
                _by_stem(images, {k: np.eye(4) for k in files}, source)
            paired = [read_pose_file(files[p.stem], fmt) for p in images]
        else:
            if len(files) != len(images):
                raise DataError(f"{source}: {len(files)} pose files but {len(images)} images in {images_dir}; "
                                "pairing by sorted order needs one pose per image")
            paired = [read_pose_file(f, fmt) for f in files.values()]
    elif source.is_file():
        collection = read_pose_collection(source, fmt)
        if isinstance(collection, dict):
            if match == "order":
                raise DataError(f"{source}: the poses are named (by image stem); pair them by stem (--match stem)")
            mode, paired = "stem", _by_stem(images, collection, source)
        else:
            if match == "stem":
                raise DataError(f"{source}: the poses are not named; pair them by sorted order (--match order), or "
                                "name each (a first column, or a mapping from image stem to pose)")
            if len(collection) != len(images):
                raise DataError(f"{source}: {len(collection)} poses but {len(images)} images in {images_dir}; "
                                "pairing by sorted order needs one pose per image")
            mode, paired = "order", list(collection)
    else:
        raise DataError(f"{source}: no such file or folder of robot poses")
    _check_units(images, paired, source)
    return PosedImages(tuple(images), tuple(paired), mode, source)

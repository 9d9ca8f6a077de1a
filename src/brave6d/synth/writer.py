"""The synthetic split on disk (BOP's ``train_pbr`` layout through annotation's BOP layout and
JSON writer) and its own bookkeeping files, owned here::

    OUT/synth.json                           settings and source digest (a resumed run must match)
    OUT/train_pbr/XXXXXX/rgb/, depth/, mask/, mask_visib/, scene_camera.json, scene_gt.json,
                        scene_gt_info.json   1000 images per folder (BOP's PBR convention)
    OUT/work/IIIIII.json                     one record per finished image (its three JSON entries)

Each image's PNGs are written atomically, then its record: an image with a record was complete, so
a run stopped at any point resumes where it stopped. A resumed run checks the record and PNGs of
every such image (:func:`image_problem`) and renders a damaged one again (its files and record
replaced atomically, the record last). The scene JSON files are gathered from the records at the
end (same bytes however the images were split between workers).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.core.atomic import atomic_write_json, atomic_write_text, read_json, write_png
from brave6d.core.errors import DataError
from brave6d.core.png_check import DEFAULT_CHECK, png_problem
from brave6d.synth.render import RenderedImage

SPLIT = "train_pbr"
IMAGES_PER_FOLDER = 1000
SETTINGS_FILE = "synth.json"
FORMAT = "brave6d-synth/1"
RECORD_FIELDS = ("scene_camera", "scene_gt", "scene_gt_info")


def image_address(index: int) -> tuple[int, int]:
    """``(folder scene_id, im_id)`` of image ``index``."""
    return index // IMAGES_PER_FOLDER, index % IMAGES_PER_FOLDER


def layout_of(out: Path, index: int) -> Any:
    """annotation's ``BopLayout`` of the folder that holds image ``index``."""
    from brave6d.annotation import BopLayout

    return BopLayout(Path(out), SPLIT, image_address(index)[0])


def record_path(out: Path, index: int) -> Path:
    return Path(out) / "work" / f"{index:06d}.json"


def has_record(out: Path, index: int) -> bool:
    """True when image ``index`` was written completely once (its record exists); whether its files
    are still whole is :func:`image_problem`'s question."""
    return record_path(out, index).is_file()


def image_problem(out: Path, index: int, size: tuple[int, int], check: str = DEFAULT_CHECK) -> str | None:
    """Why image ``index`` (``size``: width, height) is not complete and whole, naming the first bad
    file: its record missing or malformed, or a PNG it lists missing or failing ``check``
    (:mod:`brave6d.core.png_check`); None when it is."""
    path = record_path(out, index)
    try:
        record = _record_fields(path, read_json(path))
    except DataError as exc:
        return str(exc)
    layout = layout_of(out, index)
    _, im_id = image_address(index)
    files = [(layout.rgb_path(im_id), "rgb"), (layout.depth_path(im_id), "depth")]
    for gt_id in range(len(record["scene_gt"])):
        files += [(layout.mask_path(im_id, gt_id), "mask"), (layout.mask_visib_path(im_id, gt_id), "mask")]
    for file, kind in files:
        problem = png_problem(file, kind, size, check)
        if problem is not None:
            return f"{file}: {problem}"
    return None


def _record_fields(path: Path, record: Any) -> dict[str, Any]:
    """``record`` when it has the three fields (``scene_gt`` and ``scene_gt_info`` lists of one length)."""
    if not isinstance(record, dict) or not set(RECORD_FIELDS) <= set(record):
        raise DataError(f"{path}: malformed image record (fields {', '.join(RECORD_FIELDS)} needed)")
    gt, info = record["scene_gt"], record["scene_gt_info"]
    if not isinstance(gt, list) or not isinstance(info, list) or len(gt) != len(info):
        raise DataError(f"{path}: malformed image record (scene_gt and scene_gt_info: lists of one length)")
    return record


def write_image(out: Path, index: int, image: RenderedImage) -> None:
    """Write image ``index``'s PNGs, then its record (see the module docstring)."""
    layout = layout_of(out, index)
    _, im_id = image_address(index)
    write_png(layout.rgb_path(im_id), image.rgb)
    write_png(layout.depth_path(im_id), image.depth_mm)
    for gt_id, (mask, visib) in enumerate(zip(image.masks, image.masks_visib)):
        write_png(layout.mask_path(im_id, gt_id), mask.astype(np.uint8) * 255)
        write_png(layout.mask_visib_path(im_id, gt_id), visib.astype(np.uint8) * 255)
    atomic_write_json(record_path(out, index), {"scene_camera": image.scene_camera, "scene_gt": image.scene_gt,
                                                "scene_gt_info": image.scene_gt_info}, indent=None)
    # record last: a stale record of a damaged image is only replaced once the new PNGs are in place


def gather_scene_files(out: Path, count: int) -> list[Path]:
    """Write each folder's ``scene_camera``/``scene_gt``/``scene_gt_info.json`` from the records of
    images ``0 .. count-1`` (annotation's BOP JSON writer); returns the folders."""
    from brave6d.annotation import dump_bop_json

    folders: dict[int, dict[str, dict[int, Any]]] = {}
    for index in range(count):
        path = record_path(out, index)
        record = _record_fields(path, read_json(path))
        folder, im_id = image_address(index)
        files = folders.setdefault(folder, {"scene_camera": {}, "scene_gt": {}, "scene_gt_info": {}})
        for key in files:
            files[key][im_id] = record[key]
    written = []
    for folder, files in sorted(folders.items()):
        layout = layout_of(out, folder * IMAGES_PER_FOLDER)
        atomic_write_text(layout.scene_camera_path, dump_bop_json(files["scene_camera"]))
        atomic_write_text(layout.scene_gt_path, dump_bop_json(files["scene_gt"]))
        atomic_write_text(layout.scene_gt_info_path, dump_bop_json(files["scene_gt_info"]))
        written.append(layout.scene_dir)
    return written


def check_settings(out: Path, settings: dict[str, Any]) -> None:
    """Write ``OUT/synth.json``, or refuse to resume into an ``OUT`` made with other settings."""
    path = Path(out) / SETTINGS_FILE
    wanted = json.loads(json.dumps({"format": FORMAT, **settings}))  # tuples as the file holds them: lists
    if path.is_file():
        old = read_json(path)
        diff = sorted(k for k in set(wanted) | set(old if isinstance(old, dict) else {})
                      if not isinstance(old, dict) or old.get(k) != wanted.get(k))
        if diff:
            raise DataError(f"{path}: this folder holds a synthetic split made with other settings "
                            f"(field '{diff[0]}'); choose another OUT or the same settings to resume")
        return
    atomic_write_json(path, wanted)

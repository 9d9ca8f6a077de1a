"""The synthetic split on disk (BOP's ``train_pbr`` layout through annotation's BOP layout and
JSON writer) and its own bookkeeping files, owned here::

    OUT/synth.json                           settings and source digest (a resumed run must match)
    OUT/train_pbr/XXXXXX/rgb/, depth/, mask/, mask_visib/, scene_camera.json, scene_gt.json,
                        scene_gt_info.json   1000 images per folder (BOP's PBR convention)
    OUT/work/IIIIII.json                     one record per finished image (its three JSON entries)

Two conventions (``CONVENTIONS``): ``brave6d`` (PNG ``rgb/``, depth PNGs in mm, ``depth_scale`` 1)
and ``blenderproc``, as BlenderProc's BOP-challenge scripts call its ``write_bop`` (``color_file_format
"JPEG"``, ``jpg_quality`` 95, ``depth_scale`` 0.1: ``rgb/XXXXXX.jpg``, depth PNGs in tenths of a mm
rounded from the rendered depth, ``scene_camera.json``'s ``depth_scale`` 0.1, and each folder's
``scene_gt_coco.json``, as ``write_bop``'s ``calc_mask_info_coco`` adds). Masks and the other JSON
files are the same in both.

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
CONVENTIONS = ("brave6d", "blenderproc")
#: BlenderProc's BOP-challenge settings: depth PNGs in 0.1 mm, colour as JPEG of quality 95.
BLENDERPROC_DEPTH_SCALE = 0.1
BLENDERPROC_JPEG_QUALITY = 95


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


def rgb_path(out: Path, index: int, convention: str = "brave6d") -> Path:
    """The colour image of image ``index``: ``.png``, or ``.jpg`` in BlenderProc's convention."""
    path = layout_of(out, index).rgb_path(image_address(index)[1])
    return path.with_suffix(".jpg") if convention == "blenderproc" else path


def image_problem(out: Path, index: int, size: tuple[int, int], check: str = DEFAULT_CHECK,
                  convention: str = "brave6d") -> str | None:
    """Why image ``index`` (``size``: width, height) is not complete and whole, naming the first bad
    file: its record missing or malformed, or a PNG it lists missing or failing ``check``
    (:mod:`brave6d.core.png_check`; a JPEG: its header, size and end marker); None when it is."""
    path = record_path(out, index)
    try:
        record = _record_fields(path, read_json(path))
    except DataError as exc:
        return str(exc)
    layout = layout_of(out, index)
    _, im_id = image_address(index)
    files = [(layout.depth_path(im_id), "depth")]
    if convention == "blenderproc":
        problem = _jpeg_problem(rgb_path(out, index, convention), size)
        if problem is not None:
            return problem
    else:
        files.insert(0, (layout.rgb_path(im_id), "rgb"))
    for gt_id in range(len(record["scene_gt"])):
        files += [(layout.mask_path(im_id, gt_id), "mask"), (layout.mask_visib_path(im_id, gt_id), "mask")]
    for file, kind in files:
        problem = png_problem(file, kind, size, check)
        if problem is not None:
            return f"{file}: {problem}"
    return None


def _jpeg_problem(path: Path, size: tuple[int, int]) -> str | None:
    """Why the JPEG ``path`` is not whole (header, size, the end-of-image marker), naming it; None when it is."""
    from brave6d.core.png_check import image_header_problem

    problem = image_header_problem(path)
    if problem is not None:
        return f"{path}: {problem}"
    from PIL import Image

    with Image.open(path) as im:
        if im.format != "JPEG" or tuple(im.size) != tuple(size):
            return f"{path}: expected a {size[0]}x{size[1]} JPEG, got {im.format} {im.size[0]}x{im.size[1]}"
    with open(path, "rb") as handle:
        handle.seek(-2, 2)
        if handle.read(2) != b"\xff\xd9":
            return f"{path}: truncated JPEG (no end-of-image marker)"
    return None


def _record_fields(path: Path, record: Any) -> dict[str, Any]:
    """``record`` when it has the three fields (``scene_gt`` and ``scene_gt_info`` lists of one length)."""
    if not isinstance(record, dict) or not set(RECORD_FIELDS) <= set(record):
        raise DataError(f"{path}: malformed image record (fields {', '.join(RECORD_FIELDS)} needed)")
    gt, info = record["scene_gt"], record["scene_gt_info"]
    if not isinstance(gt, list) or not isinstance(info, list) or len(gt) != len(info):
        raise DataError(f"{path}: malformed image record (scene_gt and scene_gt_info: lists of one length)")
    return record


def write_image(out: Path, index: int, image: RenderedImage, convention: str = "brave6d") -> None:
    """Write image ``index``'s files in ``convention``, then its record (see the module docstring)."""
    layout = layout_of(out, index)
    _, im_id = image_address(index)
    scene_camera = dict(image.scene_camera)
    if convention == "blenderproc":
        _write_jpeg(rgb_path(out, index, convention), image.rgb)
        write_png(layout.depth_path(im_id), _depth_units(image, BLENDERPROC_DEPTH_SCALE))
        scene_camera["depth_scale"] = BLENDERPROC_DEPTH_SCALE
    elif convention == "brave6d":
        write_png(layout.rgb_path(im_id), image.rgb)
        write_png(layout.depth_path(im_id), image.depth_mm)
    else:
        raise DataError(f"synth: convention must be one of {', '.join(CONVENTIONS)}, got {convention!r}")
    for gt_id, (mask, visib) in enumerate(zip(image.masks, image.masks_visib)):
        write_png(layout.mask_path(im_id, gt_id), mask.astype(np.uint8) * 255)
        write_png(layout.mask_visib_path(im_id, gt_id), visib.astype(np.uint8) * 255)
    atomic_write_json(record_path(out, index), {"scene_camera": scene_camera, "scene_gt": image.scene_gt,
                                                "scene_gt_info": image.scene_gt_info}, indent=None)
    # record last: a stale record of a damaged image is only replaced once the new PNGs are in place


def _depth_units(image: RenderedImage, depth_scale: float) -> np.ndarray:
    """The rendered depth as uint16 in units of ``depth_scale`` mm (0 = no data, saturating at 65535)."""
    if image.depth_m is None:  # only the rounded mm are known
        mm = image.depth_mm.astype(np.float64)
    else:
        d = np.asarray(image.depth_m, dtype=np.float64)
        mm = np.where(np.isfinite(d) & (d > 0) & (image.depth_mm > 0), d * 1000.0, 0.0)
    return np.clip(np.rint(mm / depth_scale), 0, 65535).astype(np.uint16)


def _write_jpeg(path: Path, rgb: np.ndarray) -> None:
    import cv2

    from brave6d.core.atomic import atomic_write_bytes

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, BLENDERPROC_JPEG_QUALITY])
    if not ok:
        raise DataError(f"{path}: JPEG encoding failed")
    atomic_write_bytes(path, buf.tobytes())


def gather_scene_files(out: Path, count: int, convention: str = "brave6d") -> list[Path]:
    """Write each folder's ``scene_camera``/``scene_gt``/``scene_gt_info.json`` from the records of
    images ``0 .. count-1`` (annotation's BOP JSON writer), and in BlenderProc's convention its
    ``scene_gt_coco.json`` (annotation's COCO writer, from the masks on disk); returns the folders."""
    from brave6d.annotation import COCO_FILE, dump_bop_json, scene_gt_coco

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
        if convention == "blenderproc":
            gts, infos = files["scene_gt"], files["scene_gt_info"]
            coco = scene_gt_coco(layout.scene_dir, {i: [g["obj_id"] for g in gts[i]] for i in gts},
                                 {i: [g["visib_fract"] for g in infos[i]] for i in infos}, ".jpg", Path(out).name,
                                 [g["obj_id"] for i in gts for g in gts[i]])
            atomic_write_json(layout.scene_dir / COCO_FILE, coco, indent=None)
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

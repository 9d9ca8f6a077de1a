"""``scene_gt_coco.json``: a BOP scene folder's instance masks as COCO annotations, the file
BlenderProc's ``write_bop`` (``calc_mask_info_coco``) and bop_toolkit's ``calc_gt_coco.py`` write
beside ``scene_gt.json`` for 2D detectors (detectron2, mmdetection) to train on. Owned here, as
the rest of the BOP format (:mod:`brave6d.annotation.bop_format`).

What each instance becomes, as those writers make it: an annotation per instance with a visible
mask (``mask_visib/``) and a full mask (``mask/``) that are not empty; its ``segmentation`` the
visible mask as uncompressed COCO RLE (``{"counts": [...], "size": [h, w]}``, runs in column-major
order starting with a run of zeros); ``bbox`` the full mask's box (``[x, y, w, h]``: the "amodal"
box, their default); ``area`` the visible pixels; ``ignore`` true below 10 % visible (BOP19's
threshold); ids counted from 1 over the scene's instances in image order. Categories are the
objects' ids. The ``info`` block's two dates are left empty, so the file's bytes depend only on
the images (a resumed or re-split run writes the same file).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError

COCO_FILE = "scene_gt_coco.json"
#: Instances less visible than this get ``ignore: true`` (BOP19's visibility threshold).
IGNORE_BELOW_VISIB_FRACT = 0.1


def mask_to_rle(mask: NDArray[Any]) -> dict[str, list[int]]:
    """A binary mask (H, W) as uncompressed COCO RLE: run lengths over the column-major pixels,
    starting with a run of zeros (0 when the first pixel is set)."""
    m = np.asarray(mask).astype(bool)
    if m.ndim != 2:
        raise DataError(f"mask_to_rle: expected an (H, W) mask, got shape {m.shape}")
    flat = m.ravel(order="F")
    if flat.size == 0:
        return {"counts": [], "size": list(m.shape)}
    edges = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate(([0], edges, [flat.size]))
    counts = np.diff(bounds).tolist()
    if flat[0]:
        counts.insert(0, 0)
    return {"counts": [int(c) for c in counts], "size": [int(m.shape[0]), int(m.shape[1])]}


def check_rle(rle: Mapping[str, Any], where: str = "segmentation") -> tuple[int, int]:
    """(height, width) of an uncompressed COCO RLE whose counts are non-negative integers summing to
    ``height * width``; anything else refused naming ``where``. Linear in the counts; decodes nothing."""
    size, counts = rle.get("size"), rle.get("counts")
    if (not isinstance(size, list) or len(size) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in size)):
        raise DataError(f"{where}: 'size' must be [height, width], got {size!r}")
    if not isinstance(counts, list) or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0
                                               for c in counts):
        raise DataError(f"{where}: 'counts' must be a list of non-negative integers (uncompressed RLE)")
    h, w = size
    if sum(counts) != h * w:
        raise DataError(f"{where}: the runs cover {sum(counts)} pixels, the mask has {h} x {w} = {h * w}")
    return h, w


def rle_to_mask(rle: Mapping[str, Any], where: str = "segmentation") -> NDArray[np.bool_]:
    """The binary mask of an uncompressed COCO RLE (:func:`check_rle`; a mask over the project's
    pixel limit is refused before anything is allocated)."""
    from brave6d.core.png_check import MAX_PIXELS

    h, w = check_rle(rle, where)
    if h * w > MAX_PIXELS:
        raise DataError(f"{where}: a {h} x {w} mask is over the pixel limit ({MAX_PIXELS})")
    counts = rle["counts"]
    values = np.zeros(len(counts), dtype=bool)
    values[1::2] = True
    flat = np.repeat(values, counts)
    return flat.reshape((w, h)).T.copy()


def _box(mask: NDArray[np.bool_]) -> list[int]:
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return [int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)]


def scene_gt_coco(scene_dir: Path | str, obj_ids: Mapping[int, Sequence[int]],
                  visib_fracts: Mapping[int, Sequence[float]], rgb_suffix: str, dataset: str,
                  category_ids: Sequence[int]) -> dict[str, Any]:
    """The ``scene_gt_coco.json`` content of one scene folder (module docstring): ``obj_ids`` and
    ``visib_fracts`` per image id in ``gt_id`` order (scene_gt / scene_gt_info), masks read from
    ``mask/`` and ``mask_visib/``, ``rgb/{im_id:06d}{rgb_suffix}`` as each image's file."""
    from brave6d.core.atomic import read_png

    d = Path(scene_dir)
    images, annotations, next_id = [], [], 1
    for im_id in sorted(obj_ids):
        ids = obj_ids[im_id]
        fracts = visib_fracts[im_id]
        if len(fracts) != len(ids):
            raise DataError(f"{d}: image {im_id}: {len(ids)} instances in scene_gt, {len(fracts)} in scene_gt_info")
        size: tuple[int, int] | None = None
        for gt_id, (obj_id, fract) in enumerate(zip(ids, fracts)):
            visib = read_png(d / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png", expect="any").astype(bool)
            full = read_png(d / "mask" / f"{im_id:06d}_{gt_id:06d}.png", expect="any").astype(bool)
            if visib.ndim != 2 or full.shape != visib.shape:
                raise DataError(f"{d}: image {im_id} instance {gt_id}: masks must be grey images of one size")
            size = (visib.shape[1], visib.shape[0])
            if not visib.any() or not full.any():
                continue
            annotations.append({"id": next_id, "image_id": im_id, "category_id": int(obj_id), "iscrowd": 0,
                                "area": int(visib.sum()), "bbox": _box(full), "segmentation": mask_to_rle(visib),
                                "width": int(visib.shape[1]), "height": int(visib.shape[0]),
                                "ignore": bool(fract < IGNORE_BELOW_VISIB_FRACT)})
            next_id += 1
        if size is None:  # no instance: the image's size from its colour image's header
            from brave6d.core.png_check import check_image_header

            size = check_image_header(d / "rgb" / f"{im_id:06d}{rgb_suffix}")
        images.append({"id": im_id, "file_name": f"rgb/{im_id:06d}{rgb_suffix}", "width": int(size[0]),
                       "height": int(size[1]), "date_captured": "", "license": 1, "coco_url": "", "flickr_url": ""})
    return {"info": {"description": f"{dataset}_train", "url": "https://github.com/thodan/bop_toolkit",
                     "version": "0.1.0", "year": 0, "contributor": "brave6d", "date_created": ""},
            "licenses": [],
            "categories": [{"id": int(o), "name": str(o), "supercategory": dataset} for o in sorted(set(category_ids))],
            "images": images, "annotations": annotations}


def read_scene_gt_coco(path: Path | str) -> dict[int, list[dict[str, Any]]]:
    """``scene_gt_coco.json`` -> ``{image_id: [annotation, ...]}``, every annotation's RLE checked
    against its size and its image's (one line naming the file, annotation and field), without
    decoding: linear in the file's size, whatever sizes it declares."""
    from brave6d.core.atomic import read_json

    p = Path(path)
    data = read_json(p)
    if not isinstance(data, dict) or not all(isinstance(data.get(k), list) for k in ("images", "annotations")):
        raise DataError(f"{p}: expected a COCO object with 'images' and 'annotations' lists")
    sizes: dict[int, tuple[int, int]] = {}
    for index, image in enumerate(data["images"]):
        try:
            sizes[int(image["id"])] = (int(image["height"]), int(image["width"]))
        except (TypeError, KeyError, ValueError):
            raise DataError(f"{p}: images[{index}]: needs integer 'id', 'width' and 'height'") from None
    out: dict[int, list[dict[str, Any]]] = {im_id: [] for im_id in sizes}
    for index, ann in enumerate(data["annotations"]):
        where = f"{p}: annotations[{index}]"
        if not isinstance(ann, dict) or not isinstance(ann.get("segmentation"), dict):
            raise DataError(f"{where}: needs an RLE 'segmentation' object")
        image_id = ann.get("image_id")
        if image_id not in sizes:
            raise DataError(f"{where}: image_id {image_id!r} is not among the file's images")
        if tuple(ann["segmentation"].get("size", ())) != sizes[image_id]:
            raise DataError(f"{where}: segmentation size {ann['segmentation'].get('size')!r} is not its image's "
                            f"{list(sizes[image_id])}")
        check_rle(ann["segmentation"], f"{where} segmentation")
        out[image_id].append(ann)
    return out

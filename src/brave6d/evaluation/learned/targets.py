"""Training batches: detector images with CenterNet targets, coordinate-net crops with their targets.

Every batch is drawn from a NumPy generator the trainer owns (its state is checkpointed), so a
resumed run draws what an uninterrupted one would. Augmentation imitates the camera (brightness,
contrast, colour balance, sensor noise, blur) and a detector image may be mirrored; the crops'
boxes are jittered in centre and scale as GDR-Net's dynamic zoom-in.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from brave6d.evaluation.learned.crops import box_crop, crop_affine, crop_size, crops_per_batch, normalise, warp_rgb
from brave6d.evaluation.learned.data import TrainingData
from brave6d.evaluation.learned.networks import COORD_STRIDE, DETECTOR_STRIDE

Array = NDArray[np.float64]
#: Detector patches are zoomed by a log-uniform factor in this range (box edges in pixel-edge units).
ZOOM_RANGE = (0.75, 1.75)


def augment(rgb: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[np.uint8]:
    """A camera-like change of ``rgb``: gain, contrast, colour balance, noise, sometimes blur."""
    import cv2

    x = rgb.astype(np.float32)
    x = (x - 128.0) * rng.uniform(0.7, 1.3) + 128.0 + rng.uniform(-30, 30)
    x = x * rng.uniform(0.85, 1.15, size=3).astype(np.float32)
    x = x + rng.normal(0.0, rng.uniform(0.0, 6.0), size=x.shape).astype(np.float32)
    if rng.uniform() < 0.3:
        x = cv2.GaussianBlur(x, (0, 0), float(rng.uniform(0.3, 1.0)))
    return np.clip(x, 0, 255).astype(np.uint8)


def detector_batch(data: TrainingData, images: list[int], rng: np.random.Generator, batch: int,
                   patch: int) -> dict[str, NDArray[np.float32]]:
    """``batch`` square patches of ``patch`` pixels from training images (each around a random object,
    the detector being fully convolutional), zoomed by a factor drawn from :data:`ZOOM_RANGE` (so the
    near ring's larger boxes are seen as often as the far ring's), with their heatmaps (B, C, p/4,
    p/4), and per cell the box size (log pixels), centre offset and a weight that is 1 at object centres."""
    import cv2

    picks = rng.choice(images, size=batch, replace=len(images) < batch)
    n_classes = len(data.objects)
    g = patch // DETECTOR_STRIDE
    rgb = np.zeros((batch, patch, patch, 3), np.uint8)
    heat = np.zeros((batch, n_classes, g, g), np.float32)
    size = np.zeros((batch, 2, g, g), np.float32)
    offset = np.zeros((batch, 2, g, g), np.float32)
    weight = np.zeros((batch, 1, g, g), np.float32)
    ys, xs = np.mgrid[0:g, 0:g].astype(np.float32)
    for b, i in enumerate(picks):
        record = data.images[int(i)]
        h, w = record.rgb.shape[:2]
        zoom = math.exp(rng.uniform(math.log(ZOOM_RANGE[0]), math.log(ZOOM_RANGE[1])))
        source = int(math.ceil(patch / zoom))
        ox, oy = _patch_origin(data, record.instances, w, h, source, rng)
        flip = rng.uniform() < 0.5
        part = augment(record.rgb[oy:oy + source, ox:ox + source], rng)
        rgb[b] = cv2.warpAffine(part, np.array([[zoom, 0.0, 0.5 * zoom - 0.5], [0.0, zoom, 0.5 * zoom - 0.5]]),
                                (patch, patch), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if flip:
            rgb[b] = rgb[b, :, ::-1]
        for k in record.instances:
            x0, y0, x1, y1 = (c * zoom for c in data.instances[k].box)
            x0, x1, y0, y1 = x0 - ox * zoom, x1 - ox * zoom, y0 - oy * zoom, y1 - oy * zoom
            if flip:
                x0, x1 = patch - x1, patch - x0
            cx, cy = (x0 + x1) / 2.0 / DETECTOR_STRIDE, (y0 + y1) / 2.0 / DETECTOR_STRIDE
            if not (0 <= cx < g and 0 <= cy < g):
                continue
            gx, gy = int(cx), int(cy)
            sigma = max(0.6, 0.15 * math.sqrt(max(x1 - x0, 1.0) * max(y1 - y0, 1.0)) / DETECTOR_STRIDE)
            c = data.instances[k].class_index
            heat[b, c] = np.maximum(heat[b, c], np.exp(-((xs - gx) ** 2 + (ys - gy) ** 2) / (2 * sigma * sigma)))
            size[b, :, gy, gx] = (math.log(max(x1 - x0, 1.0)), math.log(max(y1 - y0, 1.0)))
            offset[b, :, gy, gx] = (cx - gx, cy - gy)
            weight[b, 0, gy, gx] = 1.0
    return {"images": normalise(rgb), "heat": heat, "size": size, "offset": offset, "weight": weight}


def _patch_origin(data: TrainingData, instances: list[int], w: int, h: int, patch: int,
                  rng: np.random.Generator) -> tuple[int, int]:
    """Top-left corner (a multiple of the stride) of a patch around a random object of the image,
    or anywhere in one case of five (background)."""
    if instances and rng.uniform() < 0.8:
        x0, y0, x1, y1 = data.instances[int(rng.choice(instances))].box
        cx = (x0 + x1) / 2 + rng.uniform(-0.4, 0.4) * patch
        cy = (y0 + y1) / 2 + rng.uniform(-0.4, 0.4) * patch
    else:
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    ox = int(np.clip(cx - patch / 2, 0, max(w - patch, 0))) // DETECTOR_STRIDE * DETECTOR_STRIDE
    oy = int(np.clip(cy - patch / 2, 0, max(h - patch, 0))) // DETECTOR_STRIDE * DETECTOR_STRIDE
    return ox, oy


def jittered_crop(box: tuple[float, float, float, float], rng: np.random.Generator) -> tuple[tuple[float, float], float]:
    """The zoomed-in crop of ``box`` with its centre shifted by up to a quarter of the box and its
    side scaled by 0.75-1.25 (what a detector's boxes do)."""
    centre, side = box_crop(box)
    bw, bh = box[2] - box[0], box[3] - box[1]
    centre = (centre[0] + rng.uniform(-0.25, 0.25) * bw, centre[1] + rng.uniform(-0.25, 0.25) * bh)
    return centre, side * rng.uniform(0.75, 1.25)


def pose_sizes(data: TrainingData, instances: list[int], smallest: int, largest: int) -> dict[int, list[int]]:
    """``instances`` grouped by the size of their crop (:func:`crop_size` of their box), smallest first."""
    groups: dict[int, list[int]] = {}
    for k in instances:
        _, side = box_crop(data.instances[int(k)].box_crop)
        groups.setdefault(crop_size(side, smallest, largest), []).append(int(k))
    return dict(sorted(groups.items()))


def pose_batch(data: TrainingData, instances: list[int], rng: np.random.Generator, batch: int,
               crop_px: int, crop_px_min: int | None = None) -> dict[str, NDArray[np.float32] | NDArray[np.int64]]:
    """A batch of jittered crops (B, 3, S, S) with their class indices, coordinate targets (B, 3, S/4,
    S/4) and visible masks (B, 1, S/4, S/4) (the net's output stride). The crops follow their boxes'
    size within ``crop_px_min`` .. ``crop_px`` (None: all ``crop_px``): one size per batch, drawn so
    that every instance is seen equally often, with :func:`crops_per_batch` crops of it."""
    import cv2

    smallest = crop_px if crop_px_min is None else crop_px_min
    sizes = pose_sizes(data, instances, smallest, crop_px) if smallest < crop_px else {crop_px: list(instances)}
    if len(sizes) == 1:
        size, pool = next(iter(sizes.items()))
    else:
        weights = np.array([len(pool) / crops_per_batch(batch, s, smallest) for s, pool in sizes.items()])
        size = list(sizes)[int(rng.choice(len(sizes), p=weights / weights.sum()))]
        pool = sizes[size]
    n = crops_per_batch(batch, size, smallest)
    picks = rng.choice(pool, size=n, replace=len(pool) < n)
    out_px = size // COORD_STRIDE
    crops = np.zeros((n, size, size, 3), np.uint8)
    coords = np.zeros((n, 3, out_px, out_px), np.float32)
    masks = np.zeros((n, 1, out_px, out_px), np.float32)
    classes = np.zeros(n, np.int64)
    for b, k in enumerate(picks):
        inst = data.instances[int(k)]
        record = data.images[inst.image]
        centre, side = jittered_crop(inst.box_crop, rng)
        crops[b] = _augmented_crop(record.rgb_crop, centre, side, size, rng)
        A = crop_affine(centre, side, out_px)
        A[:, 2] += A[:, :2] @ np.asarray(inst.region, dtype=np.float64)  # region pixels -> crop pixels
        warp = dict(dsize=(out_px, out_px), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        coords[b] = np.moveaxis(cv2.warpAffine(inst.coords.astype(np.float32), A, **warp), -1, 0)
        masks[b, 0] = cv2.warpAffine(inst.mask.astype(np.uint8), A, **warp)
        classes[b] = inst.class_index
    return {"crops": normalise(crops), "classes": classes, "coords": coords, "masks": masks}


def _augmented_crop(rgb: NDArray[np.uint8], centre: tuple[float, float], side: float, size: int,
                    rng: np.random.Generator) -> NDArray[np.uint8]:
    """The crop of ``rgb`` after :func:`augment` of the image's pixels under it (noise at the image's
    own resolution, as a camera's; only that part of the image is touched)."""
    h, w = rgb.shape[:2]
    half = side / 2.0 + 2.0
    x0, y0 = max(0, int(centre[0] - half)), max(0, int(centre[1] - half))
    x1, y1 = min(w, int(math.ceil(centre[0] + half)) + 1), min(h, int(math.ceil(centre[1] + half)) + 1)
    if x1 <= x0 or y1 <= y0:
        return warp_rgb(rgb, centre, side, size)
    part = augment(rgb[y0:y1, x0:x1], rng)
    return warp_rgb(part, (centre[0] - x0, centre[1] - y0), side, size)

"""Zoomed-in crops (GDR-Net's dynamic zoom-in) and image normalisation, shared by training and inference.

A crop is a square of side ``side`` centred at ``centre`` (image pixels, OpenCV's pixel-centre
convention), resampled to ``size`` pixels: output pixel ``x_out`` shows image point
``(x_out - (size - 1) / 2) * side / size + cx``. :func:`crop_affine` is that map (image -> crop)
for ``cv2.warpAffine``; :func:`crop_to_image` maps crop pixels back for PnP.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
#: A detected or true box is padded to this many times its longer side (GDR-Net's 1.5).
CROP_PAD = 1.5
_MEAN, _STD = 0.45, 0.25


def crop_affine(centre: tuple[float, float], side: float, size: int) -> Array:
    """The 2x3 map from image pixels to crop pixels (see the module docstring)."""
    k = size / side
    c = (size - 1) / 2.0
    return np.array([[k, 0.0, c - k * centre[0]], [0.0, k, c - k * centre[1]]])


def crop_to_image(xy: Array, centre: tuple[float, float], side: float, size: int) -> Array:
    """Crop pixel coordinates (N, 2) of a ``size`` crop -> image pixel coordinates."""
    k = size / side
    c = (size - 1) / 2.0
    return (np.asarray(xy, dtype=np.float64) - c) / k + np.asarray(centre, dtype=np.float64)


def box_crop(box: tuple[float, float, float, float], pad: float = CROP_PAD) -> tuple[tuple[float, float], float]:
    """Centre and side of the square crop around ``box`` (x0, y0, x1, y1; pixel edges)."""
    x0, y0, x1, y1 = box
    centre = ((x0 + x1) / 2.0 - 0.5, (y0 + y1) / 2.0 - 0.5)
    return centre, max(x1 - x0, y1 - y0, 1.0) * pad


def crop_size(side: float, smallest: int, largest: int) -> int:
    """Pixels of the crop of a box whose padded crop measures ``side`` source pixels: the side itself,
    rounded up to a multiple of 16 (the coordinate net's input grain), within ``[smallest, largest]``.
    A near object's crop keeps the detail it shows (what an active agent comes closer for), a far
    one's is not blown up past its own pixels."""
    if not (math.isfinite(side) and side > 0):
        return int(smallest)
    return int(min(max(16 * math.ceil(side / 16.0), smallest), largest))


def crops_per_batch(batch: int, size: int, smallest: int) -> int:
    """How many ``size``-pixel crops make a training batch of ``batch`` crops of the ``smallest`` size: as
    many pixels (fewer, larger crops), so a step costs about the same whatever its crops' size."""
    return max(1, round(batch * (smallest / size) ** 2))


def warp_rgb(rgb: NDArray[np.uint8], centre: tuple[float, float], side: float, size: int) -> NDArray[np.uint8]:
    """The crop of ``rgb`` (bilinear, zeros outside the image)."""
    import cv2

    return cv2.warpAffine(rgb, crop_affine(centre, side, size), (size, size), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))


def normalise(images: NDArray[np.uint8]) -> NDArray[np.float32]:
    """uint8 (..., H, W, 3) -> float32 (..., 3, H, W), roughly zero-mean unit-variance."""
    x = np.asarray(images, dtype=np.float32) / 255.0
    return np.moveaxis((x - _MEAN) / _STD, -1, -3).copy()


def iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    """Intersection over union of two (x0, y0, x1, y1) boxes (0 for empty ones)."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0

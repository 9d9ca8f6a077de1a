"""PSNR and SSIM of two 8-bit RGB images in NumPy (the training stage's definitions: images in
[0, 1], SSIM with an 11 px Gaussian window of sigma 1.5 and zero padding, pixels outside ``valid``
-- the undistorted border without raw data -- left out: PSNR averages over the valid pixels, SSIM
fills the second image's invalid pixels from the first), for comparisons outside a training run."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError

SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def _unit(image: NDArray[np.uint8], what: str) -> NDArray[np.float64]:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3:
        raise DataError(f"{what}: expected an RGB image (H, W, 3), got shape {a.shape}")
    return a.astype(np.float64) / 255.0


def _pair(a: NDArray[np.uint8], b: NDArray[np.uint8], valid: NDArray[np.bool_] | None, what: str
          ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    x, y = _unit(a, f"{what}: first image"), _unit(b, f"{what}: second image")
    if x.shape != y.shape:
        raise DataError(f"{what}: image sizes differ: {x.shape} vs {y.shape}")
    mask = np.ones(x.shape[:2], dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if mask.shape != x.shape[:2]:
        raise DataError(f"{what}: valid mask is {mask.shape}, the images are {x.shape[:2]}")
    if not mask.any():
        raise DataError(f"{what}: no valid pixel to compare")
    return x, y, mask


def psnr(a: NDArray[np.uint8], b: NDArray[np.uint8], valid: NDArray[np.bool_] | None = None) -> float:
    """Peak signal-to-noise ratio (dB) of two RGB images of one size over ``valid``; 100 dB when identical."""
    x, y, mask = _pair(a, b, valid, "psnr")
    return -10.0 * math.log10(max(float(np.mean((x[mask] - y[mask]) ** 2)), 1e-10))


def ssim(a: NDArray[np.uint8], b: NDArray[np.uint8], valid: NDArray[np.bool_] | None = None) -> float:
    """Mean SSIM of two RGB images of one size (1 when identical; see the module docstring for ``valid``)."""
    from scipy.ndimage import gaussian_filter

    x, y, mask = _pair(a, b, valid, "ssim")
    y = np.where(mask[..., None], y, x)

    def blur(t: NDArray[np.float64]) -> NDArray[np.float64]:
        return gaussian_filter(t, sigma=(SSIM_SIGMA, SSIM_SIGMA, 0), truncate=3.5, mode="constant")

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (sxx + syy + SSIM_C2)
    return float(np.mean(num / den))

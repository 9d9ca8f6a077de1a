"""SSIM's constants and window (Inria's definition), shared by the reference SSIM
(:mod:`brave6d.training.losses`) and the fused CPU one (:mod:`brave6d.training.fused_ssim`).

An 11x11 Gaussian window (sigma 1.5), C1 = 0.01^2 and C2 = 0.03^2 for images in [0, 1]. Its own
module so that the loss can call the fused SSIM and the fused SSIM can read the constants without
either importing the other.
"""

from __future__ import annotations

import torch
from torch import Tensor

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, dtype: torch.dtype = torch.float32) -> Tensor:
    """The normalised 1D Gaussian ``[size]`` whose outer product is the SSIM window."""
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype)

"""Image losses and metrics of 3DGS training: L1, SSIM (Inria's definition) and PSNR.

SSIM uses an 11x11 Gaussian window (sigma 1.5), C1 = 0.01^2 and C2 = 0.03^2 for images in
[0, 1], zero padding at the border and the mean over pixels and channels, exactly as the Inria
reference computes it, so that numbers are comparable with published 3DGS results.
Images are ``[H, W, 3]`` or ``[B, H, W, 3]`` float tensors in [0, 1] (gsplat's layout).
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import Tensor

from brave6d.training.ssim_window import SSIM_C1, SSIM_C2, SSIM_WINDOW, gaussian_window

__all__ = ["PSNR_MAX", "SSIM_C1", "SSIM_C2", "SSIM_WINDOW", "fill_invalid", "gaussian_window", "l1_loss",
           "photometric_loss", "psnr", "psnr_tensor", "ssim", "ssim_map"]


def _to_nchw(img: Tensor) -> Tensor:
    if img.dim() == 3:
        img = img[None]
    if img.dim() != 4 or img.shape[-1] not in (1, 3):
        raise ValueError(f"expected an image [H, W, C] or [B, H, W, C] with C in (1, 3), got {list(img.shape)}")
    return img.permute(0, 3, 1, 2)


@functools.lru_cache(maxsize=16)
def _ssim_window(channels: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The depthwise 11x11 window for ``channels``, built once per dtype and device (on a GPU a
    window rebuilt per call is a host-to-device copy every training step)."""
    g = gaussian_window(dtype=dtype).to(device)
    return (g[:, None] * g[None, :]).expand(channels, 1, SSIM_WINDOW, SSIM_WINDOW).contiguous()


def ssim_map(img1: Tensor, img2: Tensor) -> Tensor:
    """Per-pixel SSIM ``[B, C, H, W]`` of two images with the same shape."""
    if img1.shape != img2.shape:
        raise ValueError(f"ssim: shapes differ: {list(img1.shape)} vs {list(img2.shape)}")
    x, y = _to_nchw(img1), _to_nchw(img2)
    c = x.shape[1]
    # one depthwise 11x11 convolution (faster on CPU than two separable 1D passes)
    window = _ssim_window(c, x.dtype, x.device)
    pad = SSIM_WINDOW // 2

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(t, window, padding=pad, groups=c)

    mu_x, mu_y = blur(x), blur(y)
    mu_x2, mu_y2, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    sigma_x2 = blur(x * x) - mu_x2
    sigma_y2 = blur(y * y) - mu_y2
    sigma_xy = blur(x * y) - mu_xy
    num = (2.0 * mu_xy + SSIM_C1) * (2.0 * sigma_xy + SSIM_C2)
    den = (mu_x2 + mu_y2 + SSIM_C1) * (sigma_x2 + sigma_y2 + SSIM_C2)
    return num / den


def ssim(img1: Tensor, img2: Tensor) -> Tensor:
    """Mean SSIM (a scalar tensor, differentiable)."""
    return ssim_map(img1, img2).mean()


def l1_loss(img1: Tensor, img2: Tensor) -> Tensor:
    """Mean absolute difference."""
    return (img1 - img2).abs().mean()


def photometric_loss(render: Tensor, target: Tensor, ssim_lambda: float = 0.2) -> tuple[Tensor, Tensor, Tensor]:
    """``(1 - lambda) * L1 + lambda * (1 - SSIM)``; returns ``(loss, l1, ssim)``.

    On the CPU the SSIM term is :func:`brave6d.training.fused_ssim.fused_ssim` (the same number, its
    gradient in compiled loops); on a GPU :func:`brave6d.training.ssim_device.device_ssim` (Triton
    kernels); elsewhere torch's autograd through :func:`ssim`. Imported here, not above: numba is
    the CPU path's dependency only, triton the GPU's.
    """
    from brave6d.training.fused_ssim import can_fuse, fused_ssim

    l1 = l1_loss(render, target)
    if can_fuse(render, target):
        s = fused_ssim(render, target)
    elif render.device.type == "cuda":
        from brave6d.training.ssim_device import can_fuse_on_device, device_ssim

        s = device_ssim(render, target) if can_fuse_on_device(render, target) else ssim(render, target)
    else:
        s = ssim(render, target)
    return (1.0 - ssim_lambda) * l1 + ssim_lambda * (1.0 - s), l1, s


#: PSNR reported for a perfect reconstruction (MSE is floored at 1e-10).
PSNR_MAX = 100.0


def fill_invalid(target: Tensor, render: Tensor, valid: Tensor | None) -> Tensor:
    """``target`` with its invalid pixels replaced by the (detached) render.

    Undistortion leaves pixels at the image border that no raw pixel maps to (black). Replacing
    them by the render makes their L1 term zero (no L1 gradient) and SSIM windows there compare
    the render with itself, so what the border holds changes neither the loss nor the scores.
    ``valid``: bool [H, W] (None: every pixel is valid).
    """
    if valid is None:
        return target
    return torch.where(valid[..., None], target, render.detach())


def psnr_tensor(img1: Tensor, img2: Tensor, valid: Tensor | None = None) -> Tensor:
    """:func:`psnr` as a 0-d tensor on the images' device, without waiting for it (the trainer's
    lean GPU step reads it only at its curve interval)."""
    sq = (img1.detach().float() - img2.detach().float()) ** 2
    if valid is not None:
        mse = (sq * valid[..., None]).sum() / (valid.sum().clamp(min=1) * sq.shape[-1])
    else:
        mse = sq.mean()
    return -10.0 * torch.log10(mse.clamp(min=1e-10))


def psnr(img1: Tensor, img2: Tensor, valid: Tensor | None = None) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (capped at 100 dB).

    ``valid``: bool [H, W]; the mean squared error is taken over those pixels only.
    """
    sq = (img1.detach().float() - img2.detach().float()) ** 2
    if valid is not None:
        count = int(valid.sum())
        mse = float(sq[valid].sum()) / (count * sq.shape[-1]) if count else 0.0
    else:
        mse = float(sq.mean())
    return -10.0 * math.log10(max(mse, 1e-10))

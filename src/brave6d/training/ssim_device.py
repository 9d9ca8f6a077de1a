"""SSIM fused on the device: Triton kernels for the forward pass and its gradient (issue #46).

On CUDA, :func:`brave6d.training.losses.photometric_loss` takes its SSIM term from here: two
kernels per step (the five windowed moments of every pixel in registers, then the gradient), where
autograd through :func:`brave6d.training.losses.ssim` runs five convolutions and 24 nodes. The
same number as that SSIM (Inria's definition: 11x11 Gaussian window, sigma 1.5, zero padding, the
mean over pixels and channels) up to float32 rounding. The window lives on the device, built once.

CPU tensors run the same kernels through Triton's interpreter when ``TRITON_INTERPRET=1`` was set
before triton's first import (the tests; CPU training uses :mod:`brave6d.training.fused_ssim`).
"""

from __future__ import annotations

import functools
from typing import Any

import torch
from torch import Tensor

from brave6d.core.triton_support import compile_ahead, interpreting
from brave6d.training.ssim_window import SSIM_C1, SSIM_C2, SSIM_WINDOW, gaussian_window

BLOCK = (16, 32)  # rows x columns per program


def can_fuse_on_device(render: Tensor, target: Tensor) -> bool:
    """Whether :func:`device_ssim` applies: an ``[H, W, C]`` float32 pair on a CUDA device with
    triton installed (or on the CPU under Triton's interpreter), the target constant."""
    if not (render.dtype == torch.float32 and target.dtype == torch.float32 and render.dim() == 3
            and render.shape == target.shape and render.device == target.device and not target.requires_grad):
        return False
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return render.device.type == "cuda" or interpreting()


@functools.lru_cache(maxsize=8)
def _window(device: torch.device) -> Tensor:
    return gaussian_window(dtype=torch.float32).to(device)


def _planes(img: Tensor) -> Tensor:
    return img.detach().permute(2, 0, 1).contiguous()  # [C, H, W]


def _grid(c: int, h: int, w: int) -> tuple[int, int, int]:
    return (c, -(-h // BLOCK[0]), -(-w // BLOCK[1]))


class _DeviceSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, render: Tensor, target: Tensor) -> Tensor:
        from brave6d.training._ssim_triton import ssim_fwd_kernel

        x, y = _planes(render), _planes(target)
        c, h, w = x.shape
        maps = [torch.empty_like(x) for _ in range(4)]
        ssim_fwd_kernel[_grid(c, h, w)](x, y, _window(x.device), *maps, h, w, C1=SSIM_C1, C2=SSIM_C2,
                                        RADIUS=SSIM_WINDOW // 2, BH=BLOCK[0], BW=BLOCK[1])
        ctx.save_for_backward(x, y, *maps[1:])
        return maps[0].mean()

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor, None]:
        from brave6d.training._ssim_triton import ssim_bwd_kernel

        x, y, d_mu, d_xx, d_xy = ctx.saved_tensors
        c, h, w = x.shape
        g = grad_out / x.numel()  # d mean / d map
        grad = torch.empty_like(x)
        ssim_bwd_kernel[_grid(c, h, w)](x, y, _window(x.device), (g * d_mu).contiguous(), (g * d_xx).contiguous(),
                                        (g * d_xy).contiguous(), grad, h, w, RADIUS=SSIM_WINDOW // 2,
                                        BH=BLOCK[0], BW=BLOCK[1])
        return grad.permute(1, 2, 0), None


def device_ssim(render: Tensor, target: Tensor) -> Tensor:
    """Mean SSIM of ``render`` against the constant ``target`` ([H, W, C] float32), differentiable
    with respect to ``render``; see the module doc."""
    if not can_fuse_on_device(render, target):
        raise ValueError(f"device_ssim: needs one [H, W, C] float32 pair on a CUDA device (or Triton's "
                         f"interpreter), the target without grad; got {list(render.shape)} {render.dtype} "
                         f"on {render.device} and {list(target.shape)} {target.dtype} on {target.device}")
    return _DeviceSSIM.apply(render, target)


_SIGNATURES = {
    "fwd": {"x_ptr": "*fp32", "y_ptr": "*fp32", "win_ptr": "*fp32", "map_ptr": "*fp32", "d_mu_ptr": "*fp32",
            "d_xx_ptr": "*fp32", "d_xy_ptr": "*fp32", "height": "i32", "width": "i32",
            "C1": "constexpr", "C2": "constexpr", "RADIUS": "constexpr", "BH": "constexpr", "BW": "constexpr"},
    "bwd": {"x_ptr": "*fp32", "y_ptr": "*fp32", "win_ptr": "*fp32", "g_mu_ptr": "*fp32", "g_xx_ptr": "*fp32",
            "g_xy_ptr": "*fp32", "grad_ptr": "*fp32", "height": "i32", "width": "i32",
            "RADIUS": "constexpr", "BH": "constexpr", "BW": "constexpr"},
}


def compile_ssim_kernels(arch: int = 90) -> dict[str, dict[str, Any]]:
    """Compile both kernels ahead of time for CUDA compute capability ``arch`` without a GPU (the
    build check CI runs); Triton's stages by kernel (``fwd``, ``bwd``) and name."""
    from brave6d.training._ssim_triton import ssim_bwd_kernel, ssim_fwd_kernel

    shared = {"RADIUS": SSIM_WINDOW // 2, "BH": BLOCK[0], "BW": BLOCK[1]}
    return {"fwd": compile_ahead(ssim_fwd_kernel, _SIGNATURES["fwd"], {"C1": SSIM_C1, "C2": SSIM_C2, **shared}, arch),
            "bwd": compile_ahead(ssim_bwd_kernel, _SIGNATURES["bwd"], shared, arch)}


__all__ = ["can_fuse_on_device", "compile_ssim_kernels", "device_ssim"]

"""SSIM with a hand-written gradient for CPU training: the training loss's SSIM in two passes.

Autograd through :func:`brave6d.training.losses.ssim` (the reference) runs about twenty image-sized torch operations
forward and forty backward (about 20 ms per 320x200 step on 2 cores, as much as a fifth of a
CPU training step). This computes the same number (Inria's definition: 11x11 Gaussian window,
sigma 1.5, zero padding, C1 = 0.01^2, C2 = 0.03^2) and its gradient with respect to the
rendered image in compiled loops: five separable blurs forward, three backward, using the
closed form of the per-pixel derivatives (as the CUDA ``fused-ssim`` kernel of Taming 3DGS
does). ``tests/test_fused_ssim.py`` checks value and gradient against the torch reference.

With ``S = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2))``,
``s_x^2 = E[x^2] - mu_x^2`` and ``s_xy = E[xy] - mu_x mu_y`` (E: the Gaussian blur), the
gradient of ``mean(S)`` at pixel ``p`` is ``blur(dS/dmu_x) + 2 x_p blur(dS/dE[x^2]) +
y_p blur(dS/dE[xy])`` (the window is symmetric, so the blur is its own adjoint).

The forward moments are blurred in float64: ``E[x^2] - mu^2`` cancels two numbers near ``mu^2``,
and in float32 that left errors of 5e-5 in S on flat images (against C2 = 9e-4), more than torch's
float32 reference. Products of float32 pixels are exact in float64, so S is the float64
reference's to rounding; it costs about 3 ms per 320x200 call on 2 cores (9.5 -> 12.8 ms, median
of 40, forward and backward), about 2 % of a ``fast`` step. The backward blur stays float32.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from brave6d.training.ssim_window import SSIM_C1, SSIM_C2, gaussian_window

_TAPS = gaussian_window().numpy().astype(np.float32)
_TAPS64 = gaussian_window(dtype=torch.float64).numpy()
_C1 = float(SSIM_C1)
_C2 = float(SSIM_C2)
_MATH = {"contract"}  # FMA only: no reassociation, NaN/inf stay visible


@njit(parallel=True, cache=True, fastmath=_MATH)
def blur_planes(src: np.ndarray, taps: np.ndarray, out: np.ndarray) -> None:
    """``out[c] = src[c]`` convolved with ``taps`` along rows, then columns (zero padding).

    Each row is copied into a zero-padded buffer and the row-blurred plane gets zero rows above
    and below, so every inner loop runs over contiguous pixels with non-negative indices: LLVM
    vectorises it (6x faster than clamping the tap range per pixel).
    """
    n_planes, h, w = src.shape
    n_taps = taps.shape[0]
    r = n_taps // 2
    for c in prange(n_planes):
        plane, result = src[c], out[c]
        rows = np.zeros((h + 2 * r, w), src.dtype)  # the row-blurred plane between r zero rows
        padded = np.zeros(w + 2 * r, src.dtype)
        for i in range(h):
            padded[r:r + w] = plane[i]
            row = rows[i + r]
            for t in range(n_taps):
                tap = taps[t]
                for j in range(w):
                    row[j] += tap * padded[j + t]
        for i in range(h):
            line = result[i]
            line[:] = 0.0
            for t in range(n_taps):
                tap = taps[t]
                row = rows[i + t]
                for j in range(w):
                    line[j] += tap * row[j]


@njit(parallel=True, cache=True, fastmath=_MATH)
def _moments(x: np.ndarray, y: np.ndarray, out: np.ndarray) -> None:
    """``[H, W, C]`` float32 images -> float64 planes ``x, y, x^2, y^2, xy`` (``[5C, H, W]``)."""
    h, w, n_ch = x.shape
    for i in prange(h):
        for j in range(w):
            for c in range(n_ch):
                a, b = np.float64(x[i, j, c]), np.float64(y[i, j, c])
                out[c, i, j] = a
                out[n_ch + c, i, j] = b
                out[2 * n_ch + c, i, j] = a * a
                out[3 * n_ch + c, i, j] = b * b
                out[4 * n_ch + c, i, j] = a * b


@njit(parallel=True, cache=True, fastmath=_MATH)
def _ssim_and_partials(blurred: np.ndarray, partials: np.ndarray) -> float:
    """Mean SSIM from the blurred moments; ``partials`` gets dS/dmu_x, dS/dE[x^2], dS/dE[xy]."""
    n_ch = blurred.shape[0] // 5
    h, w = blurred.shape[1], blurred.shape[2]
    row_sums = np.zeros(h, np.float64)
    for i in prange(h):
        acc = 0.0
        for c in range(n_ch):
            for j in range(w):
                mx, my = blurred[c, i, j], blurred[n_ch + c, i, j]
                exx, eyy, exy = blurred[2 * n_ch + c, i, j], blurred[3 * n_ch + c, i, j], blurred[4 * n_ch + c, i, j]
                a1 = 2.0 * mx * my + _C1
                a2 = 2.0 * (exy - mx * my) + _C2
                b1 = mx * mx + my * my + _C1
                b2 = (exx - mx * mx) + (eyy - my * my) + _C2
                den = b1 * b2
                s = a1 * a2 / den
                acc += s
                partials[c, i, j] = (2.0 * my * (a2 - a1) - 2.0 * mx * s * (b2 - b1)) / den
                partials[n_ch + c, i, j] = -s / b2
                partials[2 * n_ch + c, i, j] = 2.0 * a1 / den
        row_sums[i] = acc
    return row_sums.sum() / (n_ch * h * w)


@njit(parallel=True, cache=True, fastmath=_MATH)
def _combine(x: np.ndarray, y: np.ndarray, blurred_partials: np.ndarray, scale: np.float32, grad: np.ndarray) -> None:
    """``grad = scale * (blur(dS/dmu_x) + 2 x blur(dS/dE[x^2]) + y blur(dS/dE[xy]))`` in ``[H, W, C]``."""
    h, w, n_ch = x.shape
    for i in prange(h):
        for j in range(w):
            for c in range(n_ch):
                g = (blurred_partials[c, i, j] + np.float32(2.0) * x[i, j, c] * blurred_partials[n_ch + c, i, j]
                     + y[i, j, c] * blurred_partials[2 * n_ch + c, i, j])
                grad[i, j, c] = scale * g


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, render: Tensor, target: Tensor) -> Tensor:  # type: ignore[override]
        x = render.detach().contiguous().numpy()
        y = target.detach().contiguous().numpy()
        h, w, n_ch = x.shape
        moments = np.empty((5 * n_ch, h, w), np.float64)
        _moments(x, y, moments)
        blurred = np.empty_like(moments)
        blur_planes(moments, _TAPS64, blurred)
        partials = np.empty((3 * n_ch, h, w), np.float32)
        value = _ssim_and_partials(blurred, partials)
        ctx.saved = (x, y, partials)
        return torch.tensor(value, dtype=render.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        x, y, partials = ctx.saved
        blurred = np.empty_like(partials)
        blur_planes(partials, _TAPS, blurred)
        grad = np.empty_like(x)
        _combine(x, y, blurred, np.float32(float(grad_out) / x.size), grad)
        return torch.from_numpy(grad), None


def can_fuse(render: Tensor, target: Tensor) -> bool:
    """Whether :func:`fused_ssim` applies: one ``[H, W, C]`` float32 CPU image pair, the target constant."""
    return (render.device.type == "cpu" and target.device.type == "cpu" and render.dtype == torch.float32
            and target.dtype == torch.float32 and render.dim() == 3 and render.shape == target.shape
            and render.shape[-1] in (1, 3) and not target.requires_grad)


def fused_ssim(render: Tensor, target: Tensor) -> Tensor:
    """Mean SSIM of ``render`` against the constant ``target`` (``[H, W, C]`` float32 on the CPU),
    differentiable with respect to ``render``; equal to :func:`brave6d.training.losses.ssim` up to float32
    rounding."""
    if not can_fuse(render, target):
        raise ValueError("fused_ssim takes two [H, W, C] float32 CPU images of one shape, the target without "
                         f"gradient; got {list(render.shape)} {render.dtype} {render.device} and "
                         f"{list(target.shape)} {target.dtype} {target.device}")
    return _FusedSSIM.apply(render, target)

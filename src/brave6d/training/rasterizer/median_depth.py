"""Median depth from projected Gaussians and their tile lists, on the GPU (Triton).

gsplat renders colour and expected depth but no median depth; this computes it from what one
gsplat call already made (``meta``: ``means2d``, ``conics``, ``opacities``, ``depths``,
``isect_offsets``, ``flatten_ids``), so a served frame is rasterised once, on the device.
The definition is the CPU kernel's (``kernels._fwd_tile``): per pixel, the depth of the Gaussian
whose compositing takes the transmittance from above 0.5 to 0.5 or below, 0 where it never does,
with gsplat's alpha rules (alpha = min(0.999, o exp(-sigma)), skipped if sigma < 0 or alpha <
1/255, pixel centres at +0.5).

CPU tensors run the same Triton kernel through Triton's interpreter when ``TRITON_INTERPRET=1`` was
set before triton's first import (slow: for tests, which is how CI proves the kernel against the
CPU rasterizer without a GPU; CPU renders get their median from the CPU rasterizer itself). :func:`tile_intersections`
builds gsplat's tile lists in torch for callers that have projections but no gsplat ``meta``.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from brave6d.core.triton_support import compile_ahead, interpreting

from .constants import ALPHA_MAX, ALPHA_THRESHOLD, TILE_SIZE
from ._validation import RasterBackendError, RasterInputError


def tile_intersections(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int,
                       tile_size: int = TILE_SIZE) -> tuple[Tensor, Tensor]:
    """gsplat's ``isect_tiles`` + ``isect_offset_encode`` (non-packed) in torch.

    Args:
        means2d: [C,N,2] pixel centres in gsplat's convention; radii: [C,N,2] (0: culled);
        depths: [C,N] camera depths (positive for every Gaussian with radii > 0).

    Returns:
        ``(isect_offsets [C,TH,TW] int32, flatten_ids [M] int32)``: each tile's first entry in
        ``flatten_ids``, which lists indices into the flattened [C*N] Gaussians by camera, tile and
        depth (ties by index), the order gsplat's radix sort gives.
    """
    c, n = depths.shape
    device = means2d.device
    tile_w, tile_h = math.ceil(width / tile_size), math.ceil(height / tile_size)
    t_mean = means2d.detach().float() / tile_size
    t_rad = radii.float() / tile_size
    lo = torch.floor(t_mean - t_rad).long()
    hi = torch.ceil(t_mean + t_rad).long()
    limit = torch.tensor([tile_w, tile_h], device=device)
    lo = torch.minimum(lo.clamp(min=0), limit)
    hi = torch.minimum(hi.clamp(min=0), limit)
    box = (hi - lo).clamp(min=0)
    counts = (box[..., 0] * box[..., 1] * (radii > 0).all(dim=-1)).reshape(-1)  # [C*N]
    gauss = torch.repeat_interleave(torch.arange(c * n, device=device), counts)
    first = torch.cumsum(counts, 0) - counts
    j = torch.arange(gauss.numel(), device=device) - first[gauss]
    box_w = box.reshape(-1, 2)[gauss, 0]
    tx = lo.reshape(-1, 2)[gauss, 0] + j % box_w.clamp(min=1)
    ty = lo.reshape(-1, 2)[gauss, 1] + j // box_w.clamp(min=1)
    image = gauss // n
    tile = (image * tile_h + ty) * tile_w + tx
    depth = depths.detach().float().reshape(-1)[gauss].double()
    order = torch.argsort(depth, stable=True)  # depth within a tile, then index
    order = order[torch.argsort(tile[order], stable=True)]
    tile_counts = torch.bincount(tile, minlength=c * tile_h * tile_w)
    offsets = (torch.cumsum(tile_counts, 0) - tile_counts).reshape(c, tile_h, tile_w)
    return offsets.to(torch.int32), gauss[order].to(torch.int32)


def median_depth(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor,
                 isect_offsets: Tensor, flatten_ids: Tensor, width: int, height: int,
                 tile_size: int = TILE_SIZE) -> Tensor:
    """The median depth image [C,H,W,1] from projected Gaussians and their tile lists.

    Args:
        means2d [C,N,2], conics [C,N,3], opacities [C,N] (after any antialiasing compensation),
        depths [C,N]: gsplat's projection (``meta`` of a non-packed ``rasterization``);
        isect_offsets [C,TH,TW], flatten_ids [M]: its tile lists (or :func:`tile_intersections`).

    CUDA tensors run the compiled Triton kernel; CPU tensors its interpreter (tests).

    Raises:
        RasterBackendError: triton is missing, or CPU tensors without the interpreter.
        RasterInputError: ``isect_offsets`` does not match the cameras and image size.
    """
    try:
        from ._median_triton import median_depth_kernel
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise RasterBackendError("median_depth needs triton (installed with torch's CUDA wheels; "
                                 "pip install triton for the CPU interpreter)") from exc
    if tile_size * tile_size & (tile_size * tile_size - 1):
        raise RasterInputError(f"median_depth: tile_size {tile_size} must be a power of two")
    c, n = depths.shape
    tile_w, tile_h = math.ceil(width / tile_size), math.ceil(height / tile_size)
    if tuple(isect_offsets.shape) != (c, tile_h, tile_w):
        raise RasterInputError(f"median_depth: isect_offsets has shape {tuple(isect_offsets.shape)}, "
                               f"expected {(c, tile_h, tile_w)} for {c} cameras at {width}x{height}")
    device = depths.device
    if device.type != "cuda" and not interpreting():
        raise RasterBackendError(
            f"median_depth: tensors on {device} need Triton's interpreter: set TRITON_INTERPRET=1 "
            "before triton is first imported (tests), or render on the CPU with "
            "rasterize(..., median_depth=True)")
    f32 = torch.float32
    offsets = torch.cat([isect_offsets.reshape(-1).to(torch.int32),
                         torch.tensor([flatten_ids.numel()], dtype=torch.int32, device=device)])
    out = torch.zeros(c, height, width, 1, dtype=f32, device=device)
    if c == 0 or width == 0 or height == 0:
        return out
    median_depth_kernel[(c * tile_h * tile_w,)](
        means2d.detach().to(f32).contiguous(), conics.detach().to(f32).contiguous(),
        opacities.detach().to(f32).contiguous(), depths.detach().to(f32).contiguous(),
        offsets, flatten_ids.to(torch.int32).contiguous(), out,
        width, height, tile_w, tile_w * tile_h,
        TILE=tile_size, BLOCK=tile_size * tile_size, ALPHA_MAX=ALPHA_MAX, ALPHA_MIN=ALPHA_THRESHOLD,
    )
    return out


_KERNEL_SIGNATURE = {
    "means2d_ptr": "*fp32", "conics_ptr": "*fp32", "opacities_ptr": "*fp32", "depths_ptr": "*fp32",
    "offsets_ptr": "*i32", "ids_ptr": "*i32", "out_ptr": "*fp32",
    "width": "i32", "height": "i32", "tile_w": "i32", "tiles_per_image": "i32",
    "TILE": "constexpr", "BLOCK": "constexpr", "ALPHA_MAX": "constexpr", "ALPHA_MIN": "constexpr",
}


def compile_median_kernel(arch: int = 90, tile_size: int = TILE_SIZE) -> dict[str, Any]:
    """Compile the kernel ahead of time for CUDA compute capability ``arch`` (90: H100/H200),
    without a GPU (Triton ships its own ptxas): the build check CI runs. Returns Triton's
    stages by name (``ttir``, ``ptx``, ``cubin``, ...)."""
    from ._median_triton import median_depth_kernel

    constants = {"TILE": tile_size, "BLOCK": tile_size * tile_size,
                 "ALPHA_MAX": ALPHA_MAX, "ALPHA_MIN": ALPHA_THRESHOLD}
    return compile_ahead(median_depth_kernel, _KERNEL_SIGNATURE, constants, arch)


__all__ = ["compile_median_kernel", "median_depth", "tile_intersections"]

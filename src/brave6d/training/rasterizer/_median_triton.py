"""The median-depth kernel in Triton: one program per screen tile, gsplat's alpha rules.

Imported only when a median depth is asked for. With ``TRITON_INTERPRET=1`` set before triton is
first imported, Triton's interpreter runs the same kernel body on CPU tensors with NumPy: how CI
proves it against the CPU rasterizer without a GPU. See
:mod:`brave6d.training.rasterizer.median_depth` for the contract.
"""

from __future__ import annotations

import triton
import triton.language as tl


@triton.jit
def median_depth_kernel(
    means2d_ptr, conics_ptr, opacities_ptr, depths_ptr, offsets_ptr, ids_ptr, out_ptr,
    width, height, tile_w, tiles_per_image,
    TILE: tl.constexpr, BLOCK: tl.constexpr, ALPHA_MAX: tl.constexpr, ALPHA_MIN: tl.constexpr,
):
    """Walk one tile's depth-sorted Gaussians until every pixel's transmittance is <= 0.5.

    A pixel's median depth is the depth of the Gaussian whose compositing takes its
    transmittance from above 0.5 to 0.5 or below (0 where none does). While T > 0.5 gsplat's
    early stop (T <= 1e-4) cannot fire, since alpha <= 0.999, so only the skip rules matter:
    sigma < 0 or alpha < 1/255 leave the pixel unchanged.
    """
    tile = tl.program_id(0)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    image = tile // tiles_per_image
    local = tile % tiles_per_image
    lane = tl.arange(0, BLOCK)
    x = (local % tile_w) * TILE + lane % TILE
    y = (local // tile_w) * TILE + lane // TILE
    inside = (x < width) & (y < height)
    px = x.to(tl.float32) + 0.5
    py = y.to(tl.float32) + 0.5
    trans = tl.full([BLOCK], 1.0, tl.float32)
    median = tl.full([BLOCK], 0.0, tl.float32)
    open_lanes = inside
    n_open = tl.sum(open_lanes.to(tl.int32), axis=0)
    k = start
    while (k < end) & (n_open > 0):
        g = tl.load(ids_ptr + k).to(tl.int64)
        dx = tl.load(means2d_ptr + 2 * g) - px
        dy = tl.load(means2d_ptr + 2 * g + 1) - py
        ca = tl.load(conics_ptr + 3 * g)
        cb = tl.load(conics_ptr + 3 * g + 1)
        cc = tl.load(conics_ptr + 3 * g + 2)
        sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
        alpha = tl.minimum(ALPHA_MAX, tl.load(opacities_ptr + g) * tl.exp(-sigma))
        ok = open_lanes & (sigma >= 0.0) & (alpha >= ALPHA_MIN)
        next_t = trans * (1.0 - alpha)
        trans = tl.where(ok, next_t, trans)
        crossed = ok & (next_t <= 0.5)
        median = tl.where(crossed, tl.load(depths_ptr + g), median)
        open_lanes = open_lanes & (crossed == 0)
        n_open = tl.sum(open_lanes.to(tl.int32), axis=0)
        k += 1
    pixel = image.to(tl.int64) * height * width + y * width + x
    tl.store(out_ptr + pixel, median, mask=inside)


__all__ = ["median_depth_kernel"]

"""Fused SSIM kernels in Triton (forward with its partial derivatives, backward), one program per
image tile of one channel: the 11x11 window's five moments accumulated in registers, no
intermediate maps in memory but the three partials the backward pass needs.

Imported only when the SSIM runs on a GPU, or, with ``TRITON_INTERPRET=1`` set before triton is
first imported, through Triton's interpreter on CPU tensors (the tests). See
:mod:`brave6d.training.ssim_device` for the contract.
"""

from __future__ import annotations

import triton
import triton.language as tl


@triton.jit
def _tile(height, width, BH: tl.constexpr, BW: tl.constexpr):
    """This program's pixels: rows [BH,1], columns [1,BW], its plane's offset and the in-image mask."""
    rows = tl.program_id(1) * BH + tl.arange(0, BH)[:, None]
    cols = tl.program_id(2) * BW + tl.arange(0, BW)[None, :]
    base = tl.program_id(0).to(tl.int64) * height * width
    return rows, cols, base, (rows < height) & (cols < width)


@triton.jit
def _tap(rows, cols, dy, dx, win_ptr, height, width, RADIUS: tl.constexpr):
    """Window tap (dy, dx): its weight, where it lands inside the image, and the offsets there."""
    r = rows + (dy - RADIUS)
    c = cols + (dx - RADIUS)
    ok = (r >= 0) & (r < height) & (c >= 0) & (c < width)
    return tl.load(win_ptr + dy) * tl.load(win_ptr + dx), ok, r * width + c


@triton.jit
def ssim_fwd_kernel(x_ptr, y_ptr, win_ptr, map_ptr, d_mu_ptr, d_xx_ptr, d_xy_ptr, height, width,
                    C1: tl.constexpr, C2: tl.constexpr, RADIUS: tl.constexpr,
                    BH: tl.constexpr, BW: tl.constexpr):
    """SSIM map of planes x, y and dmap/dmu_x, dmap/dE[x^2], dmap/dE[xy] (zero padding)."""
    rows, cols, base, inside = _tile(height, width, BH, BW)
    mu_x = tl.full([BH, BW], 0.0, tl.float32)
    mu_y = tl.full([BH, BW], 0.0, tl.float32)
    e_xx = tl.full([BH, BW], 0.0, tl.float32)
    e_yy = tl.full([BH, BW], 0.0, tl.float32)
    e_xy = tl.full([BH, BW], 0.0, tl.float32)
    for dy in tl.static_range(2 * RADIUS + 1):
        for dx in tl.static_range(2 * RADIUS + 1):
            w, ok, at = _tap(rows, cols, dy, dx, win_ptr, height, width, RADIUS)
            a = tl.load(x_ptr + base + at, mask=ok, other=0.0)
            b = tl.load(y_ptr + base + at, mask=ok, other=0.0)
            mu_x += w * a
            mu_y += w * b
            e_xx += w * a * a
            e_yy += w * b * b
            e_xy += w * a * b
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    num_a = 2.0 * mu_x * mu_y + C1
    num_b = 2.0 * cov + C2
    den_c = mu_x * mu_x + mu_y * mu_y + C1
    den_d = var_x + var_y + C2
    m = num_a * num_b / (den_c * den_d)
    # partials with E[x^2] and E[xy] held fixed (var_x = E[x^2] - mu_x^2, cov = E[xy] - mu_x mu_y)
    d_mu = (2.0 * mu_y * (num_b - num_a) / (den_c * den_d)
            - 2.0 * mu_x * m / den_c + 2.0 * mu_x * m / den_d)
    d_xx = -m / den_d
    d_xy = 2.0 * num_a / (den_c * den_d)
    out = base + rows * width + cols
    tl.store(map_ptr + out, m, mask=inside)
    tl.store(d_mu_ptr + out, d_mu, mask=inside)
    tl.store(d_xx_ptr + out, d_xx, mask=inside)
    tl.store(d_xy_ptr + out, d_xy, mask=inside)


@triton.jit
def ssim_bwd_kernel(x_ptr, y_ptr, win_ptr, g_mu_ptr, g_xx_ptr, g_xy_ptr, grad_ptr, height, width,
                    RADIUS: tl.constexpr, BH: tl.constexpr, BW: tl.constexpr):
    """dL/dx = W * (dL/dm dm/dmu) + 2 x W * (dL/dm dm/dE[x^2]) + y W * (dL/dm dm/dE[xy]) (the
    window is symmetric, so its transpose is itself)."""
    rows, cols, base, inside = _tile(height, width, BH, BW)
    s_mu = tl.full([BH, BW], 0.0, tl.float32)
    s_xx = tl.full([BH, BW], 0.0, tl.float32)
    s_xy = tl.full([BH, BW], 0.0, tl.float32)
    for dy in tl.static_range(2 * RADIUS + 1):
        for dx in tl.static_range(2 * RADIUS + 1):
            w, ok, at = _tap(rows, cols, dy, dx, win_ptr, height, width, RADIUS)
            at = base + at
            s_mu += w * tl.load(g_mu_ptr + at, mask=ok, other=0.0)
            s_xx += w * tl.load(g_xx_ptr + at, mask=ok, other=0.0)
            s_xy += w * tl.load(g_xy_ptr + at, mask=ok, other=0.0)
    out = base + rows * width + cols
    x = tl.load(x_ptr + out, mask=inside, other=0.0)
    y = tl.load(y_ptr + out, mask=inside, other=0.0)
    tl.store(grad_ptr + out, s_mu + 2.0 * x * s_xx + y * s_xy, mask=inside)


__all__ = ["ssim_bwd_kernel", "ssim_fwd_kernel"]

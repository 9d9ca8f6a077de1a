"""Pure-torch reference rasterizer (differentiable by autograd): for tests and benchmarks only.

It implements the same conventions as the CPU kernel and gsplat 1.5.3's CUDA kernels
(projection, SH, opacity-aware radii, 16 px tiles, depth order, alpha cap and threshold,
transmittance stop) with vectorised tensor operations, tile by tile in padded chunks.
It computes in the dtype of its inputs, so tests can run it in float64.  It is slow
(seconds for tens of thousands of Gaussians): never use it for training.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from .constants import (
    ALPHA_MAX,
    ALPHA_THRESHOLD,
    DEPTH_ALPHA_EPS,
    RADIUS_EXTEND,
    RADIUS_MAX,
    T_MIN,
    TILE_SIZE,
)
from ._validation import prepare_inputs


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z), normalised here -> [N, 3, 3] rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    r = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return r.reshape(quats.shape[:-1] + (3, 3))


def project(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor | None,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    antialiased: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """EWA projection -> (radii [C,N,2] int32, means2d [C,N,2], depths [C,N], conics [C,N,3],
    compensations [C,N]).

    With ``opacities`` the radius uses gsplat 1.5.3's opacity-aware bound and Gaussians
    with opacity below 1/255 are culled; without, the plain 3.33 sigma box.
    ``compensations`` is the 2D mip filter's opacity factor
    ``sqrt(clamp(det(cov2d) / det(cov2d + eps2d I), 0, 1))`` when ``antialiased`` (the box
    then uses the compensated opacity), else ones.
    Culled entries are 0 and carry no gradient.
    """
    rot = quat_to_rotmat(quats)
    m = rot * scales[:, None, :]
    covars = m @ m.transpose(-1, -2)
    rv = viewmats[:, :3, :3]
    tv = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", rv, means) + tv[:, None, :]
    covars_c = torch.einsum("cij,njk,clk->cnil", rv, covars, rv)
    x, y, z = means_c.unbind(-1)
    valid = (z >= near_plane) & (z <= far_plane) & (z > 0)
    z_safe = torch.where(valid, z, torch.ones_like(z))

    fx = Ks[:, 0, 0, None]
    fy = Ks[:, 1, 1, None]
    cx = Ks[:, 0, 2, None]
    cy = Ks[:, 1, 2, None]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    tx = z_safe * torch.clamp(x / z_safe, min=-lim_x_neg, max=lim_x_pos)
    ty = z_safe * torch.clamp(y / z_safe, min=-lim_y_neg, max=lim_y_pos)
    zeros = torch.zeros_like(z_safe)
    jac = torch.stack(
        [fx / z_safe, zeros, -fx * tx / z_safe**2, zeros, fy / z_safe, -fy * ty / z_safe**2],
        dim=-1,
    ).reshape(z.shape + (2, 3))
    cov2d = jac @ covars_c @ jac.transpose(-1, -2)
    a = cov2d[..., 0, 0] + eps2d
    b = 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0])
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    valid = valid & (det > 0)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    comp = torch.ones_like(det)
    if antialiased:
        det0 = cov2d[..., 0, 0] * cov2d[..., 1, 1] - b * b
        ratio = det0 / det_safe
        inner = valid & (ratio > 0) & (ratio < 1)
        ratio_safe = torch.where(inner, ratio, torch.ones_like(ratio))  # no inf gradient at 0
        comp = torch.where(inner, torch.sqrt(ratio_safe),
                           (ratio.detach() >= 1).to(ratio.dtype))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)

    with torch.no_grad():
        extend = torch.full_like(z, RADIUS_EXTEND)
        if opacities is not None:
            op = opacities.to(torch.float32)[None].expand_as(z) * comp.detach().to(torch.float32)
            thr = torch.tensor(ALPHA_THRESHOLD, dtype=torch.float32)
            valid = valid & (op >= thr)
            ratio = torch.clamp(op / thr, min=1.0)
            extend = torch.minimum(extend, torch.sqrt(2.0 * torch.log(ratio)).to(z.dtype))
        a_safe = torch.where(valid, a, torch.zeros_like(a)).clamp(min=0)
        c_safe = torch.where(valid, c, torch.zeros_like(c)).clamp(min=0)
        rx = torch.ceil(extend * torch.sqrt(a_safe))
        ry = torch.ceil(extend * torch.sqrt(c_safe))
        valid = valid & ((rx > 0) | (ry > 0))
        u = means2d[..., 0].detach()
        v = means2d[..., 1].detach()
        inside = (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
        valid = valid & inside
        radii = torch.stack([rx, ry], dim=-1).clamp(max=RADIUS_MAX)
        radii = torch.where(valid[..., None], radii, torch.zeros_like(radii)).to(torch.int32)

    keep = valid[..., None]
    means2d = torch.where(keep, means2d, torch.zeros_like(means2d))
    conics = torch.where(keep, conics, torch.zeros_like(conics))
    depths = torch.where(valid, z, torch.zeros_like(z))
    return radii, means2d, depths, conics, comp


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """SH basis [..., (degree + 1)^2] at unit directions (gsplat's order and signs)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree >= 1:
        out += [-0.48860251190292 * y, 0.48860251190292 * z, -0.48860251190292 * x]
    if degree >= 2:
        z2 = z * z
        tb = -1.092548430592079 * z
        c1 = x * x - y * y
        s1 = 2 * x * y
        out += [0.5462742152960395 * s1, tb * y, 0.9461746957575601 * z2 - 0.3153915652525201,
                tb * x, 0.5462742152960395 * c1]
    if degree >= 3:
        tc = -2.285228997322329 * z2 + 0.4570457994644658
        tb3 = 1.445305721320277 * z
        c2 = x * c1 - y * s1
        s2 = x * s1 + y * c1
        out += [-0.5900435899266435 * s2, tb3 * s1, tc * y,
                z * (1.865881662950577 * z2 - 1.119528997770346), tc * x, tb3 * c1,
                -0.5900435899266435 * c2]
    return torch.stack(out, dim=-1)


def sh_colors(degree: int, means: Tensor, coeffs: Tensor, viewmats: Tensor, radii: Tensor) -> Tensor:
    """RGB [C,N,3] from SH coefficients [N,K,3] or [C,N,K,3], shifted by +0.5, clamped at 0."""
    campos = torch.inverse(viewmats.detach().double())[:, :3, 3].to(means.dtype)
    dirs = means[None] - campos[:, None]
    norm = dirs.norm(dim=-1, keepdim=True)
    dirs = dirs / torch.where(norm > 0, norm, torch.ones_like(norm))
    n_basis = (degree + 1) ** 2
    basis = sh_basis(degree, dirs)
    coeffs = coeffs[..., :n_basis, :]
    if coeffs.dim() == 3:
        coeffs = coeffs[None]
    rgb = (basis[..., None] * coeffs).sum(dim=-2)
    visible = (radii > 0).all(dim=-1)
    rgb = torch.where(visible[..., None], rgb, torch.zeros_like(rgb))
    return torch.clamp_min(rgb + 0.5, 0.0)


@torch.no_grad()
def _tile_lists(means2d: Tensor, radii: Tensor, depths: Tensor, tile_w: int, tile_h: int):
    """(tile id, flat Gaussian id) pairs sorted by tile then depth (stable in index)."""
    c, n = depths.shape
    vis = (radii > 0).all(dim=-1).reshape(-1)
    m = means2d.detach().reshape(-1, 2).double()
    r = radii.reshape(-1, 2).double()
    x0 = torch.floor((m[:, 0] - r[:, 0]) / TILE_SIZE).clamp(0, tile_w).long()
    y0 = torch.floor((m[:, 1] - r[:, 1]) / TILE_SIZE).clamp(0, tile_h).long()
    x1 = torch.ceil((m[:, 0] + r[:, 0]) / TILE_SIZE).clamp(0, tile_w).long()
    y1 = torch.ceil((m[:, 1] + r[:, 1]) / TILE_SIZE).clamp(0, tile_h).long()
    counts = torch.where(vis, (x1 - x0) * (y1 - y0), torch.zeros_like(x0))
    total = int(counts.sum())
    ids = torch.repeat_interleave(torch.arange(c * n), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(total) - torch.repeat_interleave(start, counts)
    span = (x1 - x0)[ids]
    tx = x0[ids] + local % span.clamp(min=1)
    ty = y0[ids] + local // span.clamp(min=1)
    cam = ids // n
    tiles = cam * (tile_w * tile_h) + ty * tile_w + tx
    order = torch.argsort(depths.reshape(-1).double(), stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(order.numel())
    key = tiles * (c * n) + rank[ids]
    srt = torch.argsort(key)
    return tiles[srt], ids[srt]


def composite(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    backgrounds: Tensor | None = None,
    chunk_elems: int = 1 << 22,
) -> tuple[Tensor, Tensor, Tensor]:
    """Front-to-back compositing of D channels -> (out [C,H,W,D] incl. background, alphas [C,H,W,1],
    median depth [C,H,W,1]: the depth of the Gaussian that takes the transmittance from above 0.5 to
    0.5 or below, 0 where it never does; no gradient).

    Tiles are processed in chunks of similar length, each padded to its longest list; a
    chunk holds about ``chunk_elems`` pixel-Gaussian pairs.
    """
    c, _n = depths.shape
    d = colors.shape[-1]
    tile_w = math.ceil(width / TILE_SIZE)
    tile_h = math.ceil(height / TILE_SIZE)
    n_tiles = c * tile_w * tile_h
    tp = TILE_SIZE * TILE_SIZE
    dtype = means2d.dtype
    tiles, ids = _tile_lists(means2d, radii, depths, tile_w, tile_h)
    counts = torch.bincount(tiles, minlength=n_tiles)
    offsets = torch.cumsum(counts, 0) - counts

    flat_m = means2d.reshape(-1, 2)
    flat_c = conics.reshape(-1, 3)
    flat_o = opacities.reshape(-1)
    flat_col = colors.reshape(-1, d)
    ly, lx = torch.meshgrid(torch.arange(TILE_SIZE), torch.arange(TILE_SIZE), indexing="ij")
    local = torch.stack([lx.reshape(-1), ly.reshape(-1)], dim=-1).to(dtype)  # [256, 2]

    tile_ids = torch.nonzero(counts > 0).reshape(-1)
    tile_ids = tile_ids[torch.argsort(counts[tile_ids], descending=True, stable=True)]
    flat_depth = depths.reshape(-1).detach()
    results_col, results_t, results_med, done_tiles = [], [], [], []
    i = 0
    while i < tile_ids.numel():
        length = int(counts[tile_ids[i]])
        per = max(1, chunk_elems // (tp * length))
        chunk = tile_ids[i : i + per]
        i += per
        chunk.numel()
        pos = offsets[chunk][:, None] + torch.arange(length)[None, :]  # [T, L]
        pad = torch.arange(length)[None, :] < counts[chunk][:, None]
        g = ids[pos.clamp(max=ids.numel() - 1)]
        g = torch.where(pad, g, torch.zeros_like(g))
        img = chunk % (tile_w * tile_h)
        origin = torch.stack([(img % tile_w) * TILE_SIZE, (img // tile_w) * TILE_SIZE], -1).to(dtype)
        pix = origin[:, None, :] + local[None] + 0.5  # [T, 256, 2]
        mg = flat_m[g]  # [T, L, 2]
        cg = flat_c[g]
        dx = mg[:, None, :, 0] - pix[:, :, None, 0]  # [T, 256, L]
        dy = mg[:, None, :, 1] - pix[:, :, None, 1]
        sigma = 0.5 * (cg[:, None, :, 0] * dx * dx + cg[:, None, :, 2] * dy * dy) + cg[:, None, :, 1] * dx * dy
        valid = pad[:, None, :] & (sigma >= 0)
        sigma = torch.where(valid, sigma, torch.zeros_like(sigma))
        alpha = torch.clamp_max(flat_o[g][:, None, :] * torch.exp(-sigma), ALPHA_MAX)
        valid = valid & (alpha >= ALPHA_THRESHOLD)
        alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            keep = torch.cumprod(1.0 - alpha, dim=-1) > T_MIN
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        trans = torch.cumprod(1.0 - alpha, dim=-1)
        t_before = torch.cat([torch.ones_like(trans[..., :1]), trans[..., :-1]], dim=-1)
        weights = alpha * t_before
        results_col.append(torch.einsum("tpl,tld->tpd", weights, flat_col[g]))
        results_t.append(trans[..., -1])
        with torch.no_grad():
            crosses = (alpha > 0) & (t_before > 0.5) & (trans <= 0.5)
            results_med.append(torch.einsum("tpl,tl->tp", crosses.to(dtype), flat_depth[g]))
        done_tiles.append(chunk)

    all_col = torch.zeros(n_tiles, tp, d, dtype=dtype)
    all_t = torch.ones(n_tiles, tp, dtype=dtype)
    all_med = torch.zeros(n_tiles, tp, dtype=dtype)
    if done_tiles:
        idx = torch.cat(done_tiles)
        all_col = all_col.index_copy(0, idx, torch.cat(results_col))
        all_t = all_t.index_copy(0, idx, torch.cat(results_t))
        all_med = all_med.index_copy(0, idx, torch.cat(results_med))
    shape = (c, tile_h, tile_w, TILE_SIZE, TILE_SIZE)
    img_col = all_col.reshape(shape + (d,)).permute(0, 1, 3, 2, 4, 5)
    img_col = img_col.reshape(c, tile_h * TILE_SIZE, tile_w * TILE_SIZE, d)[:, :height, :width]
    img_t = all_t.reshape(shape).permute(0, 1, 3, 2, 4)
    img_t = img_t.reshape(c, tile_h * TILE_SIZE, tile_w * TILE_SIZE)[:, :height, :width, None]
    img_med = all_med.reshape(shape).permute(0, 1, 3, 2, 4)
    img_med = img_med.reshape(c, tile_h * TILE_SIZE, tile_w * TILE_SIZE)[:, :height, :width, None]
    if backgrounds is not None:
        img_col = img_col + img_t * backgrounds[:, None, None, :]
    return img_col, 1.0 - img_t, img_med


def rasterize_reference(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: Tensor | None = None,
    eps2d: float = 0.3,
    antialiased: bool = False,
    chunk_elems: int = 1 << 22,
) -> tuple[Tensor, Tensor, Tensor, dict[str, Any]]:
    """Same contract as :func:`brave6d.training.rasterizer.rasterize`, in pure torch (any float dtype)."""
    inp = prepare_inputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane,
        backgrounds=backgrounds, eps2d=eps2d, antialiased=antialiased,
    )
    dtype = inp.means.dtype
    c, n = inp.n_cameras, inp.n_gaussians
    viewmats = inp.viewmats.detach().to(dtype)
    Ks = inp.Ks.detach().to(dtype)
    radii, means2d, depths, conics, comp = project(
        inp.means, inp.quats, inp.scales, inp.opacities, viewmats, Ks, width, height,
        inp.eps2d, inp.near_plane, inp.far_plane, inp.antialiased,
    )
    if inp.sh_degree is not None:
        rgb = sh_colors(inp.sh_degree, inp.means, inp.colors.to(dtype), viewmats, radii)
    else:
        rgb = inp.colors.to(dtype)
        rgb = rgb if inp.per_camera_colors else rgb[None].expand(c, n, 3)
    colors4 = torch.cat([rgb, depths[..., None]], dim=-1)
    opac = inp.opacities.to(dtype)[None].expand(c, n) * comp
    bg = None
    if inp.backgrounds is not None:
        bg = torch.cat([inp.backgrounds.to(dtype), torch.zeros(c, 1, dtype=dtype)], dim=-1)
    out, alphas, median = composite(means2d, conics, colors4, opac, radii, depths, width, height, bg,
                                    chunk_elems)
    depth = out[..., 3:4] / alphas.clamp(min=DEPTH_ALPHA_EPS)
    info = {"means2d": means2d, "radii": radii, "depths": depths, "conics": conics,
            "opacities": opac, "visible": (radii > 0).all(dim=-1), "median_depth": median}
    return out[..., :3], depth, alphas, info

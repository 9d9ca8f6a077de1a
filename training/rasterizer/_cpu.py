"""CPU backend: the Numba kernels wrapped in autograd Functions.

The graph mirrors gsplat's: projection -> (SH) -> compositing, with ``means2d`` an
intermediate tensor so that densification can read its gradient (``retain_grad``).
Cameras (``viewmats``, ``Ks``) are constants: no gradient flows to them.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor

from . import _cpu_kernels as K
from ._constants import DEPTH_ALPHA_EPS, TILE_SIZE
from ._validation import RasterInputError, RasterInputs

_MAX_ISECTS = 2**31 - 1  # intersection indices are int32 in the kernels


def _np(t: Tensor) -> np.ndarray:
    """Zero-copy float32/int view of a CPU tensor for the kernels."""
    return t.detach().contiguous().numpy()


def _zeros_if_none(g: Tensor | None, like: Tensor) -> Tensor:
    return torch.zeros_like(like) if g is None else g


class _Project(torch.autograd.Function):
    """EWA projection of 3D Gaussians: -> radii, means2d, depths, conics."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, eps2d,
                near_plane, far_plane):
        radii, means2d, depths, conics = K.project_fwd(
            _np(means), _np(quats), _np(scales), _np(opacities), True, _np(viewmats), _np(Ks),
            width, height, eps2d, near_plane, far_plane,
        )
        radii_t = torch.from_numpy(radii)
        ctx.save_for_backward(means, quats, scales, viewmats, Ks, radii_t)
        ctx.cfg = (width, height, eps2d)
        ctx.mark_non_differentiable(radii_t)
        return radii_t, torch.from_numpy(means2d), torch.from_numpy(depths), torch.from_numpy(conics)

    @staticmethod
    def backward(ctx, _v_radii, v_means2d, v_depths, v_conics):
        means, quats, scales, viewmats, Ks, radii = ctx.saved_tensors
        width, height, eps2d = ctx.cfg
        c, n = radii.shape[:2]
        v_means2d = _zeros_if_none(v_means2d, torch.empty(c, n, 2))
        v_depths = _zeros_if_none(v_depths, torch.empty(c, n))
        v_conics = _zeros_if_none(v_conics, torch.empty(c, n, 3))
        v_means, v_quats, v_scales = K.project_bwd(
            _np(means), _np(quats), _np(scales), _np(viewmats), _np(Ks), width, height, eps2d,
            _np(radii), _np(v_means2d), _np(v_depths), _np(v_conics),
        )
        return (torch.from_numpy(v_means), torch.from_numpy(v_quats), torch.from_numpy(v_scales),
                None, None, None, None, None, None, None, None)


class _SphericalHarmonics(torch.autograd.Function):
    """View-dependent colour from SH coefficients (direction: camera centre -> mean)."""

    @staticmethod
    def forward(ctx, degree, means, coeffs, campos, radii):
        colors = K.sh_fwd(degree, _np(means), _np(campos), _np(coeffs), _np(radii))
        ctx.save_for_backward(means, coeffs, campos, radii)
        ctx.degree = degree
        return torch.from_numpy(colors)

    @staticmethod
    def backward(ctx, v_colors):
        means, coeffs, campos, radii = ctx.saved_tensors
        v_coeffs, v_means = K.sh_bwd(ctx.degree, _np(means), _np(campos), _np(coeffs),
                                     _np(radii), _np(v_colors))
        return None, torch.from_numpy(v_means), torch.from_numpy(v_coeffs), None, None


class _Composite(torch.autograd.Function):
    """Tile binning and front-to-back alpha compositing of 4 channels (RGB + depth)."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, backgrounds, radii, depths, width,
                height, absgrad):
        c, n = radii.shape[:2]
        tile_w = math.ceil(width / TILE_SIZE)
        tile_h = math.ceil(height / TILE_SIZE)
        rec = K.prepare_splats(_np(means2d).reshape(c * n, 2), _np(conics).reshape(c * n, 3),
                               _np(colors).reshape(c * n, 4), _np(opacities).reshape(c * n))
        tile_offsets, flatten_ids, isect_rows, gauss_offsets, isect_of = K.bin_splats(
            rec, _np(radii), _np(depths), tile_w, tile_h, width, height)
        if flatten_ids.shape[0] >= _MAX_ISECTS:
            raise RasterInputError(
                f"rasterize: {flatten_ids.shape[0]} Gaussian-tile intersections exceed the CPU "
                f"kernel's limit of {_MAX_ISECTS}; render fewer or smaller Gaussians"
            )
        n_workers = max(1, numba.get_num_threads())
        order = K.tile_order(K.forward_costs(tile_offsets))
        out, t_final, last_ids, bwd_costs = K.rasterize_fwd(
            rec, _np(backgrounds), width, height, tile_w, tile_h, tile_offsets, flatten_ids,
            isect_rows, order, n_workers,
        )
        ctx.save_for_backward(means2d, opacities, backgrounds)
        ctx.plan = (tile_w, tile_h, tile_offsets, flatten_ids, isect_rows, gauss_offsets,
                    isect_of, bwd_costs, n_workers, t_final, last_ids, rec)
        ctx.cfg = (width, height, absgrad)
        t_final_t = torch.from_numpy(t_final)
        alphas = (1.0 - t_final_t)[..., None]
        return torch.from_numpy(out), alphas

    @staticmethod
    def backward(ctx, v_out, v_alphas):
        means2d, opacities, backgrounds = ctx.saved_tensors
        (tile_w, tile_h, tile_offsets, flatten_ids, isect_rows, gauss_offsets, isect_of,
         bwd_costs, n_workers, t_final, last_ids, rec) = ctx.plan
        width, height, absgrad = ctx.cfg
        c, n = opacities.shape
        v_out = _zeros_if_none(v_out, torch.empty(c, height, width, 4))
        v_alphas = _zeros_if_none(v_alphas, torch.empty(c, height, width, 1))
        grads = K.rasterize_bwd(
            rec, _np(backgrounds), width, height, tile_w, tile_h, tile_offsets, flatten_ids,
            isect_rows, gauss_offsets, isect_of, K.tile_order(bwd_costs), n_workers, t_final, last_ids,
            _np(v_out), _np(v_alphas).reshape(c, height, width),
            np.empty(0, np.float32) if absgrad else None,
        )
        g = torch.from_numpy(grads).reshape(c, n, 12)
        if absgrad:
            means2d.absgrad = g[..., 10:12].clone()
        v_bg = None
        if ctx.needs_input_grad[4]:
            v_bg = (torch.from_numpy(t_final)[..., None] * v_out).sum(dim=(1, 2))
        return (g[..., 0:2].clone(), g[..., 2:5].clone(), g[..., 6:10].clone(), g[..., 5].clone(),
                v_bg, None, None, None, None, None)


def _camera_centres(viewmats: Tensor) -> Tensor:
    """Camera centres in world coordinates (gsplat: inverse(viewmats)[:, :3, 3])."""
    return torch.inverse(viewmats.detach().double())[:, :3, 3].float().contiguous()


def rasterize_cpu(inp: RasterInputs, absgrad: bool) -> tuple[Tensor, Tensor, Tensor, dict[str, Any]]:
    """Render with the compiled CPU kernels (see :func:`training.rasterizer.rasterize`)."""
    if inp.means.device.type != "cpu":
        raise RasterInputError(
            f"rasterize: the cpu backend needs CPU tensors, got {inp.means.device}; "
            "use backend='cuda' or move the tensors with .cpu()"
        )
    f32 = torch.float32
    means = inp.means.to(f32)
    quats = inp.quats.to(f32)
    scales = inp.scales.to(f32)
    opacities = inp.opacities.to(f32)
    viewmats = inp.viewmats.detach().to(f32).contiguous()
    Ks = inp.Ks.detach().to(f32).contiguous()
    c, n = inp.n_cameras, inp.n_gaussians
    width, height = inp.width, inp.height

    radii, means2d, depths, conics = _Project.apply(
        means, quats, scales, opacities.detach(), viewmats, Ks, width, height, inp.eps2d,
        inp.near_plane, inp.far_plane,
    )
    colors = inp.colors.to(f32)
    if inp.sh_degree is not None:
        coeffs = colors if inp.per_camera_colors else colors[None]
        rgb = _SphericalHarmonics.apply(inp.sh_degree, means, coeffs.contiguous(),
                                        _camera_centres(inp.viewmats), radii)
        rgb = torch.clamp_min(rgb + 0.5, 0.0)
    else:
        rgb = colors if inp.per_camera_colors else colors[None].expand(c, n, 3)
    colors4 = torch.cat([rgb, depths[..., None]], dim=-1).contiguous()
    opac_cn = opacities[None].expand(c, n).contiguous()
    if inp.backgrounds is not None:
        bg = torch.cat([inp.backgrounds.to(f32), torch.zeros(c, 1)], dim=-1).contiguous()
    else:
        bg = torch.zeros(c, 4)

    out, alphas = _Composite.apply(means2d, conics, colors4, opac_cn, bg, radii, depths, width,
                                   height, absgrad)
    render_colors = out[..., :3]
    render_depth = out[..., 3:4] / alphas.clamp(min=DEPTH_ALPHA_EPS)
    info: dict[str, Any] = {
        "backend": "cpu",
        "means2d": means2d,
        "radii": radii,
        "depths": depths,
        "conics": conics,
        "opacities": opac_cn,
        "visible": (radii > 0).all(dim=-1),
        "width": width,
        "height": height,
        "n_cameras": c,
        "n_batches": 1,
        "tile_size": TILE_SIZE,
        "tile_width": math.ceil(width / TILE_SIZE),
        "tile_height": math.ceil(height / TILE_SIZE),
        "gaussian_ids": None,
        "camera_ids": None,
        "batch_ids": None,
    }
    return render_colors, render_depth, alphas, info

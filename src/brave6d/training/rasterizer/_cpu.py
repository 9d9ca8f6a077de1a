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

from . import kernels as K
from .constants import TILE_SIZE
from ._validation import RasterInputError, RasterInputs

_MAX_ISECTS = 2**31 - 1  # intersection indices are int32 in the kernels


def _np(t: Tensor) -> np.ndarray:
    """Zero-copy float32/int view of a CPU tensor for the kernels."""
    return t.detach().contiguous().numpy()


def _zeros_if_none(g: Tensor | None, like: Tensor) -> Tensor:
    return torch.zeros_like(like) if g is None else g


class _Project(torch.autograd.Function):
    """EWA projection of 3D Gaussians: -> radii, means2d, depths, conics, compensations
    (the 2D mip filter's opacity factor [C,N], 0 where culled; all ones unless ``antialiased``)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, eps2d,
                near_plane, far_plane, antialiased):
        c, n = viewmats.shape[0], means.shape[0]
        comp = np.zeros((c, n), np.float32) if antialiased else None
        radii, means2d, depths, conics = K.project_fwd(
            _np(means), _np(quats), _np(scales), _np(opacities), True, _np(viewmats), _np(Ks),
            width, height, eps2d, near_plane, far_plane, comp,
        )
        radii_t = torch.from_numpy(radii)
        comp_t = torch.from_numpy(comp) if antialiased else torch.ones(c, n)
        ctx.save_for_backward(means, quats, scales, viewmats, Ks, radii_t)
        ctx.cfg = (width, height, eps2d, antialiased)
        ctx.mark_non_differentiable(radii_t)
        return (radii_t, torch.from_numpy(means2d), torch.from_numpy(depths),
                torch.from_numpy(conics), comp_t)

    @staticmethod
    def backward(ctx, _v_radii, v_means2d, v_depths, v_conics, v_comp):
        means, quats, scales, viewmats, Ks, radii = ctx.saved_tensors
        width, height, eps2d, antialiased = ctx.cfg
        c, n = radii.shape[:2]
        v_means2d = _zeros_if_none(v_means2d, torch.empty(c, n, 2))
        v_depths = _zeros_if_none(v_depths, torch.empty(c, n))
        v_conics = _zeros_if_none(v_conics, torch.empty(c, n, 3))
        v_comp_np = _np(v_comp) if antialiased and v_comp is not None else None
        v_means, v_quats, v_scales = K.project_bwd(
            _np(means), _np(quats), _np(scales), _np(viewmats), _np(Ks), width, height, eps2d,
            _np(radii), _np(v_means2d), _np(v_depths), _np(v_conics), v_comp_np,
        )
        return (torch.from_numpy(v_means), torch.from_numpy(v_quats), torch.from_numpy(v_scales),
                None, None, None, None, None, None, None, None, None)


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
    """Tile binning and front-to-back alpha compositing of RGB and depth -> the RGB, expected
    depth and alpha images (the depth normalisation and its gradient happen in the kernels,
    which saves a dozen image-sized torch operations per step)."""

    @staticmethod
    def forward(ctx, means2d, conics, rgb, depths, opacities, backgrounds, radii, width, height,
                absgrad, with_median):
        c, n = radii.shape[:2]
        tile_w = math.ceil(width / TILE_SIZE)
        tile_h = math.ceil(height / TILE_SIZE)
        rgb3 = rgb if rgb.dim() == 3 else rgb[None]
        rec = K.prepare_splats(_np(means2d), _np(conics), _np(rgb3), _np(depths), _np(opacities))
        n_workers = max(1, numba.get_num_threads())
        tile_offsets, flatten_ids, isect_rows, gauss_offsets, isect_of = K.bin_splats(
            rec, _np(radii), _np(depths), tile_w, tile_h, width, height, n_workers)
        if flatten_ids.shape[0] >= _MAX_ISECTS:
            raise RasterInputError(
                f"rasterize: {flatten_ids.shape[0]} Gaussian-tile intersections exceed the CPU "
                f"kernel's limit of {_MAX_ISECTS}; render fewer or smaller Gaussians"
            )
        order = K.tile_order(K.forward_costs(tile_offsets))
        bg = _np(backgrounds) if backgrounds is not None else np.zeros((c, 3), np.float32)
        median = np.zeros((c, height, width, 1), np.float32) if with_median else None
        rgb_img, depth_img, alpha_img, t_final, acc_depth, last_ids, bwd_costs = K.rasterize_fwd(
            rec, bg, width, height, tile_w, tile_h, tile_offsets, flatten_ids, isect_rows, order,
            n_workers, median,
        )
        ctx.plan = (tile_w, tile_h, tile_offsets, flatten_ids, isect_rows, gauss_offsets,
                    isect_of, bwd_costs, n_workers, t_final, acc_depth, last_ids, rec, bg)
        ctx.cfg = (width, height, absgrad, rgb3.shape[0], rgb.dim())
        ctx.save_for_backward(means2d)
        median_t = torch.from_numpy(median) if median is not None else torch.zeros(0)
        ctx.mark_non_differentiable(median_t)
        return torch.from_numpy(rgb_img), torch.from_numpy(depth_img), torch.from_numpy(alpha_img), median_t

    @staticmethod
    def backward(ctx, v_rgb, v_depth, v_alpha, _v_median):
        (means2d,) = ctx.saved_tensors
        (tile_w, tile_h, tile_offsets, flatten_ids, isect_rows, gauss_offsets, isect_of,
         bwd_costs, n_workers, t_final, acc_depth, last_ids, rec, bg) = ctx.plan
        width, height, absgrad, n_colour_cams, rgb_dim = ctx.cfg
        c = t_final.shape[0]
        v_rgb = _zeros_if_none(v_rgb, torch.empty(c, height, width, 3))
        v_depth = _zeros_if_none(v_depth, torch.empty(c, height, width, 1))
        v_alpha = _zeros_if_none(v_alpha, torch.empty(c, height, width, 1))
        v_means2d, v_conics, v_colours, v_depths, v_opacities, v_abs = K.rasterize_bwd(
            rec, bg, width, height, tile_w, tile_h, tile_offsets, flatten_ids, isect_rows,
            gauss_offsets, isect_of, K.tile_order(bwd_costs), n_workers, t_final, acc_depth,
            last_ids, _np(v_rgb), _np(v_depth), _np(v_alpha), n_colour_cams,
            np.empty(0, np.float32) if absgrad else None,
        )
        if absgrad:
            means2d.absgrad = torch.from_numpy(v_abs)
        v_bg = None
        if ctx.needs_input_grad[5]:
            v_bg = (torch.from_numpy(t_final)[..., None] * v_rgb).sum(dim=(1, 2))
        v_colours_t = torch.from_numpy(v_colours)
        if rgb_dim == 2:
            v_colours_t = v_colours_t[0]
        return (torch.from_numpy(v_means2d), torch.from_numpy(v_conics), v_colours_t,
                torch.from_numpy(v_depths), torch.from_numpy(v_opacities), v_bg,
                None, None, None, None, None)


def _camera_centres(viewmats: Tensor) -> Tensor:
    """Camera centres in world coordinates (gsplat: inverse(viewmats)[:, :3, 3])."""
    return torch.inverse(viewmats.detach().double())[:, :3, 3].float().contiguous()


def rasterize_cpu(inp: RasterInputs, absgrad: bool, median_depth: bool = False
                  ) -> tuple[Tensor, Tensor, Tensor, dict[str, Any]]:
    """Render with the compiled CPU kernels (see :func:`brave6d.training.rasterizer.rasterize`)."""
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

    radii, means2d, depths, conics, comp = _Project.apply(
        means, quats, scales, opacities.detach(), viewmats, Ks, width, height, inp.eps2d,
        inp.near_plane, inp.far_plane, inp.antialiased,
    )
    # per-camera opacities [C, N]: times the 2D mip filter's compensation when antialiased
    opacities = opacities[None] * comp if inp.antialiased else opacities[None].expand(c, n)
    colors = inp.colors.to(f32)
    if inp.sh_degree is not None:
        coeffs = colors if inp.per_camera_colors else colors[None]
        rgb = _SphericalHarmonics.apply(inp.sh_degree, means, coeffs.contiguous(),
                                        _camera_centres(inp.viewmats), radii)
        rgb = torch.clamp_min(rgb + 0.5, 0.0)
    else:
        rgb = colors  # [N, 3] (shared by the cameras) or [C, N, 3]
    bg = inp.backgrounds.to(f32) if inp.backgrounds is not None else None

    render_colors, render_depth, alphas, median = _Composite.apply(
        means2d, conics, rgb, depths, opacities, bg, radii, width, height, absgrad, median_depth)
    radii_np = radii.numpy()
    info: dict[str, Any] = {
        "backend": "cpu",
        "means2d": means2d,
        "radii": radii,
        "depths": depths,
        "conics": conics,
        "opacities": opacities,
        "visible": torch.from_numpy((radii_np > 0).all(axis=-1)),
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
    if median_depth:
        info["median_depth"] = median
    return render_colors, render_depth, alphas, info

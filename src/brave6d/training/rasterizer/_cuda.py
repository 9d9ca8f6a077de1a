"""CUDA backend: a thin adapter over ``gsplat.rasterization`` (imported lazily)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ._validation import RasterBackendError, RasterInputError, RasterInputs


def rasterize_cuda(inp: RasterInputs, absgrad: bool, median_depth: bool = False
                   ) -> tuple[Tensor, Tensor, Tensor, dict[str, Any]]:
    """Render with gsplat's CUDA kernels (see :func:`brave6d.training.rasterizer.rasterize`); the
    median depth (gsplat has none) from the same call's projections and tile lists by the Triton
    kernel of :mod:`.median_depth`, on the device: nothing goes through the CPU rasterizer."""
    if not torch.cuda.is_available():
        raise RasterBackendError(
            "rasterize: backend='cuda' needs a CUDA GPU but torch.cuda.is_available() is False; "
            "use backend='cpu' or 'auto'"
        )
    if inp.means.device.type != "cuda":
        raise RasterInputError(
            f"rasterize: backend='cuda' needs CUDA tensors, got {inp.means.device}; "
            "move them with .cuda()"
        )
    try:
        from gsplat import rasterization
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise RasterBackendError(
            "rasterize: backend='cuda' needs gsplat (pip install 'brave6d[cuda]')"
        ) from exc
    f32 = torch.float32
    backgrounds = None if inp.backgrounds is None else inp.backgrounds.to(f32).contiguous()
    out, alphas, meta = rasterization(
        inp.means.to(f32),
        inp.quats.to(f32),
        inp.scales.to(f32),
        inp.opacities.to(f32),
        inp.colors.to(f32),
        inp.viewmats.to(f32),
        inp.Ks.to(f32),
        inp.width,
        inp.height,
        near_plane=inp.near_plane,
        far_plane=inp.far_plane,
        eps2d=inp.eps2d,
        sh_degree=inp.sh_degree,
        packed=False,
        backgrounds=backgrounds,
        render_mode="RGB+ED",
        absgrad=absgrad,
        rasterize_mode="antialiased" if inp.antialiased else "classic",
    )
    meta["backend"] = "cuda"
    meta["visible"] = (meta["radii"] > 0).all(dim=-1)
    if median_depth:
        from .median_depth import median_depth as median_from_tiles

        meta["median_depth"] = median_from_tiles(
            meta["means2d"], meta["conics"], meta["opacities"], meta["depths"],
            meta["isect_offsets"], meta["flatten_ids"], inp.width, inp.height, meta["tile_size"])
    return out[..., :3], out[..., 3:4], alphas, meta

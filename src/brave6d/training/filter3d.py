"""Mip-Splatting's 3D smoothing filter: each Gaussian is widened to the finest detail the training
cameras could sample, so that views closer than the training views do not show thin, aliased
Gaussians that no training image constrained (Yu et al., "Mip-Splatting", CVPR 2024, section 5.1).

* :func:`compute_filter_3d`: per Gaussian, the highest sampling rate ``f / z`` (pixels per metre)
  over the training cameras whose view (plus a 15 % margin) holds its centre in front of the near
  plane; the filter's standard deviation is ``sqrt(scale) / rate`` (Mip-Splatting's variance
  ``s / rate^2``, ``s = 0.2`` by default). A Gaussian no camera sees gets the lowest rate of those
  seen (the widest filter); with no Gaussian seen at all the filter is zero.
* :func:`apply_filter_3d`: the effective scales ``sqrt(scale^2 + filter^2)`` and opacities times
  ``sqrt(det(S) / det(S + filter^2 I))`` (the filtered Gaussian keeps its integral), the one place
  where the filter becomes what the rasterizer draws: the trainer, the holdout evaluation and the
  render server all call it. ``filter_3d`` None: unchanged (a splat trained without the filter).

The filter is data of the model (``GaussianModel.filter_3d``, the PLY's ``filter_3d`` property),
computed from the training cameras, not a trainable parameter.
"""

from __future__ import annotations

import torch
from torch import Tensor

#: Mip-Splatting's default variance factor ``s`` of the 3D filter.
DEFAULT_FILTER_3D_SCALE = 0.2
#: A centre counts as seen by a camera within this share of the image size beyond each edge.
FRUSTUM_MARGIN = 0.15


@torch.no_grad()
def compute_filter_3d(means: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int,
                      scale: float = DEFAULT_FILTER_3D_SCALE, near_plane: float = 0.01,
                      chunk: int = 16) -> Tensor:
    """The 3D filter's standard deviation [N] (world units) from the training cameras.

    ``viewmats`` [C, 4, 4] world-to-camera (OpenCV axes), ``Ks`` [C, 3, 3] or [3, 3] pinhole
    intrinsics of images of ``width`` x ``height`` pixels. ``near_plane`` in the means' units: the
    trainer passes its own (:data:`brave6d.training.scene_frame.NEAR_PLANE` scene extents).
    """
    if not scale >= 0.0:
        raise ValueError(f"compute_filter_3d: scale must be >= 0, got {scale}")
    pts = means.detach().double()
    n = pts.shape[0]
    vm = viewmats.detach().to(device=pts.device, dtype=torch.float64)
    k = Ks.detach().to(device=pts.device, dtype=torch.float64)
    if k.dim() == 2:
        k = k[None].expand(vm.shape[0], 3, 3)
    rate = torch.zeros(n, dtype=torch.float64, device=pts.device)
    mx, my = FRUSTUM_MARGIN * width, FRUSTUM_MARGIN * height
    for start in range(0, vm.shape[0], chunk):
        r, t, kk = vm[start:start + chunk, :3, :3], vm[start:start + chunk, :3, 3], k[start:start + chunk]
        pc = torch.einsum("cij,nj->cni", r, pts) + t[:, None, :]
        z = pc[..., 2]
        zs = torch.where(z > near_plane, z, torch.ones_like(z))
        u = kk[:, 0, 0, None] * pc[..., 0] / zs + kk[:, 0, 2, None]
        v = kk[:, 1, 1, None] * pc[..., 1] / zs + kk[:, 1, 2, None]
        seen = (z > near_plane) & (u >= -mx) & (u <= width + mx) & (v >= -my) & (v <= height + my)
        focal = torch.maximum(kk[:, 0, 0], kk[:, 1, 1])[:, None]
        cam_rate = torch.where(seen, focal / zs, torch.zeros_like(zs))
        rate = torch.maximum(rate, cam_rate.max(dim=0).values)
    seen_any = rate > 0
    if not bool(seen_any.any()):
        return torch.zeros(n, dtype=means.dtype, device=means.device)
    rate = torch.where(seen_any, rate, rate[seen_any].min())
    return (scale ** 0.5 / rate).to(means.dtype)


def scale_range(dtype: torch.dtype) -> tuple[float, float]:
    """The scales ``(lo, hi)`` the filter works within for ``dtype``: squares of scales in it, and
    their sums with a squared filter, stay normal numbers, so every value and gradient is finite
    (the gradient in the scale is at most about ``1 / lo``). Far outside any scene: float32 gives
    about 4e-19 to 5e18 world units."""
    info = torch.finfo(dtype)
    return 4.0 * info.tiny ** 0.5, 0.25 * info.max ** 0.5


def apply_filter_3d(scales: Tensor, opacities: Tensor, filter_3d: Tensor | None) -> tuple[Tensor, Tensor]:
    """Effective ``(scales [N, 3], opacities [N])`` of activated scales and opacities convolved with
    an isotropic Gaussian of standard deviation ``filter_3d`` [N] (None: returned unchanged).

    Differentiable in ``scales`` and ``opacities``. Scales and the filter are taken within
    :func:`scale_range` first: a zero or subnormal scale acts as the range's floor (a point far below
    any pixel) and a scale whose square would overflow as its ceiling (the rasterizer could not draw
    it either), so values and gradients stay finite for any input."""
    if filter_3d is None:
        return scales, opacities
    if filter_3d.shape != opacities.shape:
        raise ValueError(f"apply_filter_3d: filter_3d has shape {tuple(filter_3d.shape)}, "
                         f"expected {tuple(opacities.shape)} (one value per Gaussian)")
    lo, hi = scale_range(scales.dtype)
    s2 = scales.clamp(lo, hi).square()
    f2 = filter_3d.to(scales.dtype).clamp(0.0, hi).square()[:, None]
    total = s2 + f2
    # prod(s2 / (s2 + f2)) per axis: stays in [0, 1]
    ratio = s2 / total
    tiny = torch.finfo(scales.dtype).tiny  # keeps sqrt's gradient finite at 0
    return torch.sqrt(total), opacities * torch.sqrt(ratio.prod(dim=-1).clamp_min(tiny))

"""The public rasterizer entry point: checks inputs, picks a backend, renders."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ._validation import RasterInputError, prepare_inputs

BACKENDS = ("auto", "cpu", "cuda")


def resolve_backend(backend: str, device: torch.device) -> str:
    """Map ``backend`` to 'cpu' or 'cuda'.

    ``auto`` follows the tensors: CUDA tensors (which imply a GPU) use gsplat, CPU tensors
    use the compiled CPU kernel, so no tensor is moved between devices behind the caller's back.
    """
    if backend not in BACKENDS:
        raise RasterInputError(f"rasterize: `backend` must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        return "cuda" if device.type == "cuda" and torch.cuda.is_available() else "cpu"
    return backend


def rasterize(
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
    backend: str = "auto",
    absgrad: bool = False,
    median_depth: bool = False,
    antialiased: bool = False,
    validate: bool = True,
) -> tuple[Tensor, Tensor, Tensor, dict[str, Any]]:
    """Render 3D Gaussians into one or more pinhole cameras (gsplat conventions).

    Args:
        means: [N, 3] centres (world frame).
        quats: [N, 4] rotations, (w, x, y, z), need not be normalised.
        scales: [N, 3] standard deviations, already activated (e.g. ``exp`` of the parameter).
        opacities: [N] already activated (e.g. ``sigmoid`` of the parameter).
        colors: [N, 3] or [C, N, 3] RGB; or [N, K, 3] / [C, N, K, 3] SH coefficients when
            ``sh_degree`` is given (K >= (sh_degree + 1)^2, degree <= 3).  SH colours are
            evaluated from the camera centre towards the mean, shifted by +0.5 and clamped
            at 0, like gsplat.
        viewmats: [C, 4, 4] world-to-camera transforms (OpenCV camera axes).
        Ks: [C, 3, 3] pinhole intrinsics in OpenCV's pixel convention (pixel ``(u, v)``
            centred at integer ``(u, v)``, the project's ``K``); both backends shift the
            principal point by +0.5 px into gsplat's convention (see ``_pixels``), so a
            point ``X`` renders centred at ``K @ X`` like in the simulator's images.
        width, height: image size in pixels.
        sh_degree: SH degree to evaluate, or None for plain RGB colours.
        near_plane, far_plane: Gaussians whose camera depth lies outside are culled.
        backgrounds: [C, 3] or [3] colour behind the Gaussians (default black).
        eps2d: added to the 2D covariance diagonal (px^2), gsplat's anti-aliasing floor.
        backend: 'cpu' (compiled Numba kernels), 'cuda' (gsplat) or 'auto' (follows the
            tensors' device).
        absgrad: also accumulate ``info['means2d'].absgrad`` in backward (AbsGS).
        median_depth: also return ``info['median_depth']`` [C,H,W,1] (no gradient): the depth of
            the Gaussian that takes the pixel's transmittance from above 0.5 to 0.5 or below, 0
            where it never does. Unlike the expected depth it never lies between a foreground and
            a background surface (what a depth sensor reports at an edge). gsplat has no median
            depth: on ``cuda`` a Triton kernel (:mod:`.median_depth`) computes it on the device
            from the same call's projected Gaussians and tile lists.
        antialiased: the 2D mip filter (Mip-Splatting; gsplat's ``rasterize_mode="antialiased"``):
            besides the ``eps2d`` dilation, each Gaussian's opacity is multiplied per camera by
            ``sqrt(max(det(cov2d) / det(cov2d + eps2d I), 0))``, so a Gaussian far below a pixel
            fades instead of growing into a pixel-sized blob (``info['opacities']`` [C,N] holds
            the compensated opacities).  False: gsplat's ``classic`` mode.
        validate: check the values (NaN/inf in any input, focal lengths > 0). On a GPU each check
            waits for the device; False leaves them out for a caller that checked its cameras
            once and watches its parameters itself (the trainer's lean GPU step). Types, devices
            and shapes are always checked.

    Returns:
        ``(render_colors [C,H,W,3], render_depth [C,H,W,1], render_alphas [C,H,W,1], info)``.
        ``render_depth`` is the expected depth (accumulated depth / alpha).  ``info`` is
        compatible with gsplat 1.5.3's ``DefaultStrategy`` (non-packed): ``means2d`` [C,N,2]
        (gsplat's pixel coordinates, OpenCV's + 0.5; call ``retain_grad`` before backward),
        ``radii`` [C,N,2] int32, ``depths``,
        ``conics``, ``width``, ``height``, ``n_cameras``, ``gaussian_ids`` (None), plus
        ``visible`` [C,N] bool.

    Raises:
        RasterInputError: bad shapes or arguments, NaN/inf inputs.
        RasterBackendError: the requested backend cannot run on this machine.

    Gradients flow to means, quats, scales, opacities, colors and backgrounds; cameras
    (viewmats, Ks) are treated as constants.  See ``_validation`` for the rules applied
    to degenerate inputs (zero quaternions, extreme scales).
    """
    inputs = prepare_inputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane,
        backgrounds=backgrounds, eps2d=eps2d, antialiased=antialiased, validate=validate,
    )
    name = resolve_backend(backend, inputs.means.device)
    if name == "cuda":
        from ._cuda import rasterize_cuda

        return rasterize_cuda(inputs, absgrad, median_depth)
    from ._cpu import rasterize_cpu

    return rasterize_cpu(inputs, absgrad, median_depth)

"""Pixel-centre convention at the rasterizer's boundary: OpenCV intrinsics in, gsplat's inside.

The project's ``K`` follows OpenCV: pixel column ``u`` (row ``v``) has its centre at the integer
coordinate ``u`` (``v``), so a ray through pixel ``(u, v)`` is ``((u - cx) / fx, (v - cy) / fy, 1)``
(``brave6d.core.camera.PinholeCamera``; the simulator and the mask ray casters cast exactly these rays).

gsplat (1.5.3) puts the centre of pixel ``(u, v)`` at ``(u + 0.5, v + 0.5)`` instead:

* ``gsplat/cuda/_torch_impl.py``, ``_persp_proj``: ``means2d = K[:2, :3] @ x / z`` (no offset),
  and its Jacobian clamp treats ``[0, width]`` as the image's extent (``lim_x_pos = (width - cx) / fx``);
* ``_rasterize_to_pixels``: ``pixel_coords = (pixel_ids_x, pixel_ids_y) + 0.5``;
* ``gsplat/cuda/csrc/RasterizeToPixels3DGSFwd.cu``: ``px = (float)j + 0.5f; py = (float)i + 0.5f``.

The compiled CPU kernels (``kernels``) copy those conventions (pixel centre ``x + 0.5``), so
both backends need the same shift: an OpenCV principal point ``c`` is gsplat's ``c + 0.5``
(focal lengths are unchanged). :func:`gsplat_intrinsics` applies it once, in
``_validation.prepare_inputs``, for every backend and the torch reference alike.
"""

from __future__ import annotations

import torch
from torch import Tensor

from brave6d.core.camera import CORNER_ORIGIN_OFFSET

#: gsplat's coordinate of a pixel centre minus OpenCV's (px, both axes): the corner-origin offset.
GSPLAT_PIXEL_OFFSET = CORNER_ORIGIN_OFFSET


def gsplat_intrinsics(Ks: Tensor) -> Tensor:
    """``Ks`` [C, 3, 3] (OpenCV pixel centres) as gsplat expects them: ``cx, cy`` + 0.5 px.

    Out of place (the caller's tensor is left alone); dtype, device and any graph are kept.
    """
    shift = torch.zeros(3, 3, dtype=Ks.dtype, device=Ks.device)
    shift[0, 2] = GSPLAT_PIXEL_OFFSET
    shift[1, 2] = GSPLAT_PIXEL_OFFSET
    return Ks + shift

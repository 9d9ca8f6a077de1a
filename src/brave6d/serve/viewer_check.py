"""How closely other 3DGS viewers draw a splat as the server serves it (issue 45).

A standard viewer (SuperSplat, gsplat's viewer, Inria's SIBR) reads the Inria PLY layout and
nothing else: it ignores ``filter_3d`` and, unless set to gsplat's ``antialiased`` mode, draws
with the classic rasterizer. :func:`compare_viewer_renders` renders views of one splat

* as served: :class:`~brave6d.serve.renderer.SplatRenderer` with the 3D filter and the bundle's
  anti-aliasing mode (``mip``: the rasterizer's 2D mip filter);
* as a viewer draws today's file: the filter ignored, classic rasterizer (``naive``);
* as a viewer draws the viewer PLY (:func:`brave6d.training.bake_filter_3d`): classic rasterizer
  (``baked_classic``) and antialiased (``baked_antialiased``);

and scores each against the served render (PSNR of the 8-bit images). The 2D filter's opacity
compensation depends on the view, so only ``baked_antialiased`` can match exactly; ``baked_classic``
differs where Gaussians are smaller than a pixel (far views). Used by ``benchmarks/viewer_ply.py``
and its test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.transforms import ring_orbit

if TYPE_CHECKING:
    from brave6d.training import SplatData

#: Camera distances (m) of the issue's comparison, and views per distance.
DISTANCES_M = (0.1, 0.2, 0.3, 0.5)
VIEWS_PER_DISTANCE = 3
#: How a viewer may draw a file: ``name -> (filter baked in, rasterizer antialiased)``.
VIEWER_WAYS = {"naive": (False, False), "baked_classic": (True, False), "baked_antialiased": (True, True)}


@dataclass(frozen=True)
class ViewScore:
    """PSNR (dB) against the served render of one view, per way of :data:`VIEWER_WAYS`."""

    distance_m: float
    view: int
    psnr_db: dict[str, float]


def orbit_poses(target: tuple[float, float, float], distances: tuple[float, ...] = DISTANCES_M,
                per_distance: int = VIEWS_PER_DISTANCE, elevation_deg: float = 45.0
                ) -> list[tuple[float, NDArray[np.float64]]]:
    """``(distance, world_T_cam)`` of cameras on rings around ``target`` looking at it
    (:func:`brave6d.core.transforms.ring_orbit`)."""
    return [(distance, T) for _, distance, T in ring_orbit(target, distances, per_distance, elevation_deg)]


def psnr_uint8(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> float:
    """PSNR (dB) of two 8-bit images; 100 dB when identical."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)) / 255.0**2
    return -10.0 * math.log10(max(mse, 1e-10))


def compare_viewer_renders(splat: SplatData, camera: PinholeCamera, poses: list[tuple[float, NDArray[np.float64]]],
                           served_mode: str | None = None, device: str = "cpu") -> list[ViewScore]:
    """One :class:`ViewScore` per pose: each way a viewer may draw ``splat`` against the served
    render (``served_mode``: the bundle's ``render.antialiasing``; None: as the splat was trained)."""
    from brave6d.serve.renderer import SplatRenderer
    from brave6d.training import bake_filter_3d

    served = SplatRenderer.from_splat(splat, device, antialiasing=served_mode, source="served splat")
    baked, naive = bake_filter_3d(splat), replace(splat, filter_3d=None)
    viewers = {name: SplatRenderer.from_splat(baked if bake else naive, device, source=f"{name} splat",
                                              antialiasing="mip" if aa else "classic")
               for name, (bake, aa) in VIEWER_WAYS.items()}
    scores = []
    for i, (distance, pose) in enumerate(poses):
        truth = served.render(pose, camera).rgb
        scores.append(ViewScore(distance, i, {name: psnr_uint8(r.render(pose, camera).rgb, truth)
                                              for name, r in viewers.items()}))
    return scores


def per_distance(scores: list[ViewScore]) -> dict[float, dict[str, float]]:
    """Mean PSNR per distance and way (dB)."""
    out: dict[float, dict[str, float]] = {}
    for d in sorted({s.distance_m for s in scores}):
        rows = [s.psnr_db for s in scores if s.distance_m == d]
        out[d] = {name: float(np.mean([r[name] for r in rows])) for name in VIEWER_WAYS}
    return out

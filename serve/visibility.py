"""Visible fraction of each object instance in a served view (BOP-like ``visib_fract``).

Definition (as bop_toolkit's ``scene_gt_info``): ``visib_fract = px_count_visib / px_count_all``

* ``px_count_all``: pixels of the object's silhouette ALONE (no occluders), counted on a canvas
  three times the image size centred on it, so a truncated object keeps its full silhouette;
* ``px_count_visib``: image pixels where the object is the first surface seen.

Silhouettes and depths come from CPU ray casting of the bundle's object models (Open3D
``RaycastingScene``, one ray per pixel centre ``((u - cx)/fx, (v - cy)/fy, 1)``, OpenCV's pixel
centres at integer coordinates like the project's K, the simulator and the splat renders; the
hit distance is the z-depth), cast only inside the projection of each model's bounding box.
A pixel of instance *i* counts as visible when

1. among all object instances, *i* is hit first (exact mutual occlusion of the meshes), and
2. the splat does not occlude it: the rendered splat depth (where the splat's alpha is at least
   the render's ``depth_alpha_min``) is not nearer than the object's depth by more than
   ``occlusion_tolerance`` (default 15 mm, the delta bop_toolkit uses when it estimates
   visibility from a depth image). The splat stands in for everything that is not an
   annotated object (table clutter, walls), because the bundle carries no other meshes.
   Where the splat renders the object itself its depth matches the mesh (within the tolerance),
   and silhouette edges blend towards the background (farther), so neither counts as occlusion.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.camera import PinholeCamera
from brave6d.transforms import invert, transform_points

CANVAS_FACTOR = 3
_NEAR = 1e-6


@dataclass(frozen=True)
class Visibility:
    px_count_all: int
    px_count_visib: int
    visib_fract: float
    bbox_obj: tuple[int, int, int, int] | None  # [x, y, w, h] (BOP: w = x_max - x_min), whole silhouette
    bbox_visib: tuple[int, int, int, int] | None

    def to_json(self) -> dict[str, Any]:
        return {"px_count_all": self.px_count_all, "px_count_visib": self.px_count_visib,
                "visib_fract": self.visib_fract,
                "bbox_obj": list(self.bbox_obj) if self.bbox_obj else None,
                "bbox_visib": list(self.bbox_visib) if self.bbox_visib else None}


def _bbox(xs: NDArray[np.integer], ys: NDArray[np.integer]) -> tuple[int, int, int, int] | None:
    if len(xs) == 0:
        return None
    x0, y0 = int(xs.min()), int(ys.min())
    return (x0, y0, int(xs.max()) - x0, int(ys.max()) - y0)


class VisibilityComputer:
    """Per-view visibility of object instances (see the module docstring).

    ``models``: ``(vertices, faces)`` in metres in the model frame, one per instance, in the
    same order as ``world_T_objs``.
    """

    def __init__(self, models: Sequence[tuple[NDArray[np.float64], NDArray[np.int64]]],
                 world_T_objs: Sequence[NDArray[np.float64]], occlusion_tolerance: float = 0.015) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.world_T_objs = [np.asarray(T, dtype=np.float64) for T in world_T_objs]
        self.tol = float(occlusion_tolerance)
        self._alone = []
        self._corners = []
        self._world = o3d.t.geometry.RaycastingScene()
        owner = {}
        for n, ((verts, faces), T) in enumerate(zip(models, self.world_T_objs)):
            alone = o3d.t.geometry.RaycastingScene()
            alone.add_triangles(o3d.core.Tensor(np.ascontiguousarray(verts, dtype=np.float32)),
                                o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
            self._alone.append(alone)
            lo, hi = verts.min(axis=0), verts.max(axis=0)
            self._corners.append(np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                           for z in (lo[2], hi[2])]))
            gid = self._world.add_triangles(
                o3d.core.Tensor(transform_points(T, verts).astype(np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
            owner[int(gid)] = n
        self._owner = np.full(max(owner, default=0) + 2, -1, dtype=np.int64)  # last slot: misses (-1)
        for gid, n in owner.items():
            self._owner[gid] = n
        self._lock = threading.Lock()  # Open3D scenes are shared between requests

    def _cast(self, scene: Any, origin: NDArray[np.float64], R: NDArray[np.float64],
              dirs: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
        o3d = self._o3d
        rays = np.empty((len(dirs), 6), dtype=np.float32)
        rays[:, :3] = origin
        R32 = np.asarray(R, dtype=np.float32)
        for k in range(3):
            rays[:, 3 + k] = dirs[:, 0] * R32[k, 0] + dirs[:, 1] * R32[k, 1] + dirs[:, 2] * R32[k, 2]
        with self._lock:
            out = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t = out["t_hit"].numpy()
        gid = out["geometry_ids"].numpy().astype(np.int64)
        return t, np.where(np.isfinite(t), gid, -1)

    def _roi(self, n: int, cam_T_obj: NDArray[np.float64], camera: PinholeCamera) -> tuple[int, int, int, int] | None:
        w, h = camera.width, camera.height
        pad = (CANVAS_FACTOR - 1) // 2
        lo_u, hi_u, lo_v, hi_v = -pad * w, (pad + 1) * w - 1, -pad * h, (pad + 1) * h - 1
        pts = transform_points(cam_T_obj, self._corners[n])
        z = pts[:, 2]
        if np.all(z <= _NEAR):
            return None
        if np.any(z <= _NEAR):
            return lo_u, hi_u, lo_v, hi_v
        u = camera.fx * pts[:, 0] / z + camera.cx
        v = camera.fy * pts[:, 1] / z + camera.cy
        u0, u1 = max(lo_u, int(np.floor(u.min())) - 1), min(hi_u, int(np.ceil(u.max())) + 1)
        v0, v1 = max(lo_v, int(np.floor(v.min())) - 1), min(hi_v, int(np.ceil(v.max())) + 1)
        if u0 > u1 or v0 > v1:
            return None
        return u0, u1, v0, v1

    def compute(self, world_T_cam: NDArray[np.float64], camera: PinholeCamera,
                splat_depth: NDArray[np.float32] | None = None) -> list[Visibility]:
        """Visibility of every instance, in instance order. ``splat_depth``: (H, W) metres, 0 = no data."""
        T = np.asarray(world_T_cam, dtype=np.float64)
        cam_T_world = invert(T)
        w, h = camera.width, camera.height
        out = []
        for n, world_T_obj in enumerate(self.world_T_objs):
            cam_T_obj = cam_T_world @ world_T_obj
            roi = self._roi(n, cam_T_obj, camera)
            if roi is None:
                out.append(Visibility(0, 0, 0.0, None, None))
                continue
            u0, u1, v0, v1 = roi
            u, v = np.meshgrid(np.arange(u0, u1 + 1, dtype=np.float64), np.arange(v0, v1 + 1, dtype=np.float64))
            u, v = u.ravel(), v.ravel()
            dirs = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)],
                            axis=1).astype(np.float32)
            obj_T_cam = invert(world_T_obj) @ T
            t_alone, _ = self._cast(self._alone[n], obj_T_cam[:3, 3], obj_T_cam[:3, :3], dirs)
            hit = np.isfinite(t_alone)
            px_all = int(hit.sum())
            xs, ys = u[hit].astype(np.int64), v[hit].astype(np.int64)
            if px_all == 0:
                out.append(Visibility(0, 0, 0.0, None, None))
                continue
            inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
            sel = np.nonzero(hit)[0][inside]
            vis = np.zeros(0, dtype=bool)
            if len(sel):
                _, gid = self._cast(self._world, T[:3, 3], T[:3, :3], dirs[sel])
                vis = self._owner[gid] == n
                if splat_depth is not None:
                    sd = splat_depth[ys[inside], xs[inside]]
                    occluded = (sd > 0) & (sd < t_alone[sel] - self.tol)
                    vis &= ~occluded
            vx, vy = xs[inside][vis], ys[inside][vis]
            px_vis = int(vis.sum())
            out.append(Visibility(px_all, px_vis, px_vis / px_all, _bbox(xs, ys) if px_vis else None,
                                  _bbox(vx, vy)))
        return out

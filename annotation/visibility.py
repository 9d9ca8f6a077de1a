"""Object masks by CPU ray casting (Open3D ``RaycastingScene``), one ray per pixel centre.

Per view and annotated instance:

* ``mask``: the object ALONE (no occluders) inside the image;
* ``mask_visib``: the pixels where the first surface hit, among all object instances and the
  scene's static meshes (table, clutter), belongs to this instance (so ``mask_visib`` is a
  subset of ``mask``);
* ``px_count_all`` and ``bbox_obj``: the whole silhouette, including the part outside the
  image, on a canvas three times the image size centred on it (as bop_toolkit's
  ``calc_gt_info.py`` does).

The object-alone silhouette is cast only inside the projection of the model's bounding box,
against one ray-casting scene per model built in the model frame (rays are moved into it), so
it costs little; the occlusion pass casts every pixel once per view against the world scene.
Pixel ``(u, v)`` is the ray through ``((u - cx) / fx, (v - cy) / fy, 1)`` (OpenCV, centres at
integer coordinates), the same convention as the simulated camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

from annotation.models import MeshData
from brave6d.camera import PinholeCamera
from brave6d.errors import BraveError
from brave6d.transforms import check_rigid, invert, transform_points

#: Size of the canvas for truncated silhouettes, in image sizes (bop_toolkit uses 3).
CANVAS_FACTOR = 3
_NEAR = 1e-6


@dataclass(frozen=True)
class InstanceMasks:
    """Masks and counts of one instance in one view (see the module docstring)."""

    mask: NDArray[np.bool_]
    mask_visib: NDArray[np.bool_]
    px_count_all: int
    bbox_all: tuple[int, int, int, int] | None  # [x, y, w, h] of the whole silhouette, image coordinates


def bbox_xywh(xs: NDArray[np.integer], ys: NDArray[np.integer]) -> tuple[int, int, int, int] | None:
    """BOP bounding box of pixel coordinates: ``[x_min, y_min, x_max - x_min, y_max - y_min]``
    (bop_toolkit's ``calc_2d_bbox``: width and height exclude the last pixel); None when empty."""
    if len(xs) == 0:
        return None
    x0, y0 = int(xs.min()), int(ys.min())
    return (x0, y0, int(xs.max()) - x0, int(ys.max()) - y0)


def _tensor_scene(vertices: NDArray[np.float64], faces: NDArray[np.int64]) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
    return scene


def _cast(scene: o3d.t.geometry.RaycastingScene, origin: NDArray[np.float64], R: NDArray[np.float64],
          dirs_cam: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """First hits of rays from ``origin`` along ``R @ d`` for camera-frame directions ``d`` (z = 1,
    so ``t`` is the z-depth). Returns ``t`` (inf = miss) and the geometry id (-1 = miss)."""
    rays = np.empty((len(dirs_cam), 6), dtype=np.float32)
    rays[:, :3] = origin
    R32 = np.asarray(R, dtype=np.float32)
    for k in range(3):  # R @ d per ray, without a BLAS call (slow for (N, 3) @ (3, 3) here)
        rays[:, 3 + k] = dirs_cam[:, 0] * R32[k, 0] + dirs_cam[:, 1] * R32[k, 1] + dirs_cam[:, 2] * R32[k, 2]
    out = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
    t = out["t_hit"].numpy()
    geometry = out["geometry_ids"].numpy().astype(np.int64)
    return t, np.where(np.isfinite(t), geometry, -1)


class MaskRenderer:
    """Masks of annotated instances for any camera pose (see the module docstring).

    ``models``: mesh per ``obj_id`` in metres (model frame); ``instances``: ``(obj_id,
    world_T_model)``; ``static``: occluding meshes already in the world frame (metres).
    """

    def __init__(self, camera: PinholeCamera, models: dict[int, MeshData],
                 instances: Sequence[tuple[int, ArrayLike]], static: Sequence[MeshData] = ()) -> None:
        if camera.has_distortion:
            raise BraveError("mask renderer: the camera must be the undistorted pinhole camera")
        self.camera = camera
        self.instances = [(int(obj_id), check_rigid(T, f"instance {n}: world_T_model"))
                          for n, (obj_id, T) in enumerate(instances)]
        missing = {obj_id for obj_id, _ in self.instances} - set(models)
        if missing:
            raise BraveError(f"mask renderer: no model for obj_id {sorted(missing)}")
        self._model_scenes = {obj_id: _tensor_scene(m.vertices, m.faces) for obj_id, m in models.items()}
        self._corners = {obj_id: _box_corners(m.vertices) for obj_id, m in models.items()}
        self._world = o3d.t.geometry.RaycastingScene()
        owner: dict[int, int] = {}
        for n, (obj_id, T) in enumerate(self.instances):
            m = models[obj_id]
            gid = self._world.add_triangles(
                o3d.core.Tensor(transform_points(T, m.vertices).astype(np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(m.faces, dtype=np.uint32)))
            owner[int(gid)] = n
        static_ids = [int(self._world.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(s.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(s.faces, dtype=np.uint32)))) for s in static]
        # owner per geometry id; one extra -1 at the end serves misses (geometry id -1)
        self._owner = np.full(max([*owner, *static_ids], default=0) + 2, -1, dtype=np.int64)
        for gid, n in owner.items():
            self._owner[gid] = n
        w, h = camera.width, camera.height
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        self._dirs = self._directions(u.ravel(), v.ravel())

    def _directions(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float32]:
        c = self.camera
        return np.stack([(u - c.cx) / c.fx, (v - c.cy) / c.fy, np.ones_like(u)], axis=1).astype(np.float32)

    def visible_instance_map(self, world_T_cam: ArrayLike) -> NDArray[np.int64]:
        """(H, W) index of the instance seen first at each pixel; -1 = static mesh or nothing."""
        T = check_rigid(world_T_cam, "world_T_cam")
        _, geometry = _cast(self._world, T[:3, 3], T[:3, :3], self._dirs)
        return self._owner[geometry].reshape(self.camera.height, self.camera.width)  # -1 indexes the sentinel

    def render(self, world_T_cam: ArrayLike) -> list[InstanceMasks]:
        """Masks of every instance, in instance order."""
        T = check_rigid(world_T_cam, "world_T_cam")
        visible = self.visible_instance_map(T)
        return [self._instance(n, obj_id, world_T_model, T, visible)
                for n, (obj_id, world_T_model) in enumerate(self.instances)]

    def _instance(self, n: int, obj_id: int, world_T_model: NDArray[np.float64], world_T_cam: NDArray[np.float64],
                  visible: NDArray[np.int64]) -> InstanceMasks:
        w, h = self.camera.width, self.camera.height
        mask = np.zeros((h, w), dtype=bool)
        roi = self._roi(obj_id, invert(world_T_cam) @ world_T_model)
        if roi is None:
            return InstanceMasks(mask, mask.copy(), 0, None)
        u0, u1, v0, v1 = roi
        u, v = np.meshgrid(np.arange(u0, u1 + 1, dtype=np.float64), np.arange(v0, v1 + 1, dtype=np.float64))
        u, v = u.ravel(), v.ravel()
        model_T_cam = invert(world_T_model) @ world_T_cam
        t, _ = _cast(self._model_scenes[obj_id], model_T_cam[:3, 3], model_T_cam[:3, :3], self._directions(u, v))
        hit = np.isfinite(t)
        xs, ys = u[hit].astype(np.int64), v[hit].astype(np.int64)
        inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
        mask[ys[inside], xs[inside]] = True
        mask_visib = mask & (visible == n)
        return InstanceMasks(mask, mask_visib, int(hit.sum()), bbox_xywh(xs, ys))

    def _roi(self, obj_id: int, cam_T_model: NDArray[np.float64]) -> tuple[int, int, int, int] | None:
        """Canvas pixel range ``(u0, u1, v0, v1)`` (inclusive) that can hold the silhouette."""
        w, h = self.camera.width, self.camera.height
        pad = (CANVAS_FACTOR - 1) // 2
        lo_u, hi_u, lo_v, hi_v = -pad * w, (pad + 1) * w - 1, -pad * h, (pad + 1) * h - 1
        pts = transform_points(cam_T_model, self._corners[obj_id])
        z = pts[:, 2]
        if np.all(z <= _NEAR):
            return None
        if np.any(z <= _NEAR):
            return lo_u, hi_u, lo_v, hi_v
        c = self.camera
        u = c.fx * pts[:, 0] / z + c.cx
        v = c.fy * pts[:, 1] / z + c.cy
        u0, u1 = max(lo_u, int(np.floor(u.min())) - 1), min(hi_u, int(np.ceil(u.max())) + 1)
        v0, v1 = max(lo_v, int(np.floor(v.min())) - 1), min(hi_v, int(np.ceil(v.max())) + 1)
        if u0 > u1 or v0 > v1:
            return None
        return u0, u1, v0, v1


def _box_corners(vertices: NDArray[np.float64]) -> NDArray[np.float64]:
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

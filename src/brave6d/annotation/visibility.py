"""Per-instance silhouettes and masks by CPU ray casting (Open3D ``RaycastingScene``), one ray per
pixel centre: the one implementation of BOP's ``scene_gt_info`` geometry in the project.

:class:`SilhouetteCaster` holds the scenes and answers two questions for any camera and pose:

* :meth:`~SilhouetteCaster.silhouettes`: the pixels of each instance ALONE (no occluders), on a
  canvas three times the image size centred on it (as bop_toolkit's ``calc_gt_info.py`` does), so
  a truncated object keeps its whole silhouette (``px_count_all``, ``bbox_obj``); each hit pixel
  also carries its z-depth and its ray;
* :meth:`~SilhouetteCaster.first_instance`: which instance is the first surface along given rays,
  among all instances and the static meshes (table, clutter).

:class:`MaskRenderer` turns them into the BOP export's ``mask`` (the object alone, inside the
image) and ``mask_visib`` (where the object is the first surface seen: a subset of ``mask``).
The server's visible fractions (``brave6d.serve.visibility``) use the same caster and add their
splat-occlusion rule on top.

The object-alone silhouette is cast only inside the projection of the model's bounding box,
against one ray-casting scene per model built in the model frame (rays are moved into it), so
it costs little. Pixel ``(u, v)`` is the ray through ``((u - cx) / fx, (v - cy) / fy, 1)``
(OpenCV, centres at integer coordinates), the same convention as the simulated camera, the
project's K and the splat renders; the hit distance along it is the z-depth.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.transforms import check_rigid, invert, transform_points

if TYPE_CHECKING:
    from brave6d.annotation.models import MeshData

#: Size of the canvas for truncated silhouettes, in image sizes (bop_toolkit uses 3).
CANVAS_FACTOR = 3
_NEAR = 1e-6

#: Triangles in metres: ``(vertices (V, 3), faces (F, 3))``.
Triangles = tuple[NDArray[np.float64], NDArray[np.int64]]


def bbox_xywh(xs: NDArray[np.integer], ys: NDArray[np.integer]) -> tuple[int, int, int, int] | None:
    """BOP bounding box of pixel coordinates: ``[x_min, y_min, x_max - x_min, y_max - y_min]``
    (bop_toolkit's ``calc_2d_bbox``: width and height exclude the last pixel); None when empty."""
    if len(xs) == 0:
        return None
    x0, y0 = int(xs.min()), int(ys.min())
    return (x0, y0, int(xs.max()) - x0, int(ys.max()) - y0)


def pixel_rays(camera: PinholeCamera, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float32]:
    """Camera-frame directions ``((u - cx) / fx, (v - cy) / fy, 1)`` of pixels ``(u, v)``, (N, 3)."""
    return np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)],
                    axis=1).astype(np.float32)


@dataclass(frozen=True)
class Silhouette:
    """The hit pixels of one instance alone on the canvas: ``xs``, ``ys`` (N,) int64 in image
    coordinates (may lie outside the image). Their z-depths and camera-frame rays stay in the
    arrays that were cast (``hit_index`` into ``cast_depth`` and ``cast_rays``), so that
    :meth:`within` the image copies only pixel indices."""

    xs: NDArray[np.int64]
    ys: NDArray[np.int64]
    hit_index: NDArray[np.int64]
    cast_depth: NDArray[np.float32]
    cast_rays: NDArray[np.float32]

    @property
    def px_count_all(self) -> int:
        return len(self.xs)

    @property
    def bbox_all(self) -> tuple[int, int, int, int] | None:
        """``[x, y, w, h]`` of the whole silhouette (BOP ``bbox_obj``); None when empty."""
        return bbox_xywh(self.xs, self.ys)

    @property
    def depth(self) -> NDArray[np.float32]:
        """(N,) z-depth of the hit pixels, metres."""
        return self.cast_depth[self.hit_index]

    @property
    def rays(self) -> NDArray[np.float32]:
        """(N, 3) camera-frame rays of the hit pixels (z = 1), to cast them again."""
        return self.cast_rays[self.hit_index]

    def within(self, width: int, height: int) -> Silhouette:
        """The part of this silhouette inside a ``width`` x ``height`` image."""
        inside = (self.xs >= 0) & (self.xs < width) & (self.ys >= 0) & (self.ys < height)
        return Silhouette(self.xs[inside], self.ys[inside], self.hit_index[inside], self.cast_depth, self.cast_rays)


@dataclass(frozen=True)
class SilhouetteBatch:
    """One instance's silhouettes seen from many cameras (:meth:`SilhouetteCaster.silhouettes_many`):
    the hit pixels of all cameras, camera ``owner[i]``'s pixel ``(xs[i], ys[i])`` with its z-depth and
    camera-frame ray ``(ray_x[i], ray_y[i], 1)``, grouped by camera in camera order."""

    cameras: int
    owner: NDArray[np.int64]
    xs: NDArray[np.int64]
    ys: NDArray[np.int64]
    depth: NDArray[np.float32]
    ray_x: NDArray[np.float32]
    ray_y: NDArray[np.float32]

    @property
    def px_count_all(self) -> NDArray[np.int64]:
        """(cameras,) pixels of each camera's whole silhouette."""
        return np.bincount(self.owner, minlength=self.cameras)

    @property
    def rays(self) -> NDArray[np.float32]:
        """(N, 3) camera-frame rays of the pixels (z = 1), as :func:`pixel_rays` gives them."""
        rays = np.empty((len(self.ray_x), 3), dtype=np.float32)
        rays[:, 0], rays[:, 1], rays[:, 2] = self.ray_x, self.ray_y, 1.0
        return rays

    def within(self, width: int, height: int) -> SilhouetteBatch:
        """The pixels inside a ``width`` x ``height`` image."""
        inside = (self.xs >= 0) & (self.xs < width) & (self.ys >= 0) & (self.ys < height)
        return SilhouetteBatch(self.cameras, self.owner[inside], self.xs[inside], self.ys[inside], self.depth[inside],
                               self.ray_x[inside], self.ray_y[inside])


_EMPTY = Silhouette(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32),
                    np.zeros((0, 3), np.float32))


def _tensor_scene(vertices: NDArray[np.float64], faces: NDArray[np.int64]) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
    return scene


class SilhouetteCaster:
    """Ray-casting scenes of posed object instances (see the module docstring).

    ``models``: triangles per model key in metres (model frame); ``instances``: ``(model key,
    world_T_model)``, the instance index is its position; ``static``: occluding triangles already
    in the world frame (metres). Safe to call from several threads (one lock around the casts:
    Open3D scenes are shared between calls).
    """

    def __init__(self, models: Mapping[int, Triangles], instances: Sequence[tuple[int, ArrayLike]],
                 static: Sequence[Triangles] = ()) -> None:
        self.instances = [(int(key), check_rigid(T, f"instance {n}: world_T_model"))
                          for n, (key, T) in enumerate(instances)]
        missing = {key for key, _ in self.instances} - set(models)
        if missing:
            raise BraveError(f"silhouettes: no model for obj_id {sorted(missing)}")
        self._model_T_world = [invert(T) for _, T in self.instances]
        self._model_scenes = {key: _tensor_scene(v, f) for key, (v, f) in models.items()}
        self._corners = {key: _box_corners(v) for key, (v, _) in models.items()}
        self._world = o3d.t.geometry.RaycastingScene()
        owner: dict[int, int] = {}
        for n, (key, T) in enumerate(self.instances):
            vertices, faces = models[key]
            gid = self._world.add_triangles(
                o3d.core.Tensor(transform_points(T, vertices).astype(np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
            owner[int(gid)] = n
        static_ids = [int(self._world.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))) for vertices, faces in static]
        # owner per geometry id; one extra -1 at the end serves misses (geometry id -1)
        self._owner = np.full(max([*owner, *static_ids], default=0) + 2, -1, dtype=np.int64)
        for gid, n in owner.items():
            self._owner[gid] = n
        self._lock = threading.Lock()
        self._canvas: dict[tuple[Any, ...], tuple[NDArray[np.float32], NDArray[np.float32], int, int]] = {}

    def _cast(self, scene: o3d.t.geometry.RaycastingScene, origin: NDArray[np.float64], R: NDArray[np.float64],
              rays_cam: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
        """First hits of rays from ``origin`` along ``R @ d`` for camera-frame directions ``d`` (z = 1,
        so ``t`` is the z-depth). Returns ``t`` (inf = miss) and the geometry id (-1 = miss)."""
        rays = np.empty((len(rays_cam), 6), dtype=np.float32)
        rays[:, :3] = origin
        R32 = np.asarray(R, dtype=np.float32)
        for k in range(3):  # R @ d per ray, without a BLAS call (slow for (N, 3) @ (3, 3) here)
            rays[:, 3 + k] = rays_cam[:, 0] * R32[k, 0] + rays_cam[:, 1] * R32[k, 1] + rays_cam[:, 2] * R32[k, 2]
        with self._lock:
            out = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t = out["t_hit"].numpy()
        geometry = out["geometry_ids"].numpy().astype(np.int64)
        return t, np.where(np.isfinite(t), geometry, -1)

    def silhouettes(self, world_T_cam: ArrayLike, camera: PinholeCamera) -> Iterator[Silhouette]:
        """Each instance alone, in instance order, seen from ``world_T_cam`` through the undistorted
        ``camera`` (a generator: one instance's cast arrays alive at a time)."""
        T = np.asarray(world_T_cam, dtype=np.float64)
        cam_T_world = invert(T)
        for (key, world_T_model), model_T_world in zip(self.instances, self._model_T_world):
            roi = self._roi(key, cam_T_world @ world_T_model, camera)
            if roi is None:
                yield _EMPTY
                continue
            u0, u1, v0, v1 = roi
            u, v = np.meshgrid(np.arange(u0, u1 + 1, dtype=np.float64), np.arange(v0, v1 + 1, dtype=np.float64))
            u, v = u.ravel(), v.ravel()
            rays = pixel_rays(camera, u, v)
            model_T_cam = model_T_world @ T
            t, _ = self._cast(self._model_scenes[key], model_T_cam[:3, 3], model_T_cam[:3, :3], rays)
            hit = np.isfinite(t)
            yield Silhouette(u[hit].astype(np.int64), v[hit].astype(np.int64), np.nonzero(hit)[0], t, rays)

    def first_instance(self, world_T_cam: ArrayLike, rays_cam: NDArray[np.float32]) -> NDArray[np.int64]:
        """(N,) index of the instance hit first along each camera-frame ray; -1 = a static mesh or nothing."""
        T = np.asarray(world_T_cam, dtype=np.float64)
        _, geometry = self._cast(self._world, T[:3, 3], T[:3, :3], rays_cam)
        return self._owner[geometry]  # -1 indexes the sentinel

    def silhouettes_many(self, world_T_cams: ArrayLike, camera: PinholeCamera,
                         instances: Sequence[int] | None = None) -> Iterator[SilhouetteBatch]:
        """:meth:`silhouettes` of many camera poses at once (many agents), one ray cast per instance
        for all of them: each instance's :class:`SilhouetteBatch`, in instance order. Its pixels of
        camera ``c`` equal ``silhouettes(world_T_cams[c], camera)``'s of that instance bit for bit:
        each pixel's ray is cast with the same operations, and only the pixels that cannot be hit
        are left out (:meth:`_roi_rows`: rows of the projected bounding box's hull, with the same
        one-pixel margin as :meth:`_roi`, instead of its whole bounding rectangle). ``instances``: only
        these instance indices, in this order (default: all)."""
        poses = np.asarray(world_T_cams, dtype=np.float64).reshape(-1, 4, 4)
        cam_T_world = _invert_many(poses)
        ray_x, ray_y, lo_u, lo_v = self._canvas_rays(camera)
        chosen = list(range(len(self.instances))) if instances is None else [int(n) for n in instances]
        if not chosen:
            return
        # every instance's rows at once (each camera's rows depend on its own box alone): instance k's are
        # those of the "cameras" k * C .. (k + 1) * C - 1
        c_count = len(poses)
        corners = [self._box_points(self.instances[n][0], cam_T_world @ self.instances[n][1]) for n in chosen]
        rows = self._hull_rows(np.concatenate(corners), camera)
        bounds = np.searchsorted(rows[0], np.arange(len(chosen) + 1) * c_count).tolist()
        for k, n in enumerate(chosen):
            (key, world_T_model), model_T_world = self.instances[n], self._model_T_world[n]
            lo, hi = bounds[k], bounds[k + 1]
            cams, v, u0, u1 = rows[0][lo:hi] - k * c_count, rows[1][lo:hi], rows[2][lo:hi], rows[3][lo:hi]
            sizes = u1 - u0 + 1
            starts = np.cumsum(sizes) - sizes
            owner = np.repeat(cams, sizes)
            u = np.repeat(u0 - starts, sizes) + np.arange(len(owner))
            vs = np.repeat(v, sizes)
            x, y = ray_x[u - lo_u], ray_y[vs - lo_v]
            model_T_cam = model_T_world @ poses
            t, _ = self._cast_many(self._model_scenes[key], model_T_cam[:, :3, 3], model_T_cam[:, :3, :3], owner,
                                   x, y)
            hit = np.isfinite(t)
            yield SilhouetteBatch(len(poses), owner[hit], u[hit], vs[hit], t[hit], x[hit], y[hit])

    def first_instance_many(self, world_T_cams: ArrayLike, owner: NDArray[np.int64], ray_x: NDArray[np.float32],
                            ray_y: NDArray[np.float32]) -> NDArray[np.int64]:
        """:meth:`first_instance` of rays from many camera poses: ray ``r`` is ``(ray_x[r], ray_y[r], 1)``
        (a :class:`SilhouetteBatch`'s columns) from camera ``owner[r]``."""
        poses = np.asarray(world_T_cams, dtype=np.float64).reshape(-1, 4, 4)
        _, geometry = self._cast_many(self._world, poses[:, :3, 3], poses[:, :3, :3], owner, ray_x, ray_y)
        return self._owner[geometry]

    def _cast_many(self, scene: o3d.t.geometry.RaycastingScene, origins: NDArray[np.float64],
                   Rs: NDArray[np.float64], owner: NDArray[np.int64], x: NDArray[np.float32], y: NDArray[np.float32]
                   ) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
        """:meth:`_cast` of rays from many cameras in one call: ray ``r`` from ``origins[owner[r]]`` along
        ``Rs[owner[r]] @ (x[r], y[r], 1)``, the same float32 arithmetic per ray as :meth:`_cast`'s
        (its ``1 * R`` is ``R`` exactly). Built column by column with 1-D gathers, so that building
        the rays costs less than casting them."""
        n = len(owner)
        rays = np.empty((n, 6), dtype=np.float32)
        g, tmp, acc = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
        o3 = np.asarray(origins, dtype=np.float32).reshape(-1, 3).T.copy()  # (3, cameras)
        for k in range(3):
            np.take(o3[k], owner, out=g)
            rays[:, k] = g
        R9 = np.asarray(Rs, dtype=np.float32).reshape(-1, 9).T.copy()  # (9, cameras): one row per entry
        for k in range(3):
            np.take(R9[3 * k], owner, out=g)
            np.multiply(x, g, out=acc)
            np.take(R9[3 * k + 1], owner, out=g)
            np.multiply(y, g, out=tmp)
            acc += tmp
            np.take(R9[3 * k + 2], owner, out=g)
            acc += g
            rays[:, 3 + k] = acc
        with self._lock:
            out = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t = out["t_hit"].numpy()
        geometry = out["geometry_ids"].numpy().astype(np.int64)
        return t, np.where(np.isfinite(t), geometry, -1)

    def _canvas_rays(self, camera: PinholeCamera) -> tuple[NDArray[np.float32], NDArray[np.float32], int, int]:
        """:func:`pixel_rays`' x per canvas column and y per canvas row (each depends on one
        coordinate only, computed as there), with the canvas' first column and row; kept per camera."""
        key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
        with self._lock:
            cached = self._canvas.get(key)
        if cached is None:
            pad = (CANVAS_FACTOR - 1) // 2
            u = np.arange(-pad * camera.width, (pad + 1) * camera.width, dtype=np.float64)
            v = np.arange(-pad * camera.height, (pad + 1) * camera.height, dtype=np.float64)
            cached = (((u - camera.cx) / camera.fx).astype(np.float32), ((v - camera.cy) / camera.fy).astype(np.float32),
                      -pad * camera.width, -pad * camera.height)
            with self._lock:
                if len(self._canvas) > 8:
                    self._canvas.clear()
                self._canvas[key] = cached
        return cached

    def _roi_rows(self, key: int, cam_T_models: NDArray[np.float64], camera: PinholeCamera
                  ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """The canvas pixels that can hold each pose's silhouette, row by row: ``(camera, v, u0, u1)``
        per row (inclusive, camera then row order). :meth:`_roi`'s rectangle, narrowed on each row to
        the pixels within one pixel of the convex hull of the bounding box's projected corners (a
        box wholly in front of the camera projects onto that hull, and the model lies in its box);
        a box partly behind the camera keeps the whole canvas, as in :meth:`_roi`."""
        return self._hull_rows(self._box_points(key, cam_T_models), camera)

    def _box_points(self, key: int, cam_T_models: NDArray[np.float64]) -> NDArray[np.float64]:
        """(cameras, 8, 3) the bounding box corners of model ``key`` in each camera's frame."""
        return np.einsum("cij,kj->cki", cam_T_models[:, :3, :3], self._corners[key]) + cam_T_models[:, None, :3, 3]

    @staticmethod
    def _hull_rows(pts: NDArray[np.float64], camera: PinholeCamera
                   ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """:meth:`_roi_rows` of the box corners ``pts`` (cameras, 8, 3) in the camera frames."""
        w, h = camera.width, camera.height
        pad = (CANVAS_FACTOR - 1) // 2
        lo_u, hi_u, lo_v, hi_v = -pad * w, (pad + 1) * w - 1, -pad * h, (pad + 1) * h - 1
        z = pts[..., 2]
        whole = np.all(z > _NEAR, axis=1)  # the box wholly in front: its projection is the corners' hull
        seen = np.any(z > _NEAR, axis=1)
        safe_z = np.where(whole[:, None], z, 1.0)
        pu_all = camera.fx * pts[..., 0] / safe_z + camera.cx  # (cameras, 8)
        pv_all = camera.fy * pts[..., 1] / safe_z + camera.cy
        rois = np.zeros((len(pts), 4), dtype=np.int64)  # _roi's rectangle per camera; empty: u1 < u0
        rois[:] = lo_u, hi_u, lo_v, hi_v
        rois[~seen, 1] = lo_u - 1
        if np.any(whole):
            rois[whole, 0] = np.maximum(lo_u, np.floor(pu_all[whole].min(axis=1)).astype(np.int64) - 1)
            rois[whole, 1] = np.minimum(hi_u, np.ceil(pu_all[whole].max(axis=1)).astype(np.int64) + 1)
            rois[whole, 2] = np.maximum(lo_v, np.floor(pv_all[whole].min(axis=1)).astype(np.int64) - 1)
            rois[whole, 3] = np.minimum(hi_v, np.ceil(pv_all[whole].max(axis=1)).astype(np.int64) + 1)
        rows = np.maximum(rois[:, 3] - rois[:, 2] + 1, 0) * (rois[:, 1] >= rois[:, 0])
        cams = np.repeat(np.arange(len(rois)), rows)
        v = np.repeat(rois[:, 2] - (np.cumsum(rows) - rows), rows) + np.arange(len(cams))
        u0, u1 = rois[cams, 0], rois[cams, 1]
        narrow_cams = np.flatnonzero(whole & (rows > 0))
        if len(narrow_cams):
            # the hull's extent on every line v = -1 .. rows + 1 of each narrowed camera (its edges are box
            # edges), then per row v the extent over the band [v - 1, v + 1]: its two lines and the
            # corners inside it
            lines = rows[narrow_cams] + 2
            first_line = np.cumsum(lines) - lines
            lc = np.repeat(narrow_cams, lines)
            at = (np.repeat(rois[narrow_cams, 2] - 1 - first_line, lines) + np.arange(len(lc))).astype(np.float64)
            i, j = _BOX_EDGES
            pu_lines, pv_lines = pu_all[lc], pv_all[lc]
            au, av, bu, bv = pu_lines[:, i], pv_lines[:, i], pu_lines[:, j], pv_lines[:, j]
            dv = bv - av
            flat = dv == 0.0
            s = (at[:, None] - av) / np.where(flat, 1.0, dv)
            cross = ~flat & (s >= 0.0) & (s <= 1.0)
            uu = au + s * (bu - au)
            line_min, line_max = np.where(cross, uu, np.inf).min(axis=1), np.where(cross, uu, -np.inf).max(axis=1)
            narrow = whole[cams]
            c, vv = cams[narrow], v[narrow]
            block = np.zeros(len(rois), dtype=np.int64)
            block[narrow_cams] = first_line
            below = block[c] + (vv - rois[c, 2])  # line v - 1 of row v
            pu, pv = pu_all[c], pv_all[c]
            in_band = (pv >= (vv - 1)[:, None]) & (pv <= (vv + 1)[:, None])
            umin = np.minimum(np.minimum(line_min[below], line_min[below + 2]),
                              np.where(in_band, pu, np.inf).min(axis=1))
            umax = np.maximum(np.maximum(line_max[below], line_max[below + 2]),
                              np.where(in_band, pu, -np.inf).max(axis=1))
            empty = ~np.isfinite(umin)
            lo = np.floor(np.where(empty, 0.0, umin)).astype(np.int64) - 1
            hi = np.ceil(np.where(empty, 0.0, umax)).astype(np.int64) + 1
            u0, u1 = u0.copy(), u1.copy()
            u0[narrow] = np.maximum(u0[narrow], lo)
            u1[narrow] = np.where(empty, u0[narrow] - 1, np.minimum(u1[narrow], hi))
        keep = u1 >= u0
        return cams[keep], v[keep], u0[keep], u1[keep]

    def _roi(self, key: int, cam_T_model: NDArray[np.float64],
             camera: PinholeCamera) -> tuple[int, int, int, int] | None:
        """Canvas pixel range ``(u0, u1, v0, v1)`` (inclusive) that can hold the silhouette."""
        w, h = camera.width, camera.height
        pad = (CANVAS_FACTOR - 1) // 2
        lo_u, hi_u, lo_v, hi_v = -pad * w, (pad + 1) * w - 1, -pad * h, (pad + 1) * h - 1
        pts = transform_points(cam_T_model, self._corners[key])
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


@dataclass(frozen=True)
class InstanceMasks:
    """Masks and counts of one instance in one view (see the module docstring)."""

    mask: NDArray[np.bool_]
    mask_visib: NDArray[np.bool_]
    px_count_all: int
    bbox_all: tuple[int, int, int, int] | None  # [x, y, w, h] of the whole silhouette, image coordinates


class MaskRenderer:
    """BOP masks of annotated instances for any camera pose (see the module docstring).

    ``models``: mesh per ``obj_id`` in metres (model frame); ``instances``: ``(obj_id,
    world_T_model)``; ``static``: occluding meshes already in the world frame (metres).
    """

    def __init__(self, camera: PinholeCamera, models: Mapping[int, MeshData],
                 instances: Sequence[tuple[int, ArrayLike]], static: Sequence[MeshData] = ()) -> None:
        if camera.has_distortion:
            raise BraveError("mask renderer: the camera must be the undistorted pinhole camera")
        self.camera = camera
        self.caster = SilhouetteCaster({k: (m.vertices, m.faces) for k, m in models.items()}, instances,
                                       [(s.vertices, s.faces) for s in static])
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
        self._image_rays = pixel_rays(camera, u.ravel(), v.ravel())

    def visible_instance_map(self, world_T_cam: ArrayLike) -> NDArray[np.int64]:
        """(H, W) index of the instance seen first at each pixel; -1 = static mesh or nothing."""
        T = check_rigid(world_T_cam, "world_T_cam")
        return self.caster.first_instance(T, self._image_rays).reshape(self.camera.height, self.camera.width)

    def render(self, world_T_cam: ArrayLike) -> list[InstanceMasks]:
        """Masks of every instance, in instance order."""
        T = check_rigid(world_T_cam, "world_T_cam")
        visible = self.visible_instance_map(T)
        return [self._instance(n, sil, visible) for n, sil in enumerate(self.caster.silhouettes(T, self.camera))]

    def _instance(self, n: int, sil: Silhouette, visible: NDArray[np.int64]) -> InstanceMasks:
        w, h = self.camera.width, self.camera.height
        mask = np.zeros((h, w), dtype=bool)
        seen = sil.within(w, h)
        mask[seen.ys, seen.xs] = True
        return InstanceMasks(mask, mask & (visible == n), sil.px_count_all, sil.bbox_all)


#: The 12 edges of a box as pairs of :func:`_box_corners`' indices (corner ``4 x + 2 y + z``): the
#: projection of a box wholly in front of a camera is the hull of its corners, bounded by box edges.
_BOX_EDGES = (np.array([a for bit in (1, 2, 4) for a in range(8) if not a & bit]),
              np.array([a | bit for bit in (1, 2, 4) for a in range(8) if not a & bit]))


def _invert_many(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`invert` of each rigid pose of ``poses`` (C, 4, 4)."""
    out = np.zeros_like(poses)
    Rt = np.swapaxes(poses[:, :3, :3], 1, 2)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("cij,cj->ci", Rt, poses[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def _box_corners(vertices: NDArray[np.float64]) -> NDArray[np.float64]:
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

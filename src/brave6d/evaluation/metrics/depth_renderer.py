"""Depth rendering of object meshes for the VSD pose error (CPU, BOP units).

Two methods, the same conventions:

- ``"gl"`` (the default): OpenGL's rasterisation rules as bop_toolkit's renderer meets them on
  Mesa's llvmpipe (float32 projection, vertices snapped to 1/256 px, the top-left fill rule,
  a 16-bit depth buffer; :mod:`brave6d.evaluation.metrics.gl_raster`), so VSD's errors equal
  bop_toolkit's to the pixel.
- ``"raycast"``: one ray per pixel centre with Open3D's ``RaycastingScene`` (tensor API): exact
  hits in float32, but a pixel whose centre lies within ~1e-3 px of a silhouette edge may be
  decided unlike a rasteriser (VSD errors then differ from bop_toolkit's by a pixel).

Conventions, as in the rest of the project:

- OpenCV pinhole camera without distortion (the project's K): pixel ``(u, v)`` (column, row)
  has its centre at integer coordinates, its ray is ``((u - cx) / fx, (v - cy) / fy, 1)`` in
  the camera frame: the rays of the simulator, of the masks and (after its own conversion) of
  the splat renders that episodes are scored on.
- Parity with bop_toolkit: its renderers (``renderer_vispy``, bop_renderer; OpenGL) sample
  pixel ``(u, v)`` at ``(u + 0.5, v + 0.5)`` in the coordinates of a BOP file's ``cam_K``. The BOP
  readers and the export convert ``cam_K`` to and from the project's K
  (``brave6d.evaluation.metrics.bop_results.read_scene_camera``, ``brave6d.annotation.bop_format.bop_cam_K``), so given
  a BOP dataset this renderer hits exactly the pixels bop_toolkit's renderer draws.
- The pose ``(R, t)`` maps model points to the camera frame: ``x_cam = R @ x_model + t``.
- Millimetres: vertices and ``t`` in mm, the returned z-depth in mm; 0 where no surface is hit.

For ray casting each object is put into its own ray-casting scene once, in the model frame; a
render transforms the rays into the model frame instead of the mesh, so the acceleration
structure is reused for every pose. Only the pixels inside the projected bounding box of the
mesh are cast when the whole mesh lies in front of the camera, which keeps renders of small
objects cheap.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import DataError
from brave6d.evaluation.metrics.gl_raster import bbox_corners, gl_depth

RenderFn = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]
"""``render_fn(R, t_mm) -> depth_mm (H, W)``: the renderer of one object for a fixed camera."""


METHODS = ("gl", "raycast")


@dataclass
class _Mesh:
    scene: Any  # open3d.t.geometry.RaycastingScene (method "raycast"), else None
    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    corners: NDArray[np.float64]


def _check_mesh(vertices_mm: ArrayLike, faces: ArrayLike, name: str) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    v = np.asarray(vertices_mm, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise DataError(f"{name}: vertices must be a non-empty (N, 3) array, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise DataError(f"{name}: vertices contain NaN or inf")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise DataError(f"{name}: faces must be a non-empty (M, 3) array of vertex indices, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        if not np.all(np.equal(np.mod(f, 1), 0)):
            raise DataError(f"{name}: faces must hold integer vertex indices")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise DataError(f"{name}: face indices out of range [0, {len(v) - 1}]")
    return v, f


def _check_camera(K: ArrayLike, width: int, height: int) -> NDArray[np.float64]:
    k = np.asarray(K, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise DataError(f"renderer: K must be finite with positive focal lengths, got {k.tolist()}")
    if int(width) < 1 or int(height) < 1:
        raise DataError(f"renderer: image size must be positive, got {width}x{height}")
    return k


class DepthRenderer:
    """Z-depth renderer (mm) for a set of object meshes, reused across poses and cameras.

    >>> r = DepthRenderer()
    >>> r.add_object(1, vertices_mm, faces)            # doctest: +SKIP
    >>> depth = r.render(1, R, t_mm, K, 640, 480)      # doctest: +SKIP
    """

    def __init__(self, nthreads: int = 0, method: str = "gl") -> None:
        if method not in METHODS:
            raise DataError(f"renderer: method must be one of {METHODS}, got {method!r}")
        self._meshes: dict[int, _Mesh] = {}
        self._nthreads = int(nthreads)
        self.method = method

    def __contains__(self, obj_id: object) -> bool:
        return obj_id in self._meshes

    def add_object(self, obj_id: int, vertices_mm: ArrayLike, faces: ArrayLike) -> None:
        """Register a triangle mesh (vertices in mm, model frame) under ``obj_id``."""
        v, f = _check_mesh(vertices_mm, faces, f"object {obj_id}")
        scene = None
        if self.method == "raycast":
            import open3d as o3d

            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
        self._meshes[int(obj_id)] = _Mesh(scene=scene, vertices=v, faces=f, corners=bbox_corners(v))

    def render(
        self,
        obj_id: int,
        R: ArrayLike,
        t_mm: ArrayLike,
        K: ArrayLike,
        width: int,
        height: int,
    ) -> NDArray[np.float64]:
        """Z-depth image (height, width) in mm of object ``obj_id`` at pose (R, t); 0 = no hit."""
        try:
            mesh = self._meshes[int(obj_id)]
        except KeyError:
            raise DataError(f"renderer: object {obj_id} was not added (known: {sorted(self._meshes)})") from None
        k = _check_camera(K, width, height)
        w, h = int(width), int(height)
        Rm = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t_mm, dtype=np.float64).reshape(3)
        depth = np.zeros((h, w), dtype=np.float64)
        if not (np.all(np.isfinite(Rm)) and np.all(np.isfinite(t))):
            return depth
        if self.method == "gl":
            return gl_depth(mesh.vertices, mesh.faces, mesh.corners, Rm, t, k, w, h)
        import open3d as o3d

        box = _projected_box(mesh.vertices, Rm, t, k, w, h)
        if box is None:
            return depth
        u0, u1, v0, v1 = box
        us = np.arange(u0, u1, dtype=np.float64)
        vs = np.arange(v0, v1, dtype=np.float64)
        uu, vv = np.meshgrid(us, vs)
        dirs_cam = np.stack(
            [(uu.ravel() - k[0, 2]) / k[0, 0], (vv.ravel() - k[1, 2]) / k[1, 1], np.ones(uu.size)], axis=1
        )
        # Rays in the model frame: origin -R^T t, direction R^T d (length kept, so t_hit = z).
        origin = -Rm.T @ t
        dirs_model = dirs_cam @ Rm
        rays = np.empty((len(dirs_model), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = dirs_model
        hit = mesh.scene.cast_rays(o3d.core.Tensor(rays), nthreads=self._nthreads)["t_hit"].numpy()
        z = np.where(np.isfinite(hit) & (hit > 0), hit, 0.0).astype(np.float64)
        depth[v0:v1, u0:u1] = z.reshape(len(vs), len(us))
        return depth

    def render_fn(self, obj_id: int, K: ArrayLike, width: int, height: int) -> RenderFn:
        """A ``render_fn(R, t_mm) -> depth_mm`` bound to one object and camera (for :func:`vsd`)."""
        k = _check_camera(K, width, height)

        def fn(R: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.float64]:
            return self.render(obj_id, R, t, k, width, height)

        return fn


def _projected_box(
    vertices: NDArray[np.float64], R: NDArray[np.float64], t: NDArray[np.float64], K: NDArray[np.float64], w: int, h: int
) -> tuple[int, int, int, int] | None:
    """Pixel box ``[u0, u1) x [v0, v1)`` that contains the projection; None when nothing can show.

    Falls back to the whole image when part of the mesh is at or behind the camera plane.
    """
    pts = vertices @ R.T + t
    z = pts[:, 2]
    if np.all(z <= 0):
        return None
    if np.any(z <= 1e-6):
        return 0, w, 0, h
    u = K[0, 0] * pts[:, 0] / z + K[0, 2]
    v = K[1, 1] * pts[:, 1] / z + K[1, 2]
    u0 = max(int(np.floor(u.min())) - 1, 0)
    u1 = min(int(np.ceil(u.max())) + 2, w)
    v0 = max(int(np.floor(v.min())) - 1, 0)
    v1 = min(int(np.ceil(v.max())) + 2, h)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def render_depth(
    vertices_mm: ArrayLike,
    faces: ArrayLike,
    R: ArrayLike,
    t_mm: ArrayLike,
    K: ArrayLike,
    width: int,
    height: int,
    method: str = "gl",
) -> NDArray[np.float64]:
    """One-off z-depth render (mm, 0 = no hit) of a mesh; use :class:`DepthRenderer` for many poses."""
    r = DepthRenderer(method=method)
    r.add_object(0, vertices_mm, faces)
    return r.render(0, R, t_mm, K, width, height)

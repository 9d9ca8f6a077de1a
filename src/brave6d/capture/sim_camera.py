"""Simulated camera: CPU ray casting of the scene's textured meshes (Open3D), Lambert shading.

:class:`SimCamera` implements the :class:`~brave6d.capture.protocols.Camera` protocol. ``capture()``
asks ``clock()`` for the (virtual) time ``t`` and ``pose_provider(t)`` for the TRUE
``world_T_cam``, renders, and applies the camera-side effects that the spec lists
(:mod:`brave6d.capture.effects`). :meth:`SimCamera.render` renders without effects (ground truth).

Rendering, per pixel centre (OpenCV convention, pixel (u, v) centred at integer coordinates):

* one ray through the camera model: pinhole, or the DISTORTED model when ``lens_distortion``
  is listed (its ``dist`` coefficients), so images carry real distortion; camera-frame ray
  directions are computed once (z = 1, so the hit parameter is the z-depth);
* depth: z-depth of the first hit, refined in float64 from the hit triangle's plane (exact to
  well below 1 mm); 0 outside ``depth_range`` or where nothing is hit;
* colour: texture (bilinear, trilinear mip-mapping from the pixel footprint) or barycentric
  vertex colours, times Lambert shading ``ambient + (1 - ambient) * max(0, n . l)`` with a
  fixed light travelling along ``light_direction`` (world frame) and flat (face) normals
  flipped towards the camera; ``background_rgb`` where nothing is hit. Shading is done on
  linear radiance and encoded to 8-bit sRGB at the end;
* anti-aliasing (RGB only; depth and ids always come from the pixel-centre ray): textures
  are mip-mapped; ``supersample = s`` casts s x s rays in every pixel (box filter; also
  sharpens strongly minified textures such as a far, tilted calibration board);
  ``edge_supersample = e`` casts e x e rays only in silhouette pixels (object/depth
  discontinuities, about 1.5 % of the demo's pixels), which removes jagged outlines for a
  few percent more time. Both default to 1 (off).

``Frame.extras``: ``object_ids`` (H, W) uint16 (0 = no object, k = ``spec.objects[k-1]``),
``world_T_cam_true`` (4x4), ``effects`` (camera-side effects applied, in order),
``effect_times_s`` (seconds per effect), ``frame_index``.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.spec import EffectsSpec, SceneSpec
from brave6d.core.transforms import check_rigid
from brave6d.capture.effects import EffectContext, apply_camera_effects, radiance_to_rgb8
from brave6d.capture.protocols import Frame
from brave6d.capture.scene_model import (
    STATIC_ID_BASE,
    Hits,
    SceneModel,
    TextureAtlas,
    srgb_to_linear,
)

PoseProvider = Callable[[float], NDArray[np.float64]]
Clock = Callable[[], float]

#: Grazing-angle limit of the texture footprint estimate (cosine).
_MIN_COS = 0.05
#: Mip level bias (log2 texels). A bilinear lookup at level log2(footprint) is a tent twice as wide
#: as the pixel's box; -0.5 matched a 4x4-supersampled (box-filtered) reference best in RMS.
_LOD_BIAS = -0.5
#: Largest difference (m) accepted between Embree's float32 hit and the float64 plane refinement.
_REFINE_TOLERANCE_M = 1e-3


@dataclass(frozen=True)
class RenderResult:
    """One rendered view without effects.

    ``rgb`` (H, W, 3) uint8 sRGB; ``radiance`` (H, W, 3) float32 linear; ``depth_m`` (H, W)
    float32 z-depth, 0 = outside the depth range or nothing hit; ``z_m`` (H, W) float32
    z-depth, inf = nothing hit (no range limit); ``object_ids`` (H, W) uint16 (0 = none);
    ``segment_ids`` (H, W) int32 (see :mod:`brave6d.capture.scene_model`). ``rgb`` is encoded on first use.
    """

    radiance: NDArray[np.float32]
    depth_m: NDArray[np.float32]
    z_m: NDArray[np.float32]
    object_ids: NDArray[np.uint16]
    segment_ids: NDArray[np.int32]

    @cached_property
    def rgb(self) -> NDArray[np.uint8]:
        """8-bit sRGB of ``radiance``, byte-identical to a capture with no effects listed."""
        return radiance_to_rgb8(self.radiance)


@dataclass(frozen=True)
class _Rays:
    """Camera-frame ray directions (z = 1) of one camera model, computed once."""

    camera: PinholeCamera
    centre: NDArray[np.float64]  # (H*W, 3) pixel centres, row-major
    centre_len: NDArray[np.float32]  # (H*W,) their lengths
    sub: NDArray[np.float64] | None  # (H*W*s*s, 3) sub-pixel samples, pixel-major; None if s == 1
    sub_len: NDArray[np.float32] | None
    centre_in_sub: int | None  # index of the pixel-centre sample within a pixel's s*s (odd s)
    d_du: NDArray[np.float64]  # (H*W, 3) change of the centre direction per pixel step in u
    d_dv: NDArray[np.float64]  # (H*W, 3) ... and in v (to place sub-pixel rays by interpolation)


def _camera_rays(camera: PinholeCamera, supersample: int) -> _Rays:
    def directions(pixels: NDArray[np.float64]) -> NDArray[np.float64]:
        xy = camera.normalized_rays(pixels)
        return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)

    def length(d: NDArray[np.float64]) -> NDArray[np.float32]:
        return np.linalg.norm(d, axis=1).astype(np.float32)

    grid = camera.pixel_grid()
    centre = directions(grid)
    d_dv, d_du = np.gradient(centre.reshape(camera.height, camera.width, 3), axis=(0, 1)) \
        if min(camera.height, camera.width) > 1 else (np.zeros_like(centre), np.zeros_like(centre))
    d_du, d_dv = d_du.reshape(-1, 3), d_dv.reshape(-1, 3)
    if supersample == 1:
        return _Rays(camera, centre, length(centre), None, None, None, d_du, d_dv)
    s = supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    du, dv = np.meshgrid(offsets, offsets)
    sub_offsets = np.stack([du.ravel(), dv.ravel()], axis=1)  # (s*s, 2)
    sub_pixels = (grid[:, None, :] + sub_offsets[None, :, :]).reshape(-1, 2)
    centre_index = (s * s) // 2 if s % 2 == 1 else None
    sub = directions(sub_pixels)
    return _Rays(camera, centre, length(centre), sub, length(sub), centre_index, d_du, d_dv)


def silhouette_mask(segment_ids: NDArray[np.int32], z_m: NDArray[np.float32],
                    relative_jump: float = 0.02) -> NDArray[np.bool_]:
    """Pixels next to a change of segment or a depth jump above ``relative_jump`` (both sides)."""
    z = np.where(np.isfinite(z_m), z_m, np.float32(1e6))
    edge = np.zeros(segment_ids.shape, dtype=bool)
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        ta, tb = tuple(a), tuple(b)
        jump = (segment_ids[ta] != segment_ids[tb]) | (np.abs(z[ta] - z[tb]) > relative_jump * np.minimum(z[ta], z[tb]))
        edge[ta] |= jump
        edge[tb] |= jump
    return edge


def sample_atlas(atlas: TextureAtlas, texture_id: NDArray[np.int64], uv: NDArray[np.float32],
                 lod: NDArray[np.float32]) -> NDArray[np.float32]:
    """Trilinear texture lookup: bilinear (repeating, OBJ UVs with the origin bottom-left) in the
    two mip levels around ``lod`` (log2 of texels per sample), blended by its fraction."""
    n = len(uv)
    if n == 0:
        return np.zeros((0, 3), dtype=np.float32)
    top = (np.take(atlas.level_count, texture_id) - 1).astype(np.float32)
    lod = np.clip(lod, np.float32(0.0), top)
    base = np.floor(lod)
    frac = (lod - base)[:, None]
    first = np.take(atlas.first_level, texture_id)
    level = first + base.astype(np.int64)
    fine = _sample_levels(atlas, level, uv)
    coarse = _sample_levels(atlas, np.minimum(level + 1, first + top.astype(np.int64)), uv)
    return fine + (coarse - fine) * frac


def _wrap(value: NDArray[np.float32], period: NDArray[np.float32]) -> NDArray[np.float32]:
    """``value mod period`` in [0, period] (floor form: several times faster than ``np.mod``)."""
    return value - np.floor(value / period) * period


def _sample_levels(atlas: TextureAtlas, level: NDArray[np.int64], uv: NDArray[np.float32]) -> NDArray[np.float32]:
    """Bilinear lookup of each sample in its own atlas level (wrap gutters handle the edges)."""
    import cv2

    size = np.take(atlas.size, level, axis=0)
    offset = np.take(atlas.offset, level, axis=0)
    x = _wrap(uv[:, 0] * size[:, 0] - np.float32(0.5), size[:, 0]) + offset[:, 0]
    y = _wrap((np.float32(1.0) - uv[:, 1]) * size[:, 1] - np.float32(0.5), size[:, 1]) + offset[:, 1]
    n = len(x)
    cols = 1024
    rows = -(-n // cols)
    map_x = np.zeros(rows * cols, dtype=np.float32)
    map_y = np.zeros(rows * cols, dtype=np.float32)
    map_x[:n] = x
    map_y[:n] = y
    out = cv2.remap(atlas.image, map_x.reshape(rows, cols), map_y.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * cols, 3)[:n]


class SimCamera:
    """A simulated RGB-D camera looking at a :class:`SceneModel` from ``pose_provider(t)``.

    ``intrinsics``: image size and pinhole parameters; its ``dist`` is ignored (distortion is
    the ``lens_distortion`` effect). ``effects``: the spec's :class:`EffectsSpec` (only
    camera-side ones act here). ``seed``: makes every frame reproducible (frame ``i``'s
    noise depends only on seed, i and the effect). ``supersample`` / ``edge_supersample``: RGB
    anti-aliasing factors for every pixel / silhouette pixels only (see the module docstring).
    """

    def __init__(self, scene_model: SceneModel, intrinsics: PinholeCamera, effects: EffectsSpec | None,
                 pose_provider: PoseProvider, clock: Clock, seed: int = 0,
                 light_direction: Sequence[float] = (0.3, -0.2, -1.0), ambient: float = 0.35,
                 background_rgb: Sequence[int] = (200, 200, 205), depth_range: tuple[float, float] = (0.1, 4.0),
                 *, supersample: int = 1, edge_supersample: int = 1, with_depth: bool = True) -> None:
        self.model = scene_model
        self.effects = effects if effects is not None else EffectsSpec()
        self._pose_provider = pose_provider
        self._clock = clock
        self.seed = int(seed)
        light = np.asarray(light_direction, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(light)) or np.linalg.norm(light) < 1e-12:
            raise BraveError(f"sim camera: light_direction must be a finite non-zero vector, got {light.tolist()}")
        self._to_light = (-light / np.linalg.norm(light)).astype(np.float32)
        if not 0.0 <= ambient <= 1.0:
            raise BraveError(f"sim camera: ambient must be in [0, 1], got {ambient}")
        self.ambient = float(ambient)
        bg = np.asarray(background_rgb, dtype=np.float64).reshape(3)
        if np.any(bg < 0) or np.any(bg > 255):
            raise BraveError(f"sim camera: background_rgb must be 0..255, got {bg.tolist()}")
        self._background = srgb_to_linear(bg)
        lo, hi = (float(x) for x in depth_range)
        if not 0.0 <= lo < hi:
            raise BraveError(f"sim camera: depth_range must be 0 <= min < max, got {depth_range}")
        self.depth_range = (lo, hi)
        if int(supersample) != supersample or not 1 <= supersample <= 4:
            raise BraveError(f"sim camera: supersample must be an integer in 1..4, got {supersample}")
        self.supersample = int(supersample)
        if int(edge_supersample) != edge_supersample or not 1 <= edge_supersample <= 5:
            raise BraveError(f"sim camera: edge_supersample must be an integer in 1..5, got {edge_supersample}")
        self.edge_supersample = int(edge_supersample)
        self.with_depth = bool(with_depth)
        lens = self.effects.lens_distortion
        base = intrinsics.without_distortion()
        self._camera = base if lens is None else PinholeCamera(
            base.width, base.height, base.fx, base.fy, base.cx, base.cy, tuple(lens.dist))
        self._rays_cache: dict[PinholeCamera, _Rays] = {}
        self._rays = self._rays_for(self._camera)
        self.frame_index = 0
        self._closed = False

    # ------------------------------------------------------------------ construction from a spec
    @classmethod
    def from_spec(cls, spec: SceneSpec, pose_provider: PoseProvider, clock: Clock, *, calibration: bool = False,
                  scene_model: SceneModel | None = None, supersample: int = 1,
                  edge_supersample: int = 1) -> SimCamera:
        """Camera of ``spec``: its simulation settings and effects, nominal intrinsics, depth range
        and ``capture.depth``. ``calibration`` adds the board (same lens, same effects)."""
        sim = spec.simulation
        effects = EffectsSpec() if sim is None else sim.effects
        model = scene_model if scene_model is not None else SceneModel.from_spec(spec, include_board=calibration)
        kwargs = {} if sim is None else {
            "seed": sim.seed, "light_direction": sim.light_direction, "ambient": sim.ambient,
            "background_rgb": sim.background_rgb}
        return cls(model, spec.camera.pinhole(), effects, pose_provider, clock,
                   depth_range=(spec.camera.depth_min_m, spec.camera.depth_max_m),
                   supersample=supersample, edge_supersample=edge_supersample, with_depth=spec.capture.depth,
                   **kwargs)  # type: ignore[arg-type]

    # ------------------------------------------------------------------ Camera protocol
    @property
    def intrinsics(self) -> PinholeCamera:
        """The TRUE camera model of the images (with the ``lens_distortion`` coefficients if listed)."""
        return self._camera

    def capture(self) -> Frame:
        """Render the view at ``pose_provider(clock())`` and apply the listed effects."""
        if self._closed:
            raise BraveError("sim camera: capture() after close()")
        t = float(self._clock())
        world_T_cam = check_rigid(self._pose_provider(t), "sim camera: pose_provider(t)")
        result = self.render(world_T_cam)
        index = self.frame_index
        self.frame_index += 1
        ctx = EffectContext(camera=self._camera, rays_cam=self._rays.centre, z_m=result.z_m,
                            world_T_cam=world_T_cam, time_s=t, pose_at=self._pose_provider,
                            depth_range=self.depth_range)
        out = apply_camera_effects(result.radiance, result.depth_m if self.with_depth else None, self.effects,
                                   ctx, lambda name: self.rng_for(name, index))
        applied = (["lens_distortion"] if self.effects.lens_distortion is not None else []) + out.applied
        extras = {"object_ids": result.object_ids, "world_T_cam_true": world_T_cam, "effects": applied,
                  "effect_times_s": out.timings_s, "frame_index": index}
        return Frame(rgb=out.rgb, depth_m=out.depth_m, timestamp=t, extras=extras)

    def close(self) -> None:
        """Nothing to release; later captures raise."""
        self._closed = True

    # ------------------------------------------------------------------ randomness
    def rng_for(self, effect: str, frame_index: int) -> np.random.Generator:
        """The generator of ``effect`` in frame ``frame_index`` (independent of other effects)."""
        return np.random.default_rng([self.seed & 0xFFFFFFFF, frame_index, zlib.crc32(effect.encode())])

    # ------------------------------------------------------------------ rendering
    def _rays_for(self, camera: PinholeCamera) -> _Rays:
        rays = self._rays_cache.get(camera)
        if rays is None:
            rays = _camera_rays(camera, self.supersample)
            self._rays_cache[camera] = rays
        return rays

    def render(self, world_T_cam: ArrayLike, camera: PinholeCamera | None = None) -> RenderResult:
        """Render ``world_T_cam`` without effects (lens distortion, being geometry, stays).

        ``camera`` renders another camera model instead (its own ``dist`` is used as given).
        """
        T = check_rigid(world_T_cam, "sim camera: world_T_cam")
        rays = self._rays if camera is None else self._rays_for(camera)
        cam = rays.camera
        R = T[:3, :3]
        origin = T[:3, 3]
        s = self.supersample

        centre_dirs = _rotate(rays.centre, R)  # float64 world directions, |z_cam| = 1
        centre_rays = _ray_array(origin, centre_dirs)
        if rays.sub is None:
            sub_rays, sub_len = centre_rays, rays.centre_len
        else:
            sub_rays, sub_len = _ray_array(origin, _rotate(rays.sub, R)), rays.sub_len
        sub_hits = self.model.cast(sub_rays)
        if rays.sub is None:
            hits = sub_hits
        elif rays.centre_in_sub is not None:
            k = rays.centre_in_sub
            hits = Hits(sub_hits.hit[k::s * s], sub_hits.triangle[k::s * s], sub_hits.bary[k::s * s], sub_hits.t[k::s * s])
        else:
            hits = self.model.cast(centre_rays)

        focal = math.sqrt(cam.fx * cam.fy)
        radiance = self._shade(sub_hits, sub_rays[:, 3:], sub_len, focal * s)
        if rays.sub is not None:
            radiance = radiance.reshape(-1, s * s, 3).mean(axis=1)
        h, w = cam.height, cam.width
        radiance = radiance.reshape(h, w, 3).astype(np.float32)

        z = self._refined_depth(hits, origin, centre_dirs)
        z_img = z.reshape(h, w).astype(np.float32)
        lo, hi = self.depth_range
        depth = np.where((z_img >= lo) & (z_img <= hi), z_img, np.float32(0.0)).astype(np.float32)
        segments = np.where(hits.hit, np.take(self.model.tri_segment, np.where(hits.hit, hits.triangle, 0)), 0)
        segments = segments.astype(np.int32).reshape(h, w)
        objects = np.where((segments > 0) & (segments < STATIC_ID_BASE), segments, 0).astype(np.uint16)
        if rays.sub is None and self.edge_supersample > 1:
            self._antialias_edges(radiance, silhouette_mask(segments, z_img), rays, R, origin, focal)
        return RenderResult(radiance=radiance, depth_m=depth, z_m=z_img, object_ids=objects, segment_ids=segments)

    def _antialias_edges(self, radiance: NDArray[np.float32], edge: NDArray[np.bool_], rays: _Rays,
                         R: NDArray[np.float64], origin: NDArray[np.float64], focal: float) -> None:
        """Replace the radiance of ``edge`` pixels by the mean of e x e sub-pixel rays (in place).

        Sub-pixel directions are interpolated linearly from the pixel-centre grid (exact for a
        pinhole camera; for a distorted one the error over half a pixel is far below 0.01 px).
        """
        idx = np.flatnonzero(edge)
        if idx.size == 0:
            return
        e = self.edge_supersample
        offsets = (np.arange(e) + 0.5) / e - 0.5
        du, dv = (a.ravel()[None, :, None] for a in np.meshgrid(offsets, offsets))
        d_cam = (rays.centre[idx][:, None, :] + du * rays.d_du[idx][:, None, :] + dv * rays.d_dv[idx][:, None, :])
        d_cam = d_cam.reshape(-1, 3)
        sub_rays = _ray_array(origin, _rotate(d_cam, R))
        sub_hits = self.model.cast(sub_rays)
        d_len = np.linalg.norm(d_cam, axis=1).astype(np.float32)
        shaded = self._shade(sub_hits, sub_rays[:, 3:], d_len, focal * e).reshape(-1, e * e, 3).mean(axis=1)
        radiance.reshape(-1, 3)[idx] = shaded

    def _refined_depth(self, hits: Hits, origin: NDArray[np.float64], dirs: NDArray[np.float64]) -> NDArray[np.float64]:
        """z-depth per ray (inf = no hit): exact ray/plane intersection of the hit triangle in float64."""
        model = self.model
        tri = np.where(hits.hit, hits.triangle, 0)
        n = np.take(model.tri_normal, tri, axis=0)
        denom = n[:, 0] * dirs[:, 0] + n[:, 1] * dirs[:, 1] + n[:, 2] * dirs[:, 2]
        t32 = hits.t.astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            t64 = (np.take(model.tri_plane, tri) - _dot(n, origin)) / denom
        good = hits.hit & (np.abs(denom) > 1e-9) & (np.abs(t64 - t32) < _REFINE_TOLERANCE_M)
        return np.where(good, t64, t32)

    def _shade(self, hits: Hits, dirs: NDArray[np.float32], dir_len: NDArray[np.float32],
               pixels_per_radian: float) -> NDArray[np.float32]:
        """Linear radiance per ray: albedo x Lambert, background where nothing was hit."""
        model = self.model
        hit = hits.hit
        tri = np.where(hit, hits.triangle, 0)
        normal = np.take(model.tri_normal32, tri, axis=0)
        n_dot_d = normal[:, 0] * dirs[:, 0] + normal[:, 1] * dirs[:, 1] + normal[:, 2] * dirs[:, 2]
        n_dot_l = _dot(normal, self._to_light)
        facing = np.where(n_dot_d > 0, -n_dot_l, n_dot_l)  # normal flipped towards the camera
        lambert = np.float32(self.ambient) + np.float32(1.0 - self.ambient) * np.maximum(facing, np.float32(0.0))

        b = hits.bary
        w1 = b[:, 0:1]
        w2 = b[:, 1:2]
        w0 = np.float32(1.0) - w1 - w2
        c = np.take(model.tri_color, tri, axis=0)
        albedo = c[:, 0] * w0 + c[:, 1] * w1 + c[:, 2] * w2
        if model.textures:
            texture_id = np.take(model.tri_texture, tri)
            textured = np.flatnonzero(hit & (texture_id >= 0))
            if len(textured):
                t_tri = tri[textured]
                uvs = np.take(model.tri_uv, t_tri, axis=0)
                uv = uvs[:, 0] * w0[textured] + uvs[:, 1] * w1[textured] + uvs[:, 2] * w2[textured]
                # Footprint of one sample on the surface in texels: ray length / focal (px per
                # radian), stretched by 1/sqrt(cos) (geometric mean of both axes), x density.
                ray_len = hits.t[textured] * dir_len[textured]
                cos = np.maximum(np.abs(n_dot_d[textured]) / dir_len[textured], np.float32(_MIN_COS))
                density = np.take(model.tri_texel_density, t_tri)
                footprint = density * ray_len / (np.float32(pixels_per_radian) * np.sqrt(cos))
                lod = (np.log2(np.maximum(footprint, np.float32(1.0))) + np.float32(_LOD_BIAS)).astype(np.float32)
                albedo[textured] = sample_atlas(model.atlas, texture_id[textured], uv, lod)
        radiance = albedo * lambert[:, None]
        radiance[~hit] = self._background
        return radiance


def _rotate(vectors: NDArray[np.float64], R: NDArray[np.float64]) -> NDArray[np.float64]:
    """``vectors @ R.T`` for (N, 3) arrays, written out: a BLAS call for a 3x3 product spins up
    threads that fight Open3D's for the two cores (measured 2 ms vs up to 150 ms)."""
    return vectors[:, 0:1] * R[:, 0] + vectors[:, 1:2] * R[:, 1] + vectors[:, 2:3] * R[:, 2]


def _dot(vectors: NDArray[np.floating], v: NDArray[np.floating]) -> NDArray[np.floating]:
    """Row-wise dot product of (N, 3) with a 3-vector, without BLAS (see :func:`_rotate`)."""
    return vectors[:, 0] * v[0] + vectors[:, 1] * v[1] + vectors[:, 2] * v[2]


def _ray_array(origin: NDArray[np.float64], dirs: NDArray[np.float64]) -> NDArray[np.float32]:
    rays = np.empty((len(dirs), 6), dtype=np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = dirs
    return rays

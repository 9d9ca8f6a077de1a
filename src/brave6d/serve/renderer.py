"""Render one view of a bundle's Gaussians with :func:`brave6d.training.rasterize` (forward only).

* The splat is read once (``brave6d.training.read_ply``; or handed over in memory with
  :meth:`SplatRenderer.from_splat`), activated (``sigmoid`` opacity, ``exp``
  scale, normalised ``wxyz`` quaternion, SH ``[N, K, 3]``) and kept on the chosen device
  (``cuda`` or ``cpu``; ``auto`` picks CUDA when torch sees a GPU: ``brave6d.training.resolve_device``).
* A splat with a NaN or inf parameter, no Gaussians, or none visible is refused at load with a
  message naming the file (:func:`brave6d.serve.splat_check.check_splat`), never served half-broken.
* Gaussians whose activated opacity is below 1/255 are dropped at load: the rasterizer skips
  any Gaussian whose alpha ``o * exp(-sigma) <= o`` is below 1/255, so they can never change a
  pixel (lossless).
* Per request, Gaussians that cannot reach the image are culled on the device before the
  rasterizer runs: centres outside ``(near, far)`` (the rasterizer drops those itself) and
  Gaussians whose screen footprint, bounded from above through the largest scale and the
  projection Jacobian (see :meth:`SplatRenderer._cull`), lies outside the image. Lossless
  too (the rasterizer would draw nothing of them); it saves their projection and binning.
* Anti-aliasing (Mip-Splatting) as the splat was trained: the PLY's ``filter_3d`` (the 3D
  smoothing filter) is folded into the scales and opacities at load
  (:func:`brave6d.training.apply_filter_3d`, the trainer's function), and ``antialiasing="mip"``
  renders with the rasterizer's 2D mip filter (``antialiased``). The server passes its bundle's
  ``render.antialiasing``; left None, it follows the splat (``mip`` when it has ``filter_3d``).
* SH bands that are all zero (a degree-2 model saved with 45 ``f_rest``) are not evaluated.
* Renders run under ``torch.no_grad`` and one lock: the CPU kernels use every core, and
  concurrent renders would only slow each other down. ``render_ms`` is the wall time of the
  rasterizer call (including waiting for the GPU), ``queue_ms`` the wait for the lock. A render whose
  request was withdrawn while it waited for the lock is skipped (:data:`STILL_WANTED`).
* Many views at once (:meth:`SplatRenderer.render_batch`, N agents on one scene): a rasterizer
  call draws several cameras over the union of their culled sets, each view bit for bit its
  :meth:`SplatRenderer.render`; on CUDA one gsplat call takes every camera, on the CPU cameras
  that share most of their Gaussians share a call (``CPU_BATCH_OVERLAP``).
  :meth:`SplatRenderer.render` is a batch of one.
* Depth is z-depth in the camera frame (metres, float32) with a depth sensor's semantics: 0 (= no
  data, the project's depth convention) where the splat's alpha is below ``depth_alpha_min`` (no
  surface there), and with ``depth_mode="median"`` (the bundles' default) the depth of the one
  surface that takes the pixel's transmittance across 0.5, never a blend of a foreground and a
  background surface at an edge; ``"expected"`` is the alpha-weighted mean (older bundles).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.transforms import invert
from brave6d.serve.splat_check import MIN_ALPHA, activated_opacity, check_splat

#: CPU batches (:meth:`SplatRenderer._groups`): cameras share a rasterizer call while its work
#: (cameras x the union of their culled Gaussians) is at most this times that of separate calls.
CPU_BATCH_OVERLAP = 1.25

#: The most camera x Gaussian pairs one rasterizer call may hold: gsplat keeps each camera's
#: projection of each Gaussian (about 50 bytes a pair), so 2^27 pairs stay near 7 GB. A batch
#: larger than that is drawn in several calls (each view still equals its single render).
MAX_PAIRS_PER_CALL = 1 << 27

#: The depths a render may report (the module docstring; ``brave6d.training.rasterize``'s median_depth).
DEPTH_MODES = ("median", "expected")

#: Asked once a render holds the device lock, before it draws: a callable returning False withdraws
#: the render (:class:`RenderWithdrawn`), so a request whose client has gone, or that timed out while
#: it waited for the device, costs no render (set per action by :mod:`brave6d.serve.inflight`).
STILL_WANTED: ContextVar[Callable[[], bool] | None] = ContextVar("brave6d_render_still_wanted", default=None)


class RenderWithdrawn(Exception):
    """The render's request was withdrawn while it waited for the device: nothing was drawn."""

if TYPE_CHECKING:
    from brave6d.training import SplatData


def _check_poses(world_T_cams: Sequence[NDArray[np.float64]] | NDArray[np.float64]) -> NDArray[np.float64]:
    """``world_T_cams`` as a [C, 4, 4] float64 array (C >= 1), or a BraveError saying what is wrong."""
    poses = np.asarray(world_T_cams, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] == 0:
        raise BraveError(f"render_batch: world_T_cams must be one or more 4x4 poses ([C, 4, 4]), got shape {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise BraveError("render_batch: world_T_cams holds NaN or inf")
    return poses


def effective_sh_degree(shN: NDArray[np.float32]) -> int:
    """The lowest SH degree that represents ``shN`` [N, K, 3] exactly: PLY writers pad lower-degree
    models with zero coefficients (e.g. a degree-2 model saved with 45 ``f_rest``), and evaluating
    those zero bands changes nothing but costs time."""
    from brave6d.training import sh_degree_for

    degree = sh_degree_for(shN.shape[1])
    while degree > 0:
        lo = degree * degree - 1  # coefficients of degree `degree` are [lo, (degree+1)^2 - 1)
        if np.any(shN[:, lo:(degree + 1) ** 2 - 1]):
            break
        degree -= 1
    return degree


@dataclass(frozen=True)
class RenderOutput:
    rgb: NDArray[np.uint8]  # (H, W, 3)
    depth: NDArray[np.float32]  # (H, W) metres, 0 = no data
    alpha: NDArray[np.float32]  # (H, W)
    render_ms: float
    queue_ms: float
    gaussians_drawn: int


class SplatRenderer:
    """The Gaussians of one splat PLY, ready to render (see the module docstring)."""

    def __init__(self, splat_path: Path | str, device: str = "auto", cull: bool = True,
                 antialiasing: str | None = None) -> None:
        from brave6d.training import read_ply

        self._load(read_ply(splat_path), splat_path, device, cull, antialiasing)

    @classmethod
    def from_splat(cls, splat: SplatData, device: str = "auto", cull: bool = True,
                   source: str = "in-memory splat", antialiasing: str | None = None) -> SplatRenderer:
        """A renderer of ``splat`` as it is in memory (no PLY file); ``source`` names it in errors."""
        renderer = cls.__new__(cls)
        renderer._load(splat, source, device, cull, antialiasing)
        return renderer

    def _load(self, splat: SplatData, source: Path | str, device: str, cull: bool,
              antialiasing: str | None) -> None:
        import torch

        from brave6d.training import ANTIALIASING_MODES, apply_filter_3d, resolve_device

        if antialiasing is None:
            antialiasing = "mip" if splat.filter_3d is not None else "classic"
        if antialiasing not in ANTIALIASING_MODES:
            raise BraveError(f"{source}: antialiasing must be one of {', '.join(ANTIALIASING_MODES)}, "
                             f"got {antialiasing!r}")
        self.antialiasing = antialiasing
        dev = resolve_device(device)
        self.device = dev.type
        check_splat(splat, source)  # NaN/inf, no Gaussians, nothing visible: refused with the source's name
        scales_all, opac_all = apply_filter_3d(
            torch.from_numpy(np.exp(np.clip(splat.scales.astype(np.float64), -30, 30))),
            torch.from_numpy(activated_opacity(splat)),
            None if splat.filter_3d is None else torch.from_numpy(splat.filter_3d.astype(np.float64)))
        opac = opac_all.numpy()
        keep = opac >= MIN_ALPHA  # after the 3D filter: what the rasterizer would draw (still lossless)
        self.n_loaded = splat.num_gaussians
        self.n_pruned = int((~keep).sum())
        f32 = torch.float32
        quats = splat.quats[keep].astype(np.float64)
        norm = np.linalg.norm(quats, axis=1, keepdims=True)
        quats = np.where(norm > 1e-12, quats / np.maximum(norm, 1e-12), np.array([1.0, 0, 0, 0]))
        scales = scales_all.numpy()[keep]
        self.means = torch.as_tensor(splat.means[keep], dtype=f32, device=dev).contiguous()
        self.quats = torch.as_tensor(quats, dtype=f32, device=dev).contiguous()
        self.scales = torch.as_tensor(scales, dtype=f32, device=dev).contiguous()
        self.opacities = torch.as_tensor(opac[keep], dtype=f32, device=dev).contiguous()
        self.sh_degree = effective_sh_degree(splat.shN[keep])
        k = (self.sh_degree + 1) ** 2 - 1
        coeffs = np.concatenate([splat.sh0[keep], splat.shN[keep][:, :k]], axis=1)
        self.colors = torch.as_tensor(coeffs, dtype=f32, device=dev).contiguous()
        self.max_scale = self.scales.max(dim=1).values.contiguous()
        self.cull = cull
        self.lock = threading.Lock()
        self.renders = 0

    #: The lowest SH degree that represents a splat's ``shN`` exactly (what the renderer evaluates).
    effective_sh_degree = staticmethod(effective_sh_degree)

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def _cull(self, viewmat, K, width: int, height: int, near: float, far: float):  # type: ignore[no-untyped-def]
        """Indices of Gaussians that may touch the image (a superset; see the module docstring).

        The rasterizer's screen radius is at most ``3.33 * sqrt(lambda_max(J S J^T) + 0.3)`` px
        with ``S`` the 3D covariance (``lambda_max <= s_max^2``) and ``J`` the projection
        Jacobian, whose x/z, y/z terms are clamped to the image plus 30 % of the half field of
        view; ``||J||_2 <= ||J||_F = sqrt(fx^2 (1 + tx^2) + fy^2 (1 + ty^2)) / z`` with the
        clamp limits ``tx``, ``ty``. Gaussians whose centre plus that bound (plus one pixel)
        misses the image are dropped, as are centres outside ``(near, far)`` (the rasterizer
        culls those itself). ``K`` is OpenCV's (pixel centres at integers): the image spans
        ``[-0.5, width - 0.5]``, the clamp limits are measured from those edges.
        """
        import torch

        fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        tx = max(cx + 0.5, width - 0.5 - cx) / fx + 0.3 * (0.5 * width / fx)
        ty = max(cy + 0.5, height - 0.5 - cy) / fy + 0.3 * (0.5 * height / fy)
        jf = math.sqrt(fx * fx * (1.0 + tx * tx) + fy * fy * (1.0 + ty * ty))
        R = viewmat[:3, :3]
        t = viewmat[:3, 3]
        pc = self.means @ R.T + t
        z = pc[:, 2]
        front = (z > near) & (z < far)
        zc = torch.clamp(z, min=near)
        u = fx * pc[:, 0] / zc + cx
        v = fy * pc[:, 1] / zc + cy
        sig = jf * self.max_scale / zc
        rad = 3.33 * torch.sqrt(sig * sig + 0.3) + 1.0
        inside = (u + rad > -0.5) & (u - rad < width - 0.5) & (v + rad > -0.5) & (v - rad < height - 0.5)
        return torch.nonzero(front & inside, as_tuple=False).squeeze(1)

    def render(self, world_T_cam: NDArray[np.float64], camera: PinholeCamera, *, near: float = 0.01,
               far: float = 100.0, background: tuple[float, float, float] = (0.0, 0.0, 0.0),
               depth_alpha_min: float = 0.5, depth_mode: str = "median") -> RenderOutput:
        """Render the view of an undistorted pinhole ``camera`` at ``world_T_cam`` (OpenCV axes)."""
        return self.render_batch([world_T_cam], camera, near=near, far=far, background=background,
                                 depth_alpha_min=depth_alpha_min, depth_mode=depth_mode)[0]

    def render_batch(self, world_T_cams: Sequence[NDArray[np.float64]] | NDArray[np.float64],
                     camera: PinholeCamera, *, near: float = 0.01, far: float = 100.0,
                     background: tuple[float, float, float] = (0.0, 0.0, 0.0), depth_alpha_min: float = 0.5,
                     depth_mode: str = "median",
                     out: Sequence[tuple[NDArray[np.uint8], NDArray[np.float32]] | None] | None = None
                     ) -> list[RenderOutput]:
        """Render one view per pose in ``world_T_cams`` ([C, 4, 4] or a list), the cameras batched.
        ``out[k]``: ``(rgb (H, W, 3) uint8, depth (H, W) float32)`` arrays that view ``k``'s images are
        written into (its :class:`RenderOutput` holds those arrays): the vector env's observation batch,
        so that the images are not copied into it afterwards.

        Why: many agents on one scene. The rasterizer takes C cameras at once: on CUDA gsplat
        batches them (one call for all), on the CPU the Numba kernels run their ``prange`` loops over
        all cameras' Gaussians and tiles together. A call draws the union of its cameras' culled sets
        (lossless for each camera, see :meth:`_cull`), so each view equals :meth:`render` of its
        pose, bit for bit. The CPU kernels project every Gaussian of a call for every camera of it,
        so cameras that share few Gaussians (agents all around a scene) cost more together than apart:
        on the CPU cameras are grouped (:meth:`_groups`). ``render_ms`` and ``queue_ms`` are the whole
        batch's (shared by its views); ``gaussians_drawn`` is each camera's own culled count.
        """
        import torch

        poses = _check_poses(world_T_cams)
        if camera.has_distortion:
            raise BraveError("the renderer draws pinhole images: give an undistorted camera")
        if depth_mode not in DEPTH_MODES:
            raise BraveError(f"render: depth_mode must be one of {', '.join(DEPTH_MODES)}, got {depth_mode!r}")
        dev = self.means.device
        viewmats = torch.as_tensor(np.stack([invert(T) for T in poses]), dtype=torch.float32, device=dev)
        K = torch.as_tensor(camera.K, dtype=torch.float32, device=dev)
        bg = torch.as_tensor(background, dtype=torch.float32, device=dev).reshape(1, 3)
        images: list[tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.float32]] | None] = [None] * len(poses)
        t_wait = time.perf_counter()
        with self.lock:
            wanted = STILL_WANTED.get()
            if wanted is not None and not wanted():
                raise RenderWithdrawn()
            t0 = time.perf_counter()
            with torch.no_grad():
                culled = self._culled(viewmats, K, camera, near, far)
                for members in self._groups(culled, len(poses)):
                    c = len(members)
                    views = self._rasterize(self._gaussians(culled, members), viewmats[members].contiguous(),
                                            K.expand(c, 3, 3).contiguous(), camera, near, far,
                                            bg.expand(c, 3).contiguous(), depth_alpha_min, depth_mode)
                    for i, view in zip(members, views):
                        target = out[i] if out is not None else None
                        if target is not None:  # written into the caller's arrays
                            np.copyto(target[0], view[0])
                            np.copyto(target[1], view[1])
                            view = (target[0], target[1], view[2])
                        images[i] = view
            t1 = time.perf_counter()
            self.renders += len(poses)
        ms, queue = (t1 - t0) * 1000.0, (t0 - t_wait) * 1000.0
        drawn = [self.num_gaussians] * len(poses) if culled is None else [int(c.numel()) for c in culled]
        return [RenderOutput(*view, ms, queue, n) for view, n in zip(images, drawn) if view is not None]

    def _culled(self, viewmats, K, camera: PinholeCamera, near: float, far: float):  # type: ignore[no-untyped-def]
        """Each camera's culled Gaussian indices (at least one: an empty view keeps Gaussian 0 so
        that shapes stay valid; it cannot touch that view's image), or None without culling."""
        import torch

        if not self.cull:
            return None
        empty = torch.zeros(1, dtype=torch.long, device=self.means.device)
        culled = [self._cull(viewmat, K, camera.width, camera.height, near, far) for viewmat in viewmats]
        return [idx if idx.numel() > 0 else empty for idx in culled]

    def _groups(self, culled: list | None, n_views: int) -> list[list[int]]:  # type: ignore[type-arg]
        """The cameras' rasterizer calls, in camera order. A call never holds more than
        ``MAX_PAIRS_PER_CALL`` cameras x Gaussians of their union (memory). On CUDA that is the only
        limit; on the CPU a camera also joins the current call only while the call's work (cameras x
        their union) stays within ``CPU_BATCH_OVERLAP`` times the work of separate calls (the sum of
        the sets): agents looking at the same Gaussians share a call, agents far apart do not."""
        import torch

        if culled is None:
            per_call = max(1, MAX_PAIRS_PER_CALL // max(self.num_gaussians, 1))
            return [list(range(i, min(i + per_call, n_views))) for i in range(0, n_views, per_call)]
        on_cpu = self.means.device.type != "cuda"
        groups: list[list[int]] = []
        union = torch.zeros(self.num_gaussians, dtype=torch.bool, device=self.means.device)
        total = 0
        for i, idx in enumerate(culled):
            trial = union.clone()
            trial[idx] = True
            work = (len(groups[-1]) + 1 if groups else 1) * int(trial.sum())
            fits = work <= MAX_PAIRS_PER_CALL and (not on_cpu or work <= CPU_BATCH_OVERLAP * (total + idx.numel()))
            if groups and fits:
                groups[-1].append(i)
                union, total = trial, total + int(idx.numel())
            else:
                groups.append([i])
                union = torch.zeros_like(union)
                union[idx] = True
                total = int(idx.numel())
        return groups

    def _gaussians(self, culled: list | None, members: list[int]) -> tuple:  # type: ignore[type-arg]
        """The Gaussians of one rasterizer call: the union of its cameras' culled sets (all of them
        without culling)."""
        import torch

        if culled is None:
            return (self.means, self.quats, self.scales, self.opacities, self.colors)
        keep = torch.zeros(self.num_gaussians, dtype=torch.bool, device=self.means.device)
        for i in members:
            keep[culled[i]] = True
        union = torch.nonzero(keep, as_tuple=False).squeeze(1)
        return (self.means[union], self.quats[union], self.scales[union], self.opacities[union], self.colors[union])

    def _rasterize(self, args: tuple, viewmats, Ks, camera: PinholeCamera, near: float, far: float,  # type: ignore[no-untyped-def, type-arg]
                   bg, depth_alpha_min: float, depth_mode: str
                   ) -> list[tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.float32]]]:
        """One rasterizer call for all cameras -> per camera (rgb uint8, depth with the sensor's
        0 = no data, alpha), as host arrays."""
        import torch

        from brave6d.training import rasterize

        median = depth_mode == "median"
        colors, depth, alpha, info = rasterize(
            *args, viewmats, Ks, camera.width, camera.height,
            sh_degree=self.sh_degree, near_plane=near, far_plane=far, backgrounds=bg,
            backend="cuda" if self.means.device.type == "cuda" else "cpu", median_depth=median,
            antialiased=self.antialiasing == "mip")
        if median:
            depth = info["median_depth"]
        rgb = (colors.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        a = alpha[..., 0]
        d = torch.where(a >= depth_alpha_min, depth[..., 0], torch.zeros_like(a))
        d = torch.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0).float().cpu().numpy()
        a_np = a.float().cpu().numpy()
        return [(rgb[i], d[i], a_np[i]) for i in range(rgb.shape[0])]

    def warm_up(self, camera: PinholeCamera, world_T_cam: NDArray[np.float64]) -> float:
        """One render (loads the compiled kernels / CUDA context); returns its milliseconds."""
        small = camera.scaled(max(16, camera.width // 4), max(16, camera.height // 4))
        return self.render(world_T_cam, small).render_ms


def lookat_default(bundle_start: dict, fallback_target: NDArray[np.float64]) -> NDArray[np.float64]:
    """A sensible default view: from the capture's middle distance at 45 deg elevation towards the target."""
    from brave6d.core.transforms import look_at

    target = np.asarray(bundle_start.get("target", fallback_target), dtype=np.float64)
    dists = bundle_start.get("distances_m") or [0.3]
    d = float(np.median(dists))
    el = math.radians(45.0)
    eye = target + d * np.array([-math.cos(el), 0.0, math.sin(el)])
    return look_at(eye, target)

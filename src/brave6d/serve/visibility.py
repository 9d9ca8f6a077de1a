"""Visible fraction of each object instance in a served view (BOP-like ``visib_fract``).

Definition (as bop_toolkit's ``scene_gt_info``): ``visib_fract = px_count_visib / px_count_all``

* ``px_count_all``: pixels of the object's silhouette ALONE (no occluders), counted on a canvas
  three times the image size centred on it, so a truncated object keeps its full silhouette;
* ``px_count_visib``: image pixels where the object is the first surface seen.

Silhouettes, depths and mutual occlusion come from annotation's ray caster
(``brave6d.annotation.SilhouetteCaster``, the same geometry as the BOP export's masks). A pixel of
instance *i* counts as visible when

1. among all object instances, *i* is hit first (exact mutual occlusion of the meshes), and
2. the scene does not occlude it: the occluder depth is not nearer than the object's depth by
   more than ``occlusion_tolerance`` (default 15 mm, the delta bop_toolkit uses when it
   estimates visibility from a depth image). The occluder depth stands in for everything that
   is not an annotated object (table clutter, walls): the bundle's reference geometry ray cast
   at the view (:mod:`brave6d.serve.reference`, fixed for the scene, so a re-trained splat does
   not move the fractions), or, for an older bundle without one, the rendered splat depth (where
   the splat's alpha is at least the render's ``depth_alpha_min``). Where the occluder depth is
   the object itself it matches the mesh (within the tolerance), and silhouette edges blend
   towards the background (farther), so neither counts as occlusion.

**Stride** (``stride`` of :meth:`VisibilityComputer.compute` / ``compute_many``; the episodes'
``visibility_stride``): 1 casts every pixel (exact). ``s > 1`` casts one pixel per ``s x s`` block,
the lattice ``(s*i + s//2, s*j + s//2)`` (a camera with ``fx/s, fy/s``, its principal point moved
onto the lattice: :func:`lattice_camera`), and each sample stands for its block: the pixel counts
are the samples' times ``s**2`` (so ``visib_fract`` is the samples' ratio) and the boxes cover the
samples' blocks. The effective stride of a camera is the largest ``s`` up to the one asked for that
divides both its width and height (:func:`effective_stride`: no partial blocks; 1 for a prime
size). An instance whose whole silhouette has fewer than :data:`EXACT_BELOW_SAMPLES` samples (a
far object, one smaller than a block) is computed exactly instead, in that view, so a tiny visible
object is never reported unseen. A larger object whose visible part falls between the samples (a
sliver at the border, a corner behind another object) is reported unseen (measured in BENCHMARKS:
3 of 737 visible objects); nothing refuses or ends an episode on a visible fraction, and a submit
records the exact ones (:meth:`brave6d.serve.episodes.SceneServer.complete`). Deterministic: the same pose gives the same fractions,
one view at a time or in a batch. What it costs in accuracy and saves in time: docs/BENCHMARKS.md.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera


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


_NOT_SEEN = Visibility(0, 0, 0.0, None, None)

#: with a stride > 1, silhouettes of fewer lattice samples than this are computed exactly (per view and
#: instance): chosen by measurement (docs/BENCHMARKS.md; 16 halves the reward's error for small objects at
#: a third more time per scored step on the synthetic scene's 2 cm cubes)
EXACT_BELOW_SAMPLES = 4


def effective_stride(camera: PinholeCamera, stride: int) -> int:
    """The largest ``s <= stride`` dividing both the camera's width and height (1: every pixel)."""
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"visibility stride must be an integer >= 1, got {stride!r}")
    for s in range(int(stride), 1, -1):
        if camera.width % s == 0 and camera.height % s == 0:
            return s
    return 1


def lattice_camera(camera: PinholeCamera, s: int) -> PinholeCamera:
    """The camera whose pixel ``(i, j)`` looks along ``camera``'s pixel ``(s*i + s//2, s*j + s//2)``
    (``s`` dividing its width and height): the stride's sample lattice."""
    o = s // 2
    return PinholeCamera(camera.width // s, camera.height // s, camera.fx / s, camera.fy / s,
                         (camera.cx - o) / s, (camera.cy - o) / s)


def _block_box(box: tuple[int, int, int, int] | None, s: int) -> tuple[int, int, int, int] | None:
    """A lattice box ``[x, y, w, h]`` as the full-resolution box of its samples' blocks."""
    if box is None:
        return None
    x, y, w, h = box
    return (x * s, y * s, w * s + s - 1, h * s + s - 1)


class VisibilityComputer:
    """Per-view visibility of object instances (see the module docstring); thread-safe.

    ``models``: ``(vertices, faces)`` in metres in the model frame, one per instance, in the
    same order as ``world_T_objs``. Raises ImportError when Open3D is not installed.
    """

    def __init__(self, models: Sequence[tuple[NDArray[np.float64], NDArray[np.int64]]],
                 world_T_objs: Sequence[NDArray[np.float64]], occlusion_tolerance: float = 0.015) -> None:
        import open3d  # noqa: F401 - checked here: without it the server serves with visibility off

        from brave6d.annotation import SilhouetteCaster, bbox_xywh

        self._bbox = bbox_xywh
        self.tol = float(occlusion_tolerance)
        self._caster = SilhouetteCaster(dict(enumerate(models)), list(enumerate(world_T_objs)))
        self._instances = len(models)

    def compute(self, world_T_cam: NDArray[np.float64], camera: PinholeCamera,
                splat_depth: NDArray[np.float32] | None = None,
                occluder_depth: Callable[[NDArray[np.float32]], NDArray[np.float32]] | None = None,
                stride: int = 1) -> list[Visibility]:
        """Visibility of every instance, in instance order. Occluders (see the module docstring):
        ``occluder_depth`` (camera-frame rays (N, 3) -> z-depth (N,), the reference geometry's) when
        given, else ``splat_depth`` (H, W) metres; 0 = no data. ``stride``: the module docstring's
        (> 1: :meth:`compute_many` of this one view, equal to it bit for bit)."""
        if effective_stride(camera, stride) > 1:
            many = None if occluder_depth is None else _one_view_occluders(occluder_depth)
            return self.compute_many(np.asarray(world_T_cam, dtype=np.float64)[None], camera,
                                     None if splat_depth is None else [splat_depth], many, stride=stride)[0]
        T = np.asarray(world_T_cam, dtype=np.float64)
        out = []
        for n, sil in enumerate(self._caster.silhouettes(T, camera)):
            if sil.px_count_all == 0:
                out.append(_NOT_SEEN)
                continue
            seen = sil.within(camera.width, camera.height)
            vis = np.zeros(0, dtype=bool)
            if seen.px_count_all:
                vis = self._caster.first_instance(T, seen.rays) == n
                sd = (occluder_depth(seen.rays) if occluder_depth is not None
                      else splat_depth[seen.ys, seen.xs] if splat_depth is not None else None)
                if sd is not None:
                    vis &= ~((sd > 0) & (sd < seen.depth - self.tol))
            px_vis = int(vis.sum())
            out.append(Visibility(sil.px_count_all, px_vis, px_vis / sil.px_count_all,
                                  sil.bbox_all if px_vis else None, self._bbox(seen.xs[vis], seen.ys[vis])))
        return out

    def compute_many(self, world_T_cams: NDArray[np.float64], camera: PinholeCamera,
                     splat_depths: Sequence[NDArray[np.float32]] | None = None,
                     occluder_depths: ManyOccluders | None = None,
                     instances: Sequence[int] | None = None, stride: int = 1) -> list[list[Visibility]]:
        """:meth:`compute` of many views at once (many agents on one scene): one ray cast per
        instance for all silhouettes, one for all first hits, one for the occluder depths
        (:data:`ManyOccluders`, the reference geometry's ``depth_along_many``) of the pixels where the
        instance is hit first (elsewhere it is not visible whatever the occluders) instead of one per
        view and instance. ``result[c]`` equals ``compute(world_T_cams[c], camera, splat_depths[c], its
        occluders)`` bit for bit; with ``instances``, its entries of those instance indices, in that
        order (the others are not cast at all; every instance still occludes them). ``stride``: the
        module docstring's; each view's result depends on that view alone, as with stride 1."""
        poses = np.asarray(world_T_cams, dtype=np.float64).reshape(-1, 4, 4)
        s = effective_stride(camera, stride)
        if s == 1:
            return self._exact_many(poses, camera, splat_depths, occluder_depths, instances)
        o = s // 2
        out = self._exact_many(poses, lattice_camera(camera, s),
                               None if splat_depths is None else [d[o::s, o::s] for d in splat_depths],
                               occluder_depths, instances, s)  # at full resolution
        wanted = list(range(self._instances)) if instances is None else [int(n) for n in instances]
        small_below = EXACT_BELOW_SAMPLES * s * s  # scaled counts: fewer samples than EXACT_BELOW_SAMPLES
        for j, n in enumerate(wanted):  # small silhouettes: exact, in the views where they are small
            small = [c for c in range(len(poses)) if out[c][j].px_count_all < small_below]
            if small:
                exact = self._exact_many(poses[small], camera,
                                         None if splat_depths is None else [splat_depths[c] for c in small],
                                         occluder_depths, [n])
                for c, views in zip(small, exact):
                    out[c][j] = views[0]
        return out

    def _exact_many(self, poses: NDArray[np.float64], camera: PinholeCamera,
                    splat_depths: Sequence[NDArray[np.float32]] | None, occluder_depths: ManyOccluders | None,
                    instances: Sequence[int] | None, scale: int = 1) -> list[list[Visibility]]:
        """:meth:`compute_many` at every pixel of ``camera`` (stride 1); ``scale`` > 1: ``camera`` is the
        lattice of that stride and each result is at full resolution, built once: counts times ``scale**2``,
        the fraction the lattice's, boxes of the samples' blocks (:func:`_block_box`)."""
        n_views = len(poses)
        wanted = list(range(self._instances)) if instances is None else [int(n) for n in instances]
        if not wanted:
            return [[] for _ in range(n_views)]
        per_instance = []
        for sil in self._caster.silhouettes_many(poses, camera, wanted):
            seen = sil.within(camera.width, camera.height)
            per_instance.append((sil, seen, np.searchsorted(seen.owner, np.arange(n_views + 1))))
        first = self._caster.first_instance_many(poses, np.concatenate([seen.owner for _, seen, _ in per_instance]),
                                                 np.concatenate([seen.ray_x for _, seen, _ in per_instance]),
                                                 np.concatenate([seen.ray_y for _, seen, _ in per_instance]))
        owner_of = np.concatenate([np.full(len(seen.owner), n) for n, (_, seen, _) in zip(wanted, per_instance)])
        first_is_own = first == owner_of  # where another instance is in front, no occluder can matter
        occluders: list[NDArray[np.float32] | None] = [None] * len(per_instance)
        if occluder_depths is not None:  # one call, one ray set per view: its instances' rays (compute's), in order
            owners = np.concatenate([seen.owner for _, seen, _ in per_instance])
            rays = np.empty((len(owners), 3), dtype=np.float32)
            rays[:, 0], rays[:, 1], rays[:, 2] = np.concatenate([seen.ray_x for _, seen, _ in per_instance]), \
                np.concatenate([seen.ray_y for _, seen, _ in per_instance]), 1.0
            order = np.argsort(owners, kind="stable") if len(per_instance) > 1 else None  # view by view
            needed = first_is_own if order is None else first_is_own[order]
            if order is not None:
                rays, owners = rays[order], owners[order]
            at = np.searchsorted(owners, np.arange(n_views + 1)).tolist()
            by_view = occluder_depths(list(poses), [rays[at[c]:at[c + 1]] for c in range(n_views)], needed)
            depths = by_view
            if order is not None:  # back to instance by instance
                depths = np.empty_like(by_view)
                depths[order] = by_view
            offset = 0
            for n, (_, seen, _) in enumerate(per_instance):
                occluders[n] = depths[offset:offset + len(seen.owner)]
                offset += len(seen.owner)
        elif splat_depths is not None:
            for n, (_, seen, bounds) in enumerate(per_instance):
                sd = np.zeros(len(seen.owner), np.float32)
                for c in range(n_views):
                    lo, hi = bounds[c], bounds[c + 1]
                    sd[lo:hi] = splat_depths[c][seen.ys[lo:hi], seen.xs[lo:hi]]
                occluders[n] = sd
        out: list[list[Visibility]] = [[] for _ in range(n_views)]
        offset = 0
        for n, (sil, seen, bounds) in enumerate(per_instance):
            vis = first_is_own[offset:offset + len(seen.owner)]
            offset += len(seen.owner)
            sd = occluders[n]
            if sd is not None:
                vis &= ~((sd > 0) & (sd < seen.depth - self.tol))
            all_counts = sil.px_count_all
            vis_counts = np.bincount(seen.owner[vis], minlength=n_views)
            box_all = _bboxes(sil.owner, sil.xs, sil.ys, n_views, scale)
            box_vis = _bboxes(seen.owner[vis], seen.xs[vis], seen.ys[vis], n_views, scale)
            area = scale * scale
            for c, (px_all, px_vis) in enumerate(zip(all_counts.tolist(), vis_counts.tolist())):
                out[c].append(_NOT_SEEN if px_all == 0 else
                              Visibility(px_all * area, px_vis * area, px_vis / px_all, box_all[c] if px_vis else None,
                                         box_vis[c]))
        return out


#: Occluder depths of many views: ``(poses, camera-frame rays per view, needed rays or None) -> the z-depths of
#: all views' rays, concatenated`` (0 where not needed).
ManyOccluders = Callable[[Sequence[NDArray[np.float64]], Sequence[NDArray[np.float32]], NDArray[np.bool_] | None],
                         NDArray[np.float32]]


def _one_view_occluders(occluder_depth: Callable[[NDArray[np.float32]], NDArray[np.float32]]) -> ManyOccluders:
    """One view's occluder depth (rays -> z-depths) as :data:`ManyOccluders` (its poses are that view's)."""
    def many(poses: Sequence[NDArray[np.float64]], rays: Sequence[NDArray[np.float32]],
             needed: NDArray[np.bool_] | None) -> NDArray[np.float32]:
        if not len(rays):
            return np.zeros(0, dtype=np.float32)
        all_rays = np.concatenate([np.asarray(r, dtype=np.float32).reshape(-1, 3) for r in rays])
        if needed is None:
            return occluder_depth(all_rays)
        out = np.zeros(len(all_rays), dtype=np.float32)
        out[needed] = occluder_depth(all_rays[needed])
        return out
    return many


def _bboxes(owner: NDArray[np.int64], xs: NDArray[np.int64], ys: NDArray[np.int64], n: int, scale: int = 1
            ) -> list[tuple[int, int, int, int] | None]:
    """Per view ``c < n``, ``bbox_xywh`` of the pixels whose ``owner`` is ``c`` (grouped by owner, in order);
    ``scale`` > 1: lattice pixels, the box of their blocks (:func:`_block_box`)."""
    out: list[tuple[int, int, int, int] | None] = [None] * n
    if not len(owner):
        return out
    starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    x0, x1 = np.minimum.reduceat(xs, starts).tolist(), np.maximum.reduceat(xs, starts).tolist()
    y0, y1 = np.minimum.reduceat(ys, starts).tolist(), np.maximum.reduceat(ys, starts).tolist()
    for k, c in enumerate(owner[starts].tolist()):
        out[c] = (x0[k], y0[k], x1[k] - x0[k], y1[k] - y0[k]) if scale == 1 else _block_box(
            (x0[k], y0[k], x1[k] - x0[k], y1[k] - y0[k]), scale)
    return out

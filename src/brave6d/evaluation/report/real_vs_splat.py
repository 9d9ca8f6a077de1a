"""Captured frames and the splat's renders of exactly their camera poses, for the sections that
compare an estimator on both (realism: the static estimator; learned: the learned estimator).

:class:`CapturedViews` reads the annotation stage's BOP export of the scene (undistorted RGB and
depth, ``scene_camera`` poses, ``scene_gt`` / ``scene_gt_info``), picks per distance level the
held-out views (never trained on) and a few training views, evenly spaced in capture order, and
renders each chosen view from the served bundle's splat (:class:`brave6d.serve.SplatRenderer`) at
the captured size with the same ``K`` and pose, its depth stored as the capture's is (uint16 mm),
so both sides reach an estimator in one form.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.layout import SceneDir
from brave6d.evaluation.report.common import evenly_spaced
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore, file_stamp


def choose_views(levels: Mapping[int, int], holdout: set[int], exported: set[int], holdout_per_level: int,
                 train_per_level: int) -> list[tuple[int, bool]]:
    """``(im_id, held_out)`` per distance level: up to ``holdout_per_level`` held-out views and
    ``train_per_level`` training views among the exported images, evenly spaced by image id."""
    chosen: list[tuple[int, bool]] = []
    for level in sorted(set(levels.values())):
        ids = sorted(i for i, lv in levels.items() if lv == level and i in exported)
        chosen += [(i, True) for i in evenly_spaced([i for i in ids if i in holdout], holdout_per_level)]
        chosen += [(i, False) for i in evenly_spaced([i for i in ids if i not in holdout], train_per_level)]
    return chosen


def depth_png_to_m(depth_png: NDArray[np.uint16], depth_scale: float) -> NDArray[np.float32]:
    """A BOP depth image (``depth_scale`` mm per unit, 0 = no data) in metres, one formula for both sides."""
    return (np.asarray(depth_png, dtype=np.float32) * np.float32(depth_scale)) / np.float32(1000.0)


def decimated(K: NDArray[np.float64], stride: int) -> NDArray[np.float64]:
    """``K`` of the image made of every ``stride``-th pixel (pixel centres at integers, OpenCV)."""
    out = np.array(K, dtype=np.float64)
    out[:2] /= float(stride)
    return out


def images_stamp(paths: Sequence[Path]) -> str:
    """One fingerprint of many image files (name, size, modification time; absent files count too)."""
    import hashlib

    h = hashlib.sha256()
    for p in paths:
        st = p.stat() if p.is_file() else None
        h.update(f"{p.name}:{st.st_size if st else -1}:{st.st_mtime_ns if st else -1};".encode())
    return h.hexdigest()


def raw_data_pixels(scene: Any, size: tuple[int, int]) -> NDArray[np.bool_] | None:
    """Pixels of the undistorted image that the raw (distorted) image covers, at the capture's
    size ``(width, height)``; None without distortion or when the sizes differ (every pixel counts)."""
    from brave6d.core.calibration_io import read_intrinsics

    raw = read_intrinsics(scene)
    if not raw.has_distortion or (raw.width, raw.height) != tuple(size):
        return None
    inside = raw.undistort_image(np.full((raw.height, raw.width), 255, np.uint8))
    return np.asarray(inside) >= 255


def required_inputs(scene: SceneDir) -> list[tuple[Path, str]]:
    """The files the comparison reads, with the stage that writes each (for ``MeasurementStore.require``)."""
    from brave6d.annotation import BopLayout
    from brave6d.serve import MANIFEST

    return [(scene.bundle_dir / MANIFEST, "serve export (brave6d export)"),
            (BopLayout(scene.bop_dir).info_path, "annotation (BOP export)"),
            (scene.frames_path, "capture"), (scene.intrinsics_path, "calibration")]


@dataclass(frozen=True)
class ViewPair:
    """One captured view and the splat's render of its pose, both decimated by the stride: RGB,
    depth (metres, 0 = none; None when the capture has no depth image), ``K`` of the decimated
    images, the camera pose and the render's time."""

    im_id: int
    rgb_real: NDArray[np.uint8]
    depth_real: NDArray[np.float32] | None
    rgb_splat: NDArray[np.uint8]
    depth_splat: NDArray[np.float32]
    K: NDArray[np.float64]
    world_T_cam: NDArray[np.float64]
    render_s: float


class CapturedViews:
    """The scene's exported views and the bundle's splat (see the module docstring); the renderer
    is made on the first :meth:`pair`, so a cached measurement costs no GPU or model load."""

    def __init__(self, scene: SceneDir, holdout_per_level: int, train_per_level: int, stride: int,
                 device: str) -> None:
        from brave6d.annotation import BopLayout, read_scene_camera, read_scene_gt, read_scene_gt_info
        from brave6d.core.atomic import read_png
        from brave6d.serve import MANIFEST, load_bundle

        if stride < 1:
            raise ValueError(f"real vs splat: stride must be a positive integer, got {stride}")
        self.scene, self.stride, self.device = scene, stride, device
        self.layout = layout = BopLayout.of_scene(scene)
        self.manifest = scene.bundle_dir / MANIFEST
        self.bundle = load_bundle(scene.bundle_dir)
        self.cams = read_scene_camera(layout.scene_camera_path)
        self.gts = read_scene_gt(layout.scene_gt_path)
        self.infos = read_scene_gt_info(layout.scene_gt_info_path)
        self.records = {r.index: r for r in scene.frames()}
        self.levels = {i: self.records[i].distance_level for i in self.gts if i in self.records}
        self.views = choose_views(self.levels, {h.index for h in self.bundle.holdout}, set(self.cams) & set(self.infos),
                                  holdout_per_level, train_per_level)
        self.names = {o.obj_id: o.name for o in self.bundle.objects}
        self.size: tuple[int, int] = (0, 0)
        if self.views:
            self.size = read_png(layout.rgb_path(self.views[0][0]), "rgb").shape[1::-1]
        self._renderer: Any = None
        self._valid: Any = False

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` of the decimated images the estimators see."""
        return (math.ceil(self.size[0] / self.stride), math.ceil(self.size[1] / self.stride))

    def key(self) -> dict[str, Any]:
        """What the views depend on (the bundle, the export, the capture, the chosen images, the device)."""
        layout = self.layout
        return {"bundle": file_stamp(self.manifest), "scene_gt": file_stamp(layout.scene_gt_path),
                "scene_camera": file_stamp(layout.scene_camera_path),
                "scene_gt_info": file_stamp(layout.scene_gt_info_path),
                "frames": file_stamp(self.scene.frames_path), "intrinsics": file_stamp(self.scene.intrinsics_path),
                "images": images_stamp([p for i, _ in self.views for p in (layout.rgb_path(i), layout.depth_path(i))]),
                "device": self.device}

    def describe(self, m: Measurement) -> None:
        """Record where the views come from in ``m``'s summary."""
        m.summary.update({"bop": str(self.layout.scene_dir), "bundle": str(self.scene.bundle_dir),
                          "objects": {str(k): v for k, v in self.names.items()},
                          "levels": {str(lv): self.records[i].distance_m for i, lv in self.levels.items()}})

    def valid_pixels(self) -> NDArray[np.bool_] | None:
        """:func:`raw_data_pixels` of the decimated images (computed once)."""
        if self._valid is False:
            self._valid = raw_data_pixels(self.scene, self.size)
        return None if self._valid is None else self._valid[::self.stride, ::self.stride]

    def point(self, im_id: int, held_out: bool) -> dict[str, Any]:
        """The fields every measured view records."""
        return {"im_id": im_id, "level": self.levels[im_id], "distance_m": self.records[im_id].distance_m,
                "holdout": held_out}

    def measured_pair(self, im_id: int, held_out: bool) -> tuple[dict[str, Any], ViewPair | None]:
        """The view's point fields and its :class:`ViewPair`; without a captured depth image the
        point names the missing file (and has no objects) and the pair is None."""
        point = self.point(im_id, held_out)
        if not self.layout.depth_path(im_id).is_file():
            return {**point, "note": f"no depth image {self.layout.depth_path(im_id)}", "objects": []}, None
        return point, self.pair(im_id)

    def _camera(self, K: NDArray[np.float64]) -> Any:
        from brave6d.core.camera import PinholeCamera

        return PinholeCamera(self.size[0], self.size[1], K[0, 0], K[1, 1], K[0, 2], K[1, 2])

    def renderer(self) -> Any:
        """The bundle's splat renderer, warmed up on the first view (kernels compile outside a point's time)."""
        if self._renderer is None:
            from brave6d.core.transforms import invert
            from brave6d.serve import SplatRenderer

            self._renderer = SplatRenderer(self.bundle.splat_path, self.device,
                                           antialiasing=self.bundle.render.antialiasing)
            if self.views:
                c = self.cams[self.views[0][0]]
                self._renderer.warm_up(self._camera(c.cam_K), invert(c.cam_T_world()))
        return self._renderer

    def pair(self, im_id: int) -> ViewPair:
        """View ``im_id`` as captured and as the splat renders it (see :class:`ViewPair`)."""
        from brave6d.core.atomic import depth_m_to_mm_u16, read_png
        from brave6d.core.transforms import invert

        layout, step, cam = self.layout, self.stride, self.cams[im_id]
        world_T_cam = invert(cam.cam_T_world())
        rgb_real = read_png(layout.rgb_path(im_id), "rgb")[::step, ::step]
        depth_real = None
        if layout.depth_path(im_id).is_file():
            depth_real = depth_png_to_m(read_png(layout.depth_path(im_id), "depth")[::step, ::step], cam.depth_scale)
        render = self.bundle.render  # rendered at the captured size, then decimated as the captured frame is
        out = self.renderer().render(world_T_cam, self._camera(cam.cam_K), near=render.near, far=render.far,
                                     background=render.background, depth_alpha_min=render.depth_alpha_min,
                                     depth_mode=render.depth_mode)
        depth_splat = depth_png_to_m(depth_m_to_mm_u16(out.depth)[::step, ::step], 1.0)
        return ViewPair(im_id, rgb_real, depth_real, out.rgb[::step, ::step], depth_splat,
                        decimated(cam.cam_K, step), world_T_cam, out.render_ms / 1000.0)


def open_views(store: MeasurementStore, name: str, scene: SceneDir, holdout_per_level: int, train_per_level: int,
               stride: int, device: str) -> CapturedViews | Measurement:
    """:class:`CapturedViews` of ``scene``, or the measurement that names the missing input."""
    if (absent := store.require(name, required_inputs(scene))) is not None:
        return absent
    return CapturedViews(scene, holdout_per_level, train_per_level, stride, device)

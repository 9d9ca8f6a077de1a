"""The BOP dataset layout and typed readers of its JSON files (thodan/bop_toolkit conventions).

A scene exports to ``<scene>/annotation/bop/`` as one BOP dataset with one scene::

    camera.json                                   cx, cy, fx, fy, width, height, depth_scale
    models/obj_{obj_id:06d}.ply, models_info.json models in millimetres
    {split}/{scene_id:06d}/scene_camera.json      per image: cam_K, depth_scale, cam_R_w2c, cam_t_w2c (mm)
                          scene_gt.json           per image: [{cam_R_m2c, cam_t_m2c (mm), obj_id}]
                          scene_gt_info.json      per image: [{bbox_obj, bbox_visib, px_count_*, visib_fract}]
                          rgb/{im_id:06d}.png, depth/{im_id:06d}.png   undistorted frames
                          mask/, mask_visib/{im_id:06d}_{gt_id:06d}.png
    brave6d_export.json                           split, scene_id, image ids, source (not a BOP file)

Image ids are the capture's frame indices; ``gt_id`` is the instance's position in the
annotation (the same in every image). Readers return metres-free BOP units (mm) unchanged
except :meth:`GtPose.cam_T_model`, which gives metres, and ``cam_K``, which the files hold in
BOP's pixel convention and the readers return in the project's (:func:`bop_cam_K`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.atomic import read_json
from brave6d.camera import corner_origin_K, opencv_K
from brave6d.errors import DataError
from brave6d.layout import SceneDir
from brave6d.transforms import make_transform

EXPORT_INFO = "brave6d_export.json"


@dataclass(frozen=True)
class BopLayout:
    """Paths of a one-scene BOP dataset rooted at ``root``."""

    root: Path
    split: str = "test"
    scene_id: int = 1

    @classmethod
    def of_scene(cls, scene: SceneDir) -> BopLayout:
        """The layout of a scene's export (split and scene id from ``brave6d_export.json``)."""
        root = scene.bop_dir
        info_path = root / EXPORT_INFO
        if not info_path.exists():
            raise DataError(f"{info_path}: no BOP export; run 'brave6d annotate export-bop {scene.root}' first")
        info = read_json(info_path)
        try:
            return cls(root, str(info["split"]), int(info["scene_id"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{info_path}: malformed ({exc})") from None

    def moved_to(self, root: Path) -> BopLayout:
        return BopLayout(Path(root), self.split, self.scene_id)

    @property
    def camera_path(self) -> Path:
        return self.root / "camera.json"

    @property
    def info_path(self) -> Path:
        return self.root / EXPORT_INFO

    @property
    def models_dir(self) -> Path:
        return self.root / "models"

    @property
    def models_info_path(self) -> Path:
        return self.models_dir / "models_info.json"

    def model_path(self, obj_id: int) -> Path:
        return self.models_dir / f"obj_{obj_id:06d}.ply"

    @property
    def scene_dir(self) -> Path:
        return self.root / self.split / f"{self.scene_id:06d}"

    @property
    def scene_camera_path(self) -> Path:
        return self.scene_dir / "scene_camera.json"

    @property
    def scene_gt_path(self) -> Path:
        return self.scene_dir / "scene_gt.json"

    @property
    def scene_gt_info_path(self) -> Path:
        return self.scene_dir / "scene_gt_info.json"

    def rgb_path(self, im_id: int) -> Path:
        return self.scene_dir / "rgb" / f"{im_id:06d}.png"

    def depth_path(self, im_id: int) -> Path:
        return self.scene_dir / "depth" / f"{im_id:06d}.png"

    def mask_path(self, im_id: int, gt_id: int) -> Path:
        return self.scene_dir / "mask" / f"{im_id:06d}_{gt_id:06d}.png"

    def mask_visib_path(self, im_id: int, gt_id: int) -> Path:
        return self.scene_dir / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png"


# ----------------------------------------------------------------------------- records
@dataclass(frozen=True)
class GtPose:
    """One ``scene_gt.json`` entry: model-to-camera rotation and translation (mm)."""

    obj_id: int
    cam_R_m2c: NDArray[np.float64]
    cam_t_m2c: NDArray[np.float64]

    def cam_T_model(self) -> NDArray[np.float64]:
        """``cam_T_model`` in metres (the project's convention)."""
        return make_transform(self.cam_R_m2c, self.cam_t_m2c / 1000.0)


@dataclass(frozen=True)
class GtInfo:
    """One ``scene_gt_info.json`` entry (bboxes ``[x, y, w, h]`` with ``w = x_max - x_min``, BOP style)."""

    bbox_obj: tuple[int, int, int, int]
    bbox_visib: tuple[int, int, int, int]
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float


def bop_cam_K(K: ArrayLike) -> NDArray[np.float64]:
    """The project's (OpenCV) ``K`` as BOP's ``cam_K``: the principal point + 0.5 px.

    BOP's ground truth is made and scored with bop_toolkit's renderers, which put pixel
    ``(u, v)``'s centre at ``(u + 0.5, v + 0.5)`` in ``cam_K``'s coordinates: ``renderer_vispy``'s
    ``_calc_calib_proj`` (and bop_renderer's ``GPUBuffer::calculateProjectionMatrix``) map
    ``fx X / Z + cx`` straight to OpenGL window coordinates, where fragments are sampled at
    half-integers (the vispy image is read back flipped, rows top-down). So the masks,
    ``visib_fract`` and VSD renders bop_toolkit computes from our files line up with our images
    only with this shift; :func:`read_scene_camera` (and ``evaluation.metrics.bop_results``) undo it.
    """
    return corner_origin_K(K)


@dataclass(frozen=True)
class SceneCamera:
    """One ``scene_camera.json`` entry; ``cam_T_world`` in metres when the pose is present.

    ``cam_K`` is in the project's OpenCV convention (the file's ``cam_K`` less 0.5 px on the
    principal point, see :func:`bop_cam_K`).
    """

    cam_K: NDArray[np.float64]
    depth_scale: float
    cam_R_w2c: NDArray[np.float64] | None = None
    cam_t_w2c: NDArray[np.float64] | None = None

    def cam_T_world(self) -> NDArray[np.float64] | None:
        if self.cam_R_w2c is None or self.cam_t_w2c is None:
            return None
        return make_transform(self.cam_R_w2c, self.cam_t_w2c / 1000.0)


# ----------------------------------------------------------------------------- JSON
def dump_bop_json(data: dict[Any, Any]) -> str:
    """BOP-style JSON: one line per top-level key (image id), keys in numeric order."""
    keys = sorted(data, key=lambda k: (int(k) if str(k).isdigit() else 1 << 60, str(k)))
    body = ",\n".join(f"  {json.dumps(str(k))}: {json.dumps(data[k], allow_nan=False)}" for k in keys)
    return "{\n" + body + "\n}\n" if keys else "{}\n"


def _per_image(path: Path) -> dict[int, Any]:
    data = read_json(path)
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object keyed by image id")
    try:
        return {int(k): v for k, v in data.items()}
    except ValueError as exc:
        raise DataError(f"{path}: keys must be integer image ids ({exc})") from None


def read_scene_gt(path: Path | str) -> dict[int, list[GtPose]]:
    p = Path(path)
    out: dict[int, list[GtPose]] = {}
    for im_id, items in _per_image(p).items():
        try:
            out[im_id] = [GtPose(int(g["obj_id"]), np.asarray(g["cam_R_m2c"], dtype=np.float64).reshape(3, 3),
                                 np.asarray(g["cam_t_m2c"], dtype=np.float64).reshape(3)) for g in items]
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{p}: image {im_id}: malformed entry ({exc})") from None
    return out


def read_scene_gt_info(path: Path | str) -> dict[int, list[GtInfo]]:
    p = Path(path)
    out: dict[int, list[GtInfo]] = {}
    for im_id, items in _per_image(p).items():
        try:
            out[im_id] = [GtInfo(_bbox(g["bbox_obj"]), _bbox(g["bbox_visib"]), int(g["px_count_all"]),
                                 int(g["px_count_valid"]), int(g["px_count_visib"]), float(g["visib_fract"]))
                          for g in items]
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{p}: image {im_id}: malformed entry ({exc})") from None
    return out


def _bbox(values: Any) -> tuple[int, int, int, int]:
    x, y, w, h = (int(v) for v in values)
    return (x, y, w, h)


def read_scene_camera(path: Path | str) -> dict[int, SceneCamera]:
    p = Path(path)
    out: dict[int, SceneCamera] = {}
    for im_id, c in _per_image(p).items():
        try:
            R = c.get("cam_R_w2c")
            t = c.get("cam_t_w2c")
            out[im_id] = SceneCamera(opencv_K(np.asarray(c["cam_K"], dtype=np.float64)), float(c["depth_scale"]),
                                     None if R is None else np.asarray(R, dtype=np.float64).reshape(3, 3),
                                     None if t is None else np.asarray(t, dtype=np.float64).reshape(3))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise DataError(f"{p}: image {im_id}: malformed entry ({exc})") from None
    return out


def read_models_info(path: Path | str) -> dict[int, dict[str, Any]]:
    return _per_image(Path(path))

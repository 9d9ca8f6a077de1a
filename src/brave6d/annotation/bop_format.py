"""The BOP dataset format, owned here for the whole project: the layout and the typed, validated
readers of its JSON files (thodan/bop_toolkit conventions). The export writes these files and
evaluation and serve read them only through :mod:`annotation`'s public API.

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

from brave6d.core.atomic import read_json
from brave6d.core.camera import corner_origin_K, opencv_K
from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import make_transform

EXPORT_INFO = "brave6d_export.json"


#: BOP19 targets are the GT instances with at least this visible fraction (``test_targets_bop19.json``).
BOP19_MIN_VISIB_FRACT = 0.1


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
        return model_file(self.models_dir, obj_id)

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
    """One ``scene_gt_info.json`` entry (bboxes ``[x, y, w, h]`` with ``w = x_max - x_min``, BOP style).

    Only ``visib_fract`` is required (scoring needs nothing else); the export writes every field.
    """

    visib_fract: float
    bbox_obj: tuple[int, int, int, int] | None = None
    bbox_visib: tuple[int, int, int, int] | None = None
    px_count_all: int | None = None
    px_count_valid: int | None = None
    px_count_visib: int | None = None


def bop_cam_K(K: ArrayLike) -> NDArray[np.float64]:
    """The project's (OpenCV) ``K`` as BOP's ``cam_K``: the principal point + 0.5 px.

    BOP's ground truth is made and scored with bop_toolkit's renderers, which put pixel
    ``(u, v)``'s centre at ``(u + 0.5, v + 0.5)`` in ``cam_K``'s coordinates: ``renderer_vispy``'s
    ``_calc_calib_proj`` (and bop_renderer's ``GPUBuffer::calculateProjectionMatrix``) map
    ``fx X / Z + cx`` straight to OpenGL window coordinates, where fragments are sampled at
    half-integers (the vispy image is read back flipped, rows top-down). So the masks,
    ``visib_fract`` and VSD renders bop_toolkit computes from our files line up with our images
    only with this shift; :func:`read_scene_camera` undoes it.
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


def _int_keys(data: Any, path: Path, what: str = "id") -> dict[int, Any]:
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object keyed by {what}, got {type(data).__name__}")
    out: dict[int, Any] = {}
    for k, v in data.items():
        try:
            out[int(k)] = v
        except (TypeError, ValueError):
            raise DataError(f"{path}: key {k!r} is not an integer {what}") from None
    return out


def _floats(value: Any, count: int, where: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise DataError(f"{where}: expected {count} numbers, got {value!r}") from None
    if arr.size != count or not np.all(np.isfinite(arr)):
        raise DataError(f"{where}: expected {count} finite numbers, got {value!r}")
    return arr


def read_scene_camera(path: Path | str, require_depth_scale: bool = False) -> dict[int, SceneCamera]:
    """``scene_camera.json`` -> ``{im_id: SceneCamera}`` (``cam_K`` in the project's convention,
    ``depth_scale`` 1 when absent unless ``require_depth_scale`` (a split with depth images: never
    guess their unit), the world pose when both ``cam_R_w2c`` and ``cam_t_w2c`` are given)."""
    p = Path(path)
    out: dict[int, SceneCamera] = {}
    for im_id, entry in _int_keys(read_json(p), p, "image id").items():
        where = f"{p}: image {im_id}"
        if not isinstance(entry, dict) or "cam_K" not in entry:
            raise DataError(f"{where}: missing 'cam_K'")
        K = opencv_K(_floats(entry["cam_K"], 9, f"{where} cam_K"))
        if require_depth_scale and "depth_scale" not in entry:
            raise DataError(f"{where}: missing 'depth_scale' (mm per unit of the depth PNGs: 1 = mm, "
                            "0.1 as BlenderProc writes)")
        given = entry.get("depth_scale", 1.0)
        if isinstance(given, bool) or not isinstance(given, (int, float)):
            raise DataError(f"{where}: 'depth_scale' must be a number of mm per unit, got {given!r}")
        scale = float(_floats(given, 1, f"{where} depth_scale")[0])
        if not scale > 0:
            raise DataError(f"{where}: 'depth_scale' must be a positive number of mm per unit, got {scale}")
        R = t = None
        if "cam_R_w2c" in entry and "cam_t_w2c" in entry:
            R = _floats(entry["cam_R_w2c"], 9, f"{where} cam_R_w2c").reshape(3, 3)
            t = _floats(entry["cam_t_w2c"], 3, f"{where} cam_t_w2c")
        out[im_id] = SceneCamera(K, scale, R, t)
    return out


def read_scene_gt(path: Path | str) -> dict[int, list[GtPose]]:
    """``scene_gt.json`` -> ``{im_id: [GtPose, ...]}`` (mm), in ``gt_id`` order."""
    p = Path(path)
    out: dict[int, list[GtPose]] = {}
    for im_id, entries in _int_keys(read_json(p), p, "image id").items():
        if not isinstance(entries, list):
            raise DataError(f"{p}: image {im_id}: expected a list of GT poses")
        gts = []
        for gt_id, entry in enumerate(entries):
            where = f"{p}: image {im_id} instance {gt_id}"
            if not isinstance(entry, dict) or not {"cam_R_m2c", "cam_t_m2c", "obj_id"} <= set(entry):
                raise DataError(f"{where}: needs cam_R_m2c, cam_t_m2c and obj_id")
            try:
                obj_id = int(entry["obj_id"])
            except (TypeError, ValueError):
                raise DataError(f"{where}: obj_id must be an integer, got {entry['obj_id']!r}") from None
            gts.append(GtPose(obj_id, _floats(entry["cam_R_m2c"], 9, f"{where} cam_R_m2c").reshape(3, 3),
                              _floats(entry["cam_t_m2c"], 3, f"{where} cam_t_m2c")))
        out[im_id] = gts
    return out


def read_scene_gt_info(path: Path | str) -> dict[int, list[GtInfo]]:
    """``scene_gt_info.json`` -> ``{im_id: [GtInfo, ...]}`` (every entry needs ``visib_fract``)."""
    p = Path(path)
    out: dict[int, list[GtInfo]] = {}
    for im_id, entries in _int_keys(read_json(p), p, "image id").items():
        if not isinstance(entries, list):
            raise DataError(f"{p}: image {im_id}: expected a list of GT info entries")
        infos = []
        for gt_id, g in enumerate(entries):
            where = f"{p}: image {im_id} instance {gt_id}"
            if not isinstance(g, dict) or "visib_fract" not in g:
                raise DataError(f"{where}: missing 'visib_fract'")
            visib = float(_floats(g["visib_fract"], 1, f"{where} visib_fract")[0])
            try:
                infos.append(GtInfo(visib, _bbox(g.get("bbox_obj")), _bbox(g.get("bbox_visib")),
                                    _count(g.get("px_count_all")), _count(g.get("px_count_valid")),
                                    _count(g.get("px_count_visib"))))
            except (TypeError, ValueError) as exc:
                raise DataError(f"{where}: malformed entry ({exc})") from None
        out[im_id] = infos
    return out


def read_test_targets(path: Path | str) -> dict[tuple[int, int], dict[int, int]]:
    """``test_targets_bop19.json`` (a list of ``{scene_id, im_id, obj_id, inst_count}``, as the BOP
    datasets ship it beside their test splits) -> ``{(scene_id, im_id): {obj_id: inst_count}}``: the
    instances to estimate in each image, for splits whose ``scene_gt.json`` is withheld. Every entry
    needs the four fields as non-negative integers (``inst_count`` positive); one target listed twice
    is refused, naming the entry."""
    p = Path(path)
    data = read_json(p)
    if not isinstance(data, list):
        raise DataError(f"{p}: expected a JSON list of targets (scene_id, im_id, obj_id, inst_count), "
                        f"got {type(data).__name__}")
    out: dict[tuple[int, int], dict[int, int]] = {}
    for index, entry in enumerate(data):
        where = f"{p}: entry {index}"
        if not isinstance(entry, dict):
            raise DataError(f"{where}: expected an object with scene_id, im_id, obj_id, inst_count")
        values = {}
        for key in ("scene_id", "im_id", "obj_id", "inst_count"):
            value = entry.get(key)
            if isinstance(value, bool) or not isinstance(value, int) or value < (1 if key == "inst_count" else 0):
                raise DataError(f"{where}: '{key}' must be a {'positive' if key == 'inst_count' else 'non-negative'} "
                                f"integer, got {value!r}")
            values[key] = value
        image = out.setdefault((values["scene_id"], values["im_id"]), {})
        if values["obj_id"] in image:
            raise DataError(f"{where}: scene {values['scene_id']} image {values['im_id']} object {values['obj_id']} "
                            "is listed twice")
        image[values["obj_id"]] = values["inst_count"]
    return out


def _bbox(values: Any) -> tuple[int, int, int, int] | None:
    if values is None:
        return None
    x, y, w, h = (int(v) for v in values)
    return (x, y, w, h)


def _count(value: Any) -> int | None:
    return None if value is None else int(value)


def read_models_info(path: Path | str) -> dict[int, dict[str, Any]]:
    """``models_info.json`` -> ``{obj_id: entry}`` (entries as stored); every entry needs a positive ``diameter``."""
    p = Path(path)
    out = _int_keys(read_json(p), p, "object id")
    for obj_id, entry in out.items():
        if not isinstance(entry, dict) or "diameter" not in entry:
            raise DataError(f"{p}: object {obj_id}: missing 'diameter'")
        d = _floats(entry["diameter"], 1, f"{p}: object {obj_id} diameter")[0]
        if d <= 0:
            raise DataError(f"{p}: object {obj_id}: diameter must be positive, got {d}")
    return out


def model_file(models_dir: Path | str, obj_id: int) -> Path:
    """``obj_{obj_id:06d}.ply`` in a BOP models folder (millimetres)."""
    return Path(models_dir) / f"obj_{obj_id:06d}.ply"


def dataset_image_size(root: Path | str) -> tuple[int, int] | None:
    """``(width, height)`` from a BOP dataset's ``camera.json``, or None when it does not say."""
    path = Path(root) / "camera.json"
    if not path.is_file():
        return None
    data = read_json(path)
    if isinstance(data, dict) and "width" in data and "height" in data:
        return int(data["width"]), int(data["height"])
    return None

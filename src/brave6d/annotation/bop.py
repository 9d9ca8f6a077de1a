"""Export a scene's imported annotation as a BOP dataset (``<scene>/annotation/bop/``).

For every captured view, with the calibrated camera pose (``camera_poses``: robot pose x
hand-eye) and the undistorted pinhole camera (``ensure_undistorted``):

* ``scene_camera.json``: ``cam_K`` (undistorted, in BOP's pixel convention: the project's K
  with the principal point + 0.5 px, see :func:`brave6d.annotation.bop_format.bop_cam_K`),
  ``depth_scale`` 1.0 (depth PNGs are mm), ``cam_R_w2c``/``cam_t_w2c`` (world = robot base, mm);
* ``scene_gt.json``: every annotated instance, ``cam_T_model = inv(world_T_cam) @ world_T_model``
  with ``cam_t_m2c`` in mm; the instance order (``gt_id``) is the same in every image;
* ``mask/``, ``mask_visib/`` and ``scene_gt_info.json`` from :mod:`brave6d.annotation.visibility`
  (objects occlude each other and the spec's static meshes occlude them); ``px_count_valid``
  counts object pixels with a depth value in the undistorted depth image; ``bbox_obj`` and
  ``bbox_visib`` follow bop_toolkit (``[-1, -1, -1, -1]`` when the object is not visible);
* ``rgb/``, ``depth/``: the undistorted frames, HARD-LINKED (no extra disk, and unlike symlinks
  they survive moving or archiving the dataset; a copy is made across file systems or with
  ``copy_images``);
* ``camera.json`` (``cx``, ``cy`` in BOP's pixel convention too), ``models/obj_XXXXXX.ply`` (mm,
  vertex colours when present) and ``models/models_info.json`` (extents, diameter, symmetries
  from the library), for the annotated objects only: an object without instances (an older
  ``objects.json`` may list unannotated library objects) gets no model, as it has no ground truth.

The whole folder is written beside ``bop/`` and renamed into place at the end, so a failure
leaves the previous export (or none) untouched.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from brave6d.annotation.bop_format import BOP19_MIN_VISIB_FRACT, BopLayout, bop_cam_K, dump_bop_json
from brave6d.annotation.models import MeshData, load_mesh, write_bop_model
from brave6d.annotation.staging import link_or_copy
from brave6d.annotation.store import Annotation, AnnotatedObject, load_annotation
from brave6d.annotation.visibility import InstanceMasks, MaskRenderer, bbox_xywh
from brave6d.core.atomic import atomic_write_json, atomic_write_text, read_png, staged_folder
from brave6d.core.calibration_io import camera_poses
from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir
from brave6d.core.progress import progress
from brave6d.core.transforms import invert, transform_points
from brave6d.core.undistort import ensure_undistorted

log = logging.getLogger(__name__)

#: BOP targets are instances with at least this visible fraction.
_EMPTY_BBOX = [-1, -1, -1, -1]


@dataclass(frozen=True)
class BopExportOptions:
    """``split``/``scene_id`` name the BOP scene folder; ``copy_images`` copies instead of hard-linking;
    ``include_static`` lets the spec's static meshes occlude the objects."""

    split: str = "test"
    scene_id: int = 1
    copy_images: bool = False
    include_static: bool = True


@dataclass(frozen=True)
class BopExportResult:
    """What an export wrote."""

    layout: BopLayout
    images: int
    instances: int
    targets: int  # (image, instance) pairs with visib_fract >= BOP19_MIN_VISIB_FRACT
    mean_visib_fract: float


def export_bop(scene_dir: Path | str, options: BopExportOptions = BopExportOptions()) -> BopExportResult:
    """Write ``<scene>/annotation/bop/`` (see the module docstring)."""
    if not options.split or "/" in options.split or options.scene_id < 0:
        raise DataError(f"BOP export: invalid split {options.split!r} or scene id {options.scene_id}")
    scene = SceneDir(scene_dir)
    annotation = load_annotation(scene)
    views = camera_poses(scene)
    if not views:
        raise DataError(f"{scene.frames_path}: no captured frames to export")
    frames = ensure_undistorted(scene)
    camera = frames.camera
    objects = annotated_objects(annotation)
    models_m = {o.obj_id: _load_model(o) for o in objects}
    renderer = MaskRenderer(camera, models_m,
                            [(i.obj_id, i.world_T_model) for i in annotation.instances],
                            _static_meshes(scene) if options.include_static else [])

    scene_camera: dict[int, Any] = {}
    scene_gt: dict[int, Any] = {}
    scene_gt_info: dict[int, Any] = {}
    visib: list[float] = []
    with staged_folder(scene.bop_dir) as root:
        layout = BopLayout(root, options.split, options.scene_id)
        _write_models(layout, objects, models_m)
        cam_K = bop_cam_K(camera.K)
        atomic_write_json(layout.camera_path, {
            "cx": float(cam_K[0, 2]), "cy": float(cam_K[1, 2]), "depth_scale": 1.0, "fx": camera.fx,
            "fy": camera.fy, "height": camera.height, "width": camera.width})
        for record, world_T_cam in progress(views, total=len(views), desc="BOP export", unit="view"):
            im_id = record.index
            cam_T_world = invert(world_T_cam)
            scene_camera[im_id] = {"cam_K": cam_K.reshape(-1).tolist(), "depth_scale": 1.0,
                                   "cam_R_w2c": cam_T_world[:3, :3].reshape(-1).tolist(),
                                   "cam_t_w2c": (cam_T_world[:3, 3] * 1000.0).tolist()}
            scene_gt[im_id] = [_gt_entry(cam_T_world @ i.world_T_model, i.obj_id) for i in annotation.instances]
            _link(frames.rgb_path(record), layout.rgb_path(im_id), options.copy_images)
            depth_valid = None
            depth_path = frames.depth_path(record)
            if depth_path is not None:
                depth = read_png(depth_path, "depth")
                if depth.shape != (camera.height, camera.width):
                    raise DataError(f"{depth_path}: depth is {depth.shape[1]}x{depth.shape[0]}, "
                                    f"the camera is {camera.width}x{camera.height}")
                depth_valid = depth > 0
                _link(depth_path, layout.depth_path(im_id), options.copy_images)
            infos = []
            for gt_id, masks in enumerate(renderer.render(world_T_cam)):
                _write_mask(layout.mask_path(im_id, gt_id), masks.mask)
                _write_mask(layout.mask_visib_path(im_id, gt_id), masks.mask_visib)
                info = gt_info(masks, depth_valid)
                visib.append(info["visib_fract"])
                infos.append(info)
            scene_gt_info[im_id] = infos
        atomic_write_text(layout.scene_camera_path, dump_bop_json(scene_camera))
        atomic_write_text(layout.scene_gt_path, dump_bop_json(scene_gt))
        atomic_write_text(layout.scene_gt_info_path, dump_bop_json(scene_gt_info))
        atomic_write_json(layout.info_path, {
            "split": options.split, "scene_id": options.scene_id, "image_ids": sorted(scene_gt),
            "obj_ids": [o.obj_id for o in objects], "instances": len(annotation.instances),
            "camera": camera.to_json(), "images": "copied" if options.copy_images else "hard-linked",
            "static_occluders": options.include_static, "annotation": str(scene.objects_path)})
        os.sync()  # masks are plain writes inside the staging folder: flush once before the commit
    result_layout = layout.moved_to(scene.bop_dir)
    targets = sum(1 for v in visib if v >= BOP19_MIN_VISIB_FRACT)
    return BopExportResult(result_layout, len(views), len(annotation.instances), targets,
                           float(np.mean(visib)) if visib else 0.0)


def gt_info(masks: InstanceMasks, depth_valid: NDArray[np.bool_] | None) -> dict[str, Any]:
    """One ``scene_gt_info.json`` entry from an instance's masks (bop_toolkit definitions)."""
    px_visib = int(masks.mask_visib.sum())
    px_valid = int((masks.mask & depth_valid).sum()) if depth_valid is not None else 0
    visib_fract = px_visib / masks.px_count_all if masks.px_count_all > 0 else 0.0
    ys, xs = np.nonzero(masks.mask_visib)
    bbox_visib = bbox_xywh(xs, ys)
    bbox_obj = masks.bbox_all if px_visib > 0 and masks.bbox_all is not None else None
    return {"bbox_obj": list(bbox_obj) if bbox_obj else _EMPTY_BBOX,
            "bbox_visib": list(bbox_visib) if bbox_visib else _EMPTY_BBOX,
            "px_count_all": int(masks.px_count_all), "px_count_valid": px_valid, "px_count_visib": px_visib,
            "visib_fract": float(visib_fract)}


def _gt_entry(cam_T_model: NDArray[np.float64], obj_id: int) -> dict[str, Any]:
    return {"cam_R_m2c": cam_T_model[:3, :3].reshape(-1).tolist(),
            "cam_t_m2c": (cam_T_model[:3, 3] * 1000.0).tolist(), "obj_id": int(obj_id)}


def annotated_objects(annotation: Annotation) -> list[AnnotatedObject]:
    """The objects with at least one instance: the ones that get a BOP model."""
    used = {i.obj_id for i in annotation.instances}
    return [o for o in annotation.objects if o.obj_id in used]


def _load_model(obj: AnnotatedObject) -> MeshData:
    """The object's mesh in metres (model frame)."""
    return load_mesh(obj.mesh, f"object {obj.obj_id} ({obj.name})").scaled(obj.scale)


def _static_meshes(scene: SceneDir) -> list[MeshData]:
    """The spec's static meshes in the world frame (metres); none without a spec."""
    if not scene.spec_path.exists():
        log.info("%s: no scene spec; only the annotated objects occlude each other", scene.spec_path)
        return []
    spec = scene.load_spec()
    out = []
    for i, item in enumerate(spec.static_meshes):
        mesh = load_mesh(spec.resolve(item.mesh), f"{scene.spec_path}: static_meshes[{i}] ({item.name})",
                         colors=False)
        out.append(MeshData(transform_points(item.pose.matrix(), mesh.vertices * item.scale), mesh.faces,
                            None, mesh.source))
    return out


def _write_models(layout: BopLayout, objects: list[AnnotatedObject], models_m: dict[int, MeshData]) -> None:
    """``models/obj_XXXXXX.ply`` in mm and ``models_info.json`` (symmetry translations in mm)."""
    info: dict[int, Any] = {}
    for obj in objects:
        info[obj.obj_id] = write_bop_model(layout.model_path(obj.obj_id), models_m[obj.obj_id], 1.0,
                                           obj.symmetries_discrete,
                                           [(s.axis, tuple(1000.0 * o for o in s.offset)) for s in obj.symmetries_continuous])
    atomic_write_text(layout.models_info_path, dump_bop_json(info))


def _link(src: Path, dst: Path, copy: bool) -> None:
    if not src.is_file():
        raise DataError(f"{src}: undistorted frame not found")
    if copy:
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, dst)
    else:
        link_or_copy(src, dst)


def _write_mask(path: Path, mask: NDArray[np.bool_]) -> None:
    """uint8 PNG, 255 = object (plain write: the staging folder makes the export atomic)."""
    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255)
    if not ok:
        raise DataError(f"{path}: PNG encoding failed")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buf.tobytes())


def export_summary(result: BopExportResult) -> dict[str, Any]:
    """Key figures of an export (for the CLI and the demo)."""
    return {"images": result.images, "instances": result.instances, "targets (visib>=0.1)": result.targets,
            "mean visib_fract": result.mean_visib_fract}



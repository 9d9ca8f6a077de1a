"""Render one :class:`~brave6d.synth.randomize.ImageScene` with the project's CPU renderer (capture's
``SimCamera`` over a ``SceneModel``), the spec's camera-side effects included, and compute its BOP
ground truth: ``mask`` (the object alone, annotation's ``SilhouetteCaster``), ``mask_visib``
(the renderer's object-id buffer, the pixels where the object is the first surface) and the
``scene_gt_info`` counts (bop_toolkit's definitions, as the test split's export).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import depth_m_to_mm_u16
from brave6d.core.transforms import invert, transform_points
from brave6d.synth.randomize import ImageScene, LibraryAssets

_EMPTY_BBOX = [-1, -1, -1, -1]


@dataclass(frozen=True)
class RenderedImage:
    """One image and its ground truth, ready to write (``masks``/``masks_visib`` per target)."""

    rgb: NDArray[np.uint8]
    depth_mm: NDArray[np.uint16]
    masks: tuple[NDArray[np.bool_], ...]
    masks_visib: tuple[NDArray[np.bool_], ...]
    scene_camera: dict[str, Any]
    scene_gt: list[dict[str, Any]]
    scene_gt_info: list[dict[str, Any]]
    depth_m: NDArray[np.float32] | None = None  # the rendered depth before rounding (writers in finer units)


def render_image(scene: ImageScene, assets: LibraryAssets, seed: int) -> RenderedImage:
    """Render ``scene`` and its ground truth (see the module docstring)."""
    from brave6d.annotation import SilhouetteCaster, bop_cam_K
    from brave6d.capture import STATIC_ID_BASE, SceneModel, SimCamera

    source = assets.source
    parts = []
    for k, (lib_index, T) in enumerate(scene.targets):
        for part in assets.bodies[lib_index].parts:
            parts.append(replace(part, segment_id=k + 1, vertices=transform_points(T, part.vertices)))
    parts.append(replace(scene.plane, segment_id=STATIC_ID_BASE))
    for j, (body, T) in enumerate(scene.distractors):
        for part in body.parts:
            parts.append(replace(part, segment_id=STATIC_ID_BASE + 1 + j, vertices=transform_points(T, part.vertices)))
    world_T_cam = scene.world_T_cam
    camera = SimCamera(SceneModel(parts), source.camera, source.effects, lambda _t: world_T_cam, lambda: 0.0,
                       seed=seed, light_direction=scene.light_direction, ambient=scene.ambient,
                       background_rgb=scene.background_rgb, depth_range=source.depth_range)
    camera.frame_index = scene.index  # the effects' noise of image i depends only on (seed, i)
    frame = camera.capture()
    object_ids = frame.extras["object_ids"]
    assert frame.depth_m is not None
    depth_mm = depth_m_to_mm_u16(frame.depth_m)

    cam = source.camera
    caster = SilhouetteCaster({k: (assets.bodies[i].vertices, assets.bodies[i].faces)
                               for k, (i, _) in enumerate(scene.targets)},
                              [(k, T) for k, (_, T) in enumerate(scene.targets)])
    cam_T_world = invert(world_T_cam)
    masks, masks_visib, gt, info = [], [], [], []
    for k, sil in enumerate(caster.silhouettes(world_T_cam, cam)):
        mask = np.zeros((cam.height, cam.width), dtype=bool)
        inside = sil.within(cam.width, cam.height)
        mask[inside.ys, inside.xs] = True
        visib = mask & (object_ids == k + 1)
        masks.append(mask)
        masks_visib.append(visib)
        lib_index, world_T_model = scene.targets[k]
        cam_T_model = cam_T_world @ world_T_model
        gt.append({"cam_R_m2c": cam_T_model[:3, :3].reshape(-1).tolist(),
                   "cam_t_m2c": (cam_T_model[:3, 3] * 1000.0).tolist(),
                   "obj_id": int(source.objects[lib_index].obj_id)})
        info.append(gt_info(mask, visib, sil.px_count_all, sil.bbox_all, depth_mm > 0))
    scene_camera = {"cam_K": bop_cam_K(cam.K).reshape(-1).tolist(), "depth_scale": 1.0,
                    "cam_R_w2c": cam_T_world[:3, :3].reshape(-1).tolist(),
                    "cam_t_w2c": (cam_T_world[:3, 3] * 1000.0).tolist()}
    return RenderedImage(frame.rgb, depth_mm, tuple(masks), tuple(masks_visib), scene_camera, gt, info,
                         np.asarray(frame.depth_m, dtype=np.float32))


def gt_info(mask: NDArray[np.bool_], mask_visib: NDArray[np.bool_], px_count_all: int,
            bbox_all: tuple[int, int, int, int] | None, depth_valid: NDArray[np.bool_]) -> dict[str, Any]:
    """One ``scene_gt_info`` entry (bop_toolkit's definitions, as ``annotation``'s BOP export)."""
    from brave6d.annotation import bbox_xywh

    px_visib = int(mask_visib.sum())
    ys, xs = np.nonzero(mask_visib)
    bbox_visib = bbox_xywh(xs, ys)
    bbox_obj = bbox_all if px_visib > 0 and bbox_all is not None else None
    return {"bbox_obj": list(bbox_obj) if bbox_obj else _EMPTY_BBOX,
            "bbox_visib": list(bbox_visib) if bbox_visib else _EMPTY_BBOX,
            "px_count_all": int(px_count_all), "px_count_valid": int((mask & depth_valid).sum()),
            "px_count_visib": px_visib, "visib_fract": float(px_visib / px_count_all) if px_count_all > 0 else 0.0}

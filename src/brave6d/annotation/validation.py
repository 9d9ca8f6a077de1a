"""Check an exported BOP scene against the simulator's object-id buffers (simulated scenes, tests only).

The simulated capture writes ``capture/sim_truth/object_ids/{index:06d}.png`` (uint16, value
``k`` = ``spec.objects[k - 1]``, 0 = no object) in the RAW, distorted image. The BOP masks live
in the undistorted image, so the buffer is first undistorted with the CALIBRATED intrinsics
(nearest neighbour, labels are never blended). Instances are matched to spec objects by name:
the demo's 3D-DAT library uses the spec object names as ids.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from brave6d.annotation.bop_format import BopLayout, read_scene_gt_info
from brave6d.annotation.store import load_annotation
from brave6d.annotation.threedat import id_key
from brave6d.core.atomic import read_png
from brave6d.core.calibration_io import read_intrinsics
from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir


def mask_iou_against_sim_truth(scene_dir: Path | str, min_visib_fract: float = 0.1) -> dict[str, Any]:
    """IoU of ``mask_visib`` vs the undistorted sim object-id buffer, per view and object.

    Only instances with ``visib_fract >= min_visib_fract`` count. Returns ``mean_iou``,
    ``min_iou``, ``count``, ``per_view`` (``{im_id: {object name: iou}}``), ``worst`` (the five
    lowest ``(im_id, name, iou)``) and ``unmatched`` (instances with no spec object of that name).
    """
    scene = SceneDir(scene_dir)
    layout = BopLayout.of_scene(scene)
    annotation = load_annotation(scene)
    spec = scene.load_spec()
    sim_ids = {o.name: k + 1 for k, o in enumerate(spec.objects)}
    names = [id_key(i.threedat_id) for i in annotation.instances]
    raw_camera = read_intrinsics(scene)
    infos = read_scene_gt_info(layout.scene_gt_info_path)
    per_view: dict[int, dict[str, float]] = {}
    ious: list[tuple[int, str, float]] = []
    for im_id in sorted(infos):
        path = scene.capture.sim_object_ids_path(im_id)
        buffer = read_png(path, "any", (raw_camera.width, raw_camera.height), f"the camera in {scene.intrinsics_path}")
        if buffer.ndim != 2:
            raise DataError(f"{path}: expected a single-channel object-id image")
        undistorted = raw_camera.undistort_image(buffer, cv2.INTER_NEAREST)
        for gt_id, info in enumerate(infos[im_id]):
            name = names[gt_id]
            if info.visib_fract < min_visib_fract or name not in sim_ids:
                continue
            mask = read_png(layout.mask_visib_path(im_id, gt_id)) > 0
            sim = undistorted == sim_ids[name]
            union = int((mask | sim).sum())
            iou = float((mask & sim).sum()) / union if union else 1.0
            per_view.setdefault(im_id, {})[name] = iou
            ious.append((im_id, name, iou))
    values = [v for _, _, v in ious]
    return {
        "mean_iou": float(np.mean(values)) if values else float("nan"),
        "min_iou": float(np.min(values)) if values else float("nan"),
        "count": len(values),
        "per_view": per_view,
        "worst": sorted(ious, key=lambda x: x[2])[:5],
        "unmatched": sorted({n for n in names if n not in sim_ids}),
    }

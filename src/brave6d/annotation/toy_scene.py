"""A minimal captured-and-calibrated scene directory built from known camera poses (tests, examples).

:func:`make_synthetic_scene` writes what the annotation stage reads: ``scene.yaml`` (with
optional static meshes), ``calibration/intrinsics.json`` and ``handeye.json``,
``capture/frames.jsonl`` whose ``base_T_tcp @ tcp_T_cam`` reproduce the given camera poses, and
RGB/depth PNGs (flat images unless given).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from brave6d.core.atomic import atomic_write_text, write_png
from brave6d.core.calibration_io import write_handeye, write_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir
from brave6d.core.transforms import check_rigid, invert

DepthFn = Callable[[int], NDArray[np.uint16]]


def make_synthetic_scene(
    root: Path | str,
    camera: PinholeCamera,
    world_T_cams: Mapping[int, ArrayLike],
    *,
    tcp_T_cam: ArrayLike | None = None,
    static_meshes: Sequence[dict[str, Any]] = (),
    objects: Sequence[dict[str, Any]] = (),
    depth: DepthFn | None = None,
    name: str = "synthetic",
) -> SceneDir:
    """Create the scene directory ``root`` (see the module docstring).

    ``world_T_cams``: camera pose per frame index. ``static_meshes`` and ``objects``: spec items
    (``{name, mesh, scale, pose}``, objects also ``category``; mesh paths relative to ``root``).
    ``depth(index)``: the depth image in mm (default: 500 mm everywhere).
    """
    scene = SceneDir(root)
    scene.root.mkdir(parents=True, exist_ok=True)
    spec = {
        "name": name,
        "capture": {"target": [0.0, 0.0, 0.0], "distances_m": [0.5], "views_per_distance": max(1, len(world_T_cams))},
        "workspace": {"min": [-2.0, -2.0, -2.0], "max": [2.0, 2.0, 2.0]},
        "static_meshes": list(static_meshes),
        "objects": list(objects),
        "camera": {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy,
                   "cx": camera.cx, "cy": camera.cy, "dist": list(camera.dist)},
    }
    atomic_write_text(scene.spec_path, yaml.safe_dump(spec, sort_keys=False))
    scene.load_spec()  # must validate
    write_intrinsics(scene, camera)
    hand_eye = np.eye(4) if tcp_T_cam is None else check_rigid(tcp_T_cam, "tcp_T_cam")
    write_handeye(scene, hand_eye)
    log = FrameLog(scene.frames_path)
    h, w = camera.height, camera.width
    for index in sorted(world_T_cams):
        base_T_cam = check_rigid(world_T_cams[index], f"world_T_cams[{index}]")
        name_png = f"{index:06d}.png"
        write_png(scene.rgb_dir / name_png, np.full((h, w, 3), 128, dtype=np.uint8))
        d = depth(index) if depth is not None else np.full((h, w), 500, dtype=np.uint16)
        write_png(scene.depth_dir / name_png, np.asarray(d, dtype=np.uint16))
        log.append(FrameRecord(index=index, view_id=f"view{index:04d}", distance_level=0, distance_m=0.5,
                               rgb=f"rgb/{name_png}", depth=f"depth/{name_png}",
                               base_T_tcp=(base_T_cam @ invert(hand_eye)).tolist(), joints=[0.0] * 6,
                               timestamp=float(index)))
    return scene

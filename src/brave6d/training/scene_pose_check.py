"""The pose check at the start of training: do the scene's cameras see the scene?

:func:`check_scene_poses` picks what the cameras must see, the best the scene has: the sparse points
an import brought (``capture/imported_points.ply``), else the spec's capture target (where the robot
pointed the camera), else the point where the views' optical axes meet; a scene with none of these
is not checked (logged). :func:`brave6d.training.train` calls it before it makes initial points, so
``brave6d train`` (and every in-memory training) refuses cameras that face away from the scene, naming
them, instead of training to a blur.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from brave6d.core.errors import BraveError
from brave6d.core.layout import SceneDir
from brave6d.training.pose_check import MIN_VISIBLE_SHARE, PoseCheck, axes_meeting_point, check_camera_poses

if TYPE_CHECKING:
    from brave6d.training.views import TrainingData

log = logging.getLogger(__name__)

HOW_TO_SKIP = "pass --skip-pose-check to train anyway (check_poses=False in Python)"


def check_scene_poses(data: TrainingData, scene: SceneDir | None = None, min_share: float = MIN_VISIBLE_SHARE
                      ) -> PoseCheck | None:
    """Check ``data``'s views against the scene's reference (module docstring); raises
    :class:`~brave6d.training.pose_check.PoseCheckError` naming the views that do not see it,
    returns None when the scene has no reference to check against."""
    views = data.views
    reference = _reference(scene, [v.base_T_cam for v in views])
    if reference is None:
        log.warning("pose check skipped: no imported points, no capture target and the optical axes do not meet")
        return None
    points, what = reference
    result = check_camera_poses(data.camera, [(v.view_id, v.base_T_cam) for v in views], points, what, min_share,
                                how_to_skip=HOW_TO_SKIP)
    log.info("%s", result.summary())
    return result


def _reference(scene: SceneDir | None, poses: list[np.ndarray]) -> tuple[np.ndarray, str] | None:
    if scene is not None:
        from brave6d.training.importing.scene_files import read_imported_points

        imported = read_imported_points(scene)
        if imported is not None and len(imported[0]):
            return imported[0], f"the {len(imported[0])} sparse points the import brought ({scene.imported_points_path.name})"
        if scene.spec_path.is_file():
            try:
                target = np.asarray(scene.load_spec().capture.target, np.float64)
                return target.reshape(1, 3), f"the capture target {tuple(round(float(v), 4) for v in target)} (scene.yaml)"
            except BraveError as exc:
                log.warning("pose check: %s unreadable (%s); using the optical axes instead", scene.spec_path, exc)
    meet = axes_meeting_point(poses)
    return None if meet is None else (meet.reshape(1, 3), "the point where the views' optical axes meet")

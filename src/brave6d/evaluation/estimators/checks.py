"""What an agent checks of a detector's or pose estimator's answer before using it: anything not
finite, a score outside [0, 1], an empty box or a pose that is not rigid stops with one line naming
the implementation (a user's model that answers NaN must not be scored as a pose)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from brave6d.core.errors import BraveError
from brave6d.evaluation.estimators.protocol import Detection

#: How far R^T R may be from I, and det R from 1, for a pose to count as rigid.
RIGID_TOLERANCE = 1e-4


def implementation_name(obj: Any) -> str:
    """``module.Class`` of ``obj``: what the errors and episode notes call an implementation."""
    kind = type(obj)
    return f"{kind.__module__}.{kind.__qualname__}"


def _score_ok(score: Any) -> bool:
    return isinstance(score, (int, float, np.floating, np.integer)) and math.isfinite(float(score)) \
        and 0.0 <= float(score) <= 1.0


def checked_detections(found: Any, source: Any, obj_id: int | None = None) -> list[Detection]:
    """``found`` (a detector's answer) as a list of :class:`Detection`; one line naming ``source`` when
    it is not a list of detections with finite, non-empty boxes and scores in [0, 1] (of ``obj_id``
    when given)."""
    who = implementation_name(source)
    if not isinstance(found, (list, tuple)):
        raise BraveError(f"{who}.detect returned {type(found).__name__}, expected a list of Detection")
    out = []
    for i, d in enumerate(found):
        if not isinstance(d, Detection):
            raise BraveError(f"{who}.detect: item {i} is a {type(d).__name__}, expected a Detection")
        box = tuple(d.box)
        if len(box) != 4 or not all(isinstance(b, (int, float, np.floating, np.integer)) and math.isfinite(float(b))
                                    for b in box) or not (box[2] > box[0] and box[3] > box[1]):
            raise BraveError(f"{who}.detect: item {i} has box {box}: expected finite (x0, y0, x1, y1) with x1 > x0, y1 > y0")
        if not _score_ok(d.score):
            raise BraveError(f"{who}.detect: item {i} has score {d.score!r}: expected a number in [0, 1]")
        if obj_id is not None and int(d.obj_id) != int(obj_id):
            raise BraveError(f"{who}.detect: asked for object {obj_id}, item {i} is object {d.obj_id}")
        out.append(Detection(int(d.obj_id), tuple(float(b) for b in box), float(d.score)))  # type: ignore[arg-type]
    return out


def checked_pose(pose: Any, source: Any) -> Any:
    """``pose`` (a pose estimator's answer) unchanged when it has a finite rigid ``cam_T_obj`` in front
    of the camera, a ``score`` in [0, 1] and a ``fit`` None or in [0, 1]; else one line naming ``source``."""
    who = implementation_name(source)
    if not hasattr(pose, "cam_T_obj") or not hasattr(pose, "score"):
        raise BraveError(f"{who}.estimate returned {type(pose).__name__}, expected an EstimatedPose")
    T = np.asarray(pose.cam_T_obj, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise BraveError(f"{who}.estimate: cam_T_obj must be a finite 4x4 matrix, got shape {T.shape}"
                         + ("" if T.shape != (4, 4) else " with NaN or inf"))
    R = T[:3, :3]
    if not (np.abs(R).max() <= 1.0 + RIGID_TOLERANCE and np.allclose(R.T @ R, np.eye(3), atol=RIGID_TOLERANCE) and abs(np.linalg.det(R) - 1.0) < RIGID_TOLERANCE
            and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0])):
        raise BraveError(f"{who}.estimate: cam_T_obj is not a rigid transform (a rotation and a translation)")
    if not T[2, 3] > 0:
        raise BraveError(f"{who}.estimate: cam_T_obj puts the object behind the camera (z = {T[2, 3]:.4g} m)")
    if not _score_ok(pose.score):
        raise BraveError(f"{who}.estimate: score {pose.score!r}: expected a number in [0, 1]")
    fit = getattr(pose, "fit", None)
    if fit is not None and not _score_ok(fit):
        raise BraveError(f"{who}.estimate: fit {fit!r}: expected None or a number in [0, 1]")
    return pose


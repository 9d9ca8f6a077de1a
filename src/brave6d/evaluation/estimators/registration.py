"""The weight-free estimator (:func:`~brave6d.evaluation.agents.estimate_pose`: the table plane, the
object's cluster above it, FPFH + RANSAC and ICP against the CAD model) as a
:class:`~brave6d.evaluation.estimators.protocol.PoseEstimator`: it needs depth, so it refuses an
RGB-only call (cause ``needs-depth``). Any detector's box tells it where the object is."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.evaluation.estimators.protocol import Array, Detection, EstimatedPose, EstimatorRefused


class RegistrationPoseEstimator:
    """Registration of the object's CAD model (given by :meth:`add_model`) onto the box's depth."""

    def __init__(self, options: Any = None) -> None:
        from brave6d.evaluation.agents import FrameOptions

        self.options = options if options is not None else FrameOptions()
        self.models: dict[int, Any] = {}

    def add_model(self, obj_id: int, vertices_m: Array, faces: NDArray[np.int64]) -> None:
        from brave6d.evaluation.agents import prepare_model

        self.models[int(obj_id)] = prepare_model(np.asarray(vertices_m, dtype=np.float64), "m", faces=faces,
                                                 obj_id=int(obj_id))

    def estimate(self, image: NDArray[np.uint8], depth_m: NDArray[np.floating] | None, K: Array,
                 detection: Detection) -> EstimatedPose:
        from brave6d.evaluation.agents import BoxHint, EstimateRefused, estimate_pose

        if depth_m is None:
            raise EstimatorRefused("needs-depth", "registration: the weight-free estimator needs a depth image "
                                                  "(play a -depth agent)")
        model = self.models.get(int(detection.obj_id))
        if model is None:
            raise EstimatorRefused("unknown-object", f"registration: no CAD model of object {detection.obj_id} "
                                                     "was given (add_model)")
        x0, y0, x1, y1 = detection.box
        try:
            pose = estimate_pose(depth_m, K, model, BoxHint(x0, y0, x1 - x0, y1 - y0), rgb=image, options=self.options)
        except EstimateRefused as exc:
            raise EstimatorRefused(exc.cause, f"registration: {exc}") from None
        return EstimatedPose(pose.cam_T_obj, float(np.clip(pose.score, 0.0, 1.0)), float(np.clip(pose.fitness, 0.0, 1.0)),
                             {"method": pose.method, "hypotheses": pose.hypotheses})

"""The built-in learned estimator (:class:`~brave6d.evaluation.learned.LearnedEstimator`: the
detector and the coordinate network) behind the two interfaces of
:mod:`brave6d.evaluation.estimators.protocol`, answering exactly as the learned agents always did.

- :class:`LearnedDetector`: the detector's detections of the asked object, best first, the best
  one's box refined by the coordinate net's visible mask (``LearnedEstimator.best_detection``);
- :class:`LearnedPoseEstimator`: the coordinate net + PnP (+ depth and ICP when given depth), and
  the multi-view ICP of the depth agents' fusion.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.evaluation.estimators.protocol import Array, Box, Detection, EstimatedPose


class LearnedDetector:
    """A :class:`~brave6d.evaluation.estimators.protocol.Detector` over a ``LearnedEstimator``:
    detections scoring at least ``min_score``, best first, the best one's box refined (one or two
    coordinate-net passes), the others as the detector found them."""

    def __init__(self, estimator: Any, min_score: float = 0.05) -> None:
        self.estimator, self.min_score = estimator, float(min_score)

    def detect(self, image: NDArray[np.uint8], K: Array, obj_id: int | None = None) -> list[Detection]:
        if obj_id is not None:
            self.estimator._check_object(obj_id)  # refuses an object it never trained on ("unknown-object")
        found = self.estimator.detect(image, K, self.min_score, obj_id)
        if not found:
            return []
        return [self.estimator.refine_box(image, K, found[0]), *found[1:]]


class LearnedPoseEstimator:
    """A :class:`~brave6d.evaluation.estimators.protocol.PoseEstimator` (and ``MultiViewRefiner``)
    over a ``LearnedEstimator``; ``image_width``: the width of the images its pose network was
    trained on (the learned agents ask the server for episodes this wide)."""

    def __init__(self, estimator: Any) -> None:
        self.estimator = estimator
        self.image_width: int = int(estimator.crop_source_width)

    def add_model(self, obj_id: int, vertices_m: Array, faces: NDArray[np.int64]) -> None:
        """The mesh gives the RGB-only distance from the mask's area and the depth ICP; an object the
        model never trained on is left for :meth:`estimate` to refuse."""
        e = self.estimator
        if int(obj_id) in e.surfaces or int(obj_id) not in e.model.objects or faces is None or not len(faces):
            return
        e.set_surface(int(obj_id), np.asarray(vertices_m, dtype=np.float64), faces)

    def estimate(self, image: NDArray[np.uint8], depth_m: NDArray[np.floating] | None, K: Array,
                 detection: Detection) -> EstimatedPose:
        pose = self.estimator.estimate(image, K, detection.obj_id, detection.box, depth_m, detection.score)
        return EstimatedPose(pose.cam_T_obj, pose.score, pose.fit,
                             {"inliers": pose.inliers, "correspondences": pose.correspondences,
                              "depth_scale": pose.depth_scale, "icp": pose.icp})

    def refine_views(self, obj_id: int, ref_T_obj: Array,
                     views: list[tuple[Array, Array, NDArray[np.floating], Box]]) -> tuple[Array, bool, float]:
        return self.estimator.refine_views(obj_id, ref_T_obj, views)  # type: ignore[no-any-return]

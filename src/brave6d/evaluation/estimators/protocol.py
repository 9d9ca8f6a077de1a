"""The seam between an agent and whatever finds objects and their poses: two small typed interfaces.

A :class:`Detector` finds objects in one colour image; a :class:`PoseEstimator` gives one object's
pose inside one detection's box. The learned agents (``learned-static`` / ``-active`` and their
``-depth`` variants) take any implementation of each; the built-in detector + coordinate network
and the weight-free depth registration are implementations too
(:mod:`brave6d.evaluation.estimators.learned`, :mod:`brave6d.evaluation.estimators.registration`).

What they may receive: the episode's colour image, its depth (the ``-depth`` agents only; None
otherwise), the camera matrix K of that image, the detection the agent chose, and once per object
its CAD model (:meth:`PoseEstimator.add_model`, from the server's public ``/models``). What they never
receive in a scored run: ground truth of any kind (no pose, box, mask or visibility of any
object; the server keeps them). Units: pixels with OpenCV's convention (pixel (u, v) centred at
integer (u, v), a box's edges are pixel edges: ``(x0, y0, x1, y1)``), metres for depth and poses.

An implementation says "no answer" by raising :class:`EstimatorRefused` (a cause word and a one-line
message); the agent records it and goes on. Anything else it returns is checked
(:mod:`brave6d.evaluation.estimators.checks`): a NaN box, a score outside [0, 1] or a pose that is not
rigid stops the episode with one line naming the implementation, never a silent wrong answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError

Array = NDArray[np.float64]
#: A box: (x0, y0, x1, y1), pixel edges of the image it was found in.
Box = tuple[float, float, float, float]


class EstimatorRefused(BraveError):
    """A detector or pose estimator has no answer; ``cause`` is a short word (e.g. ``no-detection``,
    ``needs-depth``, ``unknown-object``) the agent's notes record."""

    def __init__(self, cause: str, message: str) -> None:
        super().__init__(message)
        self.cause = cause


@dataclass(frozen=True)
class Detection:
    """A detected object: its obj_id, box (x0, y0, x1, y1; pixel edges of the input image) and score in [0, 1]."""

    obj_id: int
    box: Box
    score: float

    @property
    def size_px(self) -> float:
        """Geometric mean of the box's width and height."""
        return math.sqrt(max(self.box[2] - self.box[0], 0.0) * max(self.box[3] - self.box[1], 0.0))


@dataclass(frozen=True)
class EstimatedPose:
    """A pose: ``cam_T_obj`` (4x4, metres, the input image's camera frame), its score in [0, 1]
    (higher is better; it ranks the views an active agent saw), ``fit`` (optional, in [0, 1]: the
    fraction of the box's depth points the posed model explains, which ranks views with depth
    before ``score``) and free notes for the episode log."""

    cam_T_obj: Array
    score: float
    fit: float | None = None
    notes: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Detector(Protocol):
    """Finds objects in one colour image."""

    def detect(self, image: NDArray[np.uint8], K: Array, obj_id: int | None = None) -> list[Detection]:
        """The detections in ``image`` (H x W x 3, uint8 RGB) taken with ``K`` (3x3), best first; only
        ``obj_id``'s when given (an episode names its target), else every object it knows. An empty list:
        nothing found. May raise :class:`EstimatorRefused` (e.g. ``unknown-object``)."""
        ...


@runtime_checkable
class PoseEstimator(Protocol):
    """Gives one object's pose inside one detection's box."""

    def add_model(self, obj_id: int, vertices_m: Array, faces: NDArray[np.int64]) -> None:
        """The CAD model of ``obj_id`` (vertices in metres, model frame; triangle indices), as the
        server's ``/models`` gives it to any agent. Called once per object before its first
        :meth:`estimate`; an estimator that needs no mesh ignores it."""
        ...

    def estimate(self, image: NDArray[np.uint8], depth_m: NDArray[np.floating] | None, K: Array,
                 detection: Detection) -> EstimatedPose:
        """The pose of ``detection.obj_id`` inside ``detection.box`` of ``image`` (uint8 RGB); ``depth_m``:
        the same view's depth in metres (0: none) or None (RGB-only agents); ``detection.score`` is
        the detector's. Raises :class:`EstimatorRefused` when it has no pose."""
        ...


@runtime_checkable
class MultiViewRefiner(Protocol):
    """Optional, beside :class:`PoseEstimator`: one pose refined with the depth of several views at
    once (the depth agents' fusion; an estimator without it keeps its best view's pose)."""

    def refine_views(self, obj_id: int, ref_T_obj: Array,
                     views: list[tuple[Array, Array, NDArray[np.floating], Box]]) -> tuple[Array, bool, float]:
        """``ref_T_obj`` refined with every view's ``(ref_T_cam, K, depth_m, box)``; (pose, refined?, fit)."""
        ...

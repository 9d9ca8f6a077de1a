"""The static estimator on one view, scored with BOP's metrics: what the distance and realism
sections measure point by point.

The estimator is the baseline's (:mod:`brave6d.evaluation.agents`): :func:`~brave6d.evaluation.agents.perceive`
finds the target's cluster near where the target is expected, :func:`~brave6d.evaluation.agents.register_model`
fits the model to it. It is given what an episode's start view gives the static agent: the
target's place in the image (the static agent's start view looks at the target, so that place is
the principal point; a captured frame looks wherever the capture plan pointed, so it is the
projection of the target's centre), from which the expected point is read off the depth image on
that pixel's ray. Unlike the agent, a view without a cluster gives no estimate (the agent would
submit a guess on the ray, which BOP scores as a miss all the same).

Scoring is :func:`brave6d.evaluation.metrics.evaluate_bop19` on one target in one image: AR and its VSD /
MSSD / MSPD parts are the fractions of BOP19 thresholds the estimate passes, so the mean over
targets of these per-target values is the pooled AR of a set of views.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError

Array = NDArray[np.float64]

#: BOP19 targets: ground-truth instances at least this visible (``test_targets_bop19.json``).
MIN_VISIB_FRACT = 0.1


@dataclass(frozen=True)
class ViewEstimate:
    """One estimate: ``cam_T_obj`` (None: no cluster found), its score and the estimator's wall time."""

    cam_T_obj: Array | None
    score: float
    seconds: float
    method: str


@dataclass(frozen=True)
class ViewScore:
    """BOP19 scores of one estimate against one target (fractions of thresholds passed, 0..1)."""

    ar: float
    ar_vsd: float
    ar_mssd: float
    ar_mspd: float
    mssd_mm: float | None
    mspd_px: float | None

    def to_json(self) -> dict[str, Any]:
        return {"ar": self.ar, "ar_vsd": self.ar_vsd, "ar_mssd": self.ar_mssd, "ar_mspd": self.ar_mspd,
                "mssd_mm": self.mssd_mm, "mspd_px": self.mspd_px}


MISSED = ViewScore(0.0, 0.0, 0.0, 0.0, None, None)


def model_centre_m(vertices_mm: Array) -> Array:
    """Centre of a model's bounding box in metres (model frame): where the start view looks."""
    v = np.asarray(vertices_mm, dtype=np.float64).reshape(-1, 3)
    return 0.5 * (v.min(axis=0) + v.max(axis=0)) / 1000.0


def project(point_cam: Array, K: Array) -> tuple[float, float]:
    """Pixel (column, row) of a camera-frame point (OpenCV ``K``)."""
    z = max(float(point_cam[2]), 1e-9)
    return float(K[0, 0] * point_cam[0] / z + K[0, 2]), float(K[1, 1] * point_cam[1] / z + K[1, 2])


def anchor_on_ray(depth_m: NDArray[np.floating], K: Array, pixel: tuple[float, float]) -> Array:
    """The expected target point: on ``pixel``'s ray at the median depth of the valid pixels near
    it (the baseline's ``axis_anchor`` generalised from the principal point to any pixel)."""
    d = np.asarray(depth_m, dtype=np.float64)
    rows, cols = np.nonzero(np.isfinite(d) & (d > 0))
    if len(rows) == 0:
        z = 0.3
    else:
        r = np.hypot(cols - pixel[0], rows - pixel[1])
        close = r < max(4.0, 0.03 * float(K[0, 0]))
        z = float(np.median(d[rows[close], cols[close]] if np.any(close) else d[rows, cols]))
    return np.array([(pixel[0] - K[0, 2]) / K[0, 0] * z, (pixel[1] - K[1, 2]) / K[1, 1] * z, z])


class StaticEstimator:
    """The static agent's perception + registration on single views (see the module docstring).

    ``models``: ``obj_id -> (model PLY in mm, diameter in mm)``, as the server sends them;
    ``color_weight``: the registration's weight of colour (None: the agents' default, 0: depth alone).
    """

    #: What the estimator looks at; part of the stored measurements' keys, so results of an
    #: earlier estimator (depth alone) are measured again rather than reused.
    SIGNALS = "depth+colour"

    def __init__(self, models: Mapping[int, tuple[Path, float]], color_weight: float | None = None) -> None:
        from brave6d.evaluation.agents import BaselineOptions, RegistrationOptions

        self.options = BaselineOptions()
        if color_weight is not None:  # the agents' default otherwise
            self.options = replace(self.options, registration=RegistrationOptions(color_weight=float(color_weight)))
        self._sources = {int(k): (Path(p), float(d)) for k, (p, d) in models.items()}
        self._clouds: dict[int, Any] = {}

    def cloud(self, obj_id: int) -> Any:
        """The agent's model cloud of ``obj_id`` (sampled once)."""
        from brave6d.evaluation.agents import read_model_ply, sample_model

        if obj_id not in self._clouds:
            if obj_id not in self._sources:
                raise DataError(f"no model for object {obj_id} (known: {sorted(self._sources)})")
            path, diameter = self._sources[obj_id]
            verts, faces, colors = read_model_ply(path.read_bytes())
            self._clouds[obj_id] = sample_model(obj_id, verts, faces, diameter, self.options.model.points,
                                                self.options.model.seed, colors)
        return self._clouds[obj_id]

    def estimate(self, depth_m: NDArray[np.floating], K: Array, world_T_cam: Array, obj_id: int,
                 target_px: tuple[float, float], rgb: NDArray[np.uint8] | None = None) -> ViewEstimate:
        """The estimate of ``obj_id`` in one view whose target is expected at pixel ``target_px``
        (``rgb``: the view's colour image, which breaks flip ties; None: depth alone)."""
        from brave6d.evaluation.agents import perceive, register_model

        model = self.cloud(obj_id)
        t0 = time.perf_counter()
        prior = anchor_on_ray(depth_m, K, target_px)
        seen = perceive(depth_m, K, world_T_cam, model, prior, self.options.perception)
        if seen.cluster is None:
            return ViewEstimate(None, 0.0, time.perf_counter() - t0, "none")
        reg = register_model(model, seen.cluster, seen.plane, depth_m, K, self.options.registration, seen.min_height,
                             rgb)
        return ViewEstimate(reg.cam_T_obj, float(np.clip(reg.score, 0.0, 1.0)), time.perf_counter() - t0, reg.method)


class ViewScorer:
    """BOP19 scores of single estimates (one depth renderer shared by every call, for VSD)."""

    def __init__(self, models: Mapping[int, Any]) -> None:
        self.models = dict(models)
        self._renderer: Any = None

    def score(self, estimate: ViewEstimate, obj_id: int, gt_cam_T_obj: Array, K: Array, size: tuple[int, int],
              depth_m: NDArray[np.floating], visib_fract: float) -> ViewScore:
        """Scores of ``estimate`` against the target's ground truth in a view with test depth ``depth_m``."""
        from brave6d.evaluation.metrics import DepthRenderer, Estimate, GTInstance, evaluate_bop19

        if estimate.cam_T_obj is None:
            return MISSED
        if self._renderer is None:
            self._renderer = DepthRenderer()
        depth_mm = np.where(np.isfinite(depth_m), np.asarray(depth_m, dtype=np.float64) * 1000.0, 0.0)
        gt = GTInstance(0, 0, obj_id, gt_cam_T_obj[:3, :3], gt_cam_T_obj[:3, 3] * 1000.0,
                        max(float(visib_fract), MIN_VISIB_FRACT), K, size, depth_mm)
        est = Estimate(0, 0, obj_id, estimate.score, estimate.cam_T_obj[:3, :3], estimate.cam_T_obj[:3, 3] * 1000.0)
        scores = evaluate_bop19([gt], [est], {obj_id: self.models[obj_id]}, renderer=self._renderer)
        err = scores.errors[0] if scores.errors else None
        mssd = float(err.mssd[0]) if err is not None and err.mssd is not None else math.nan
        mspd = float(err.mspd[0]) if err is not None and err.mspd is not None else math.nan
        return ViewScore(scores.ar, float(scores.ar_vsd or 0.0), float(scores.ar_mssd or 0.0),
                         float(scores.ar_mspd or 0.0), mssd if math.isfinite(mssd) else None,
                         mspd if math.isfinite(mspd) else None)


def bbox_diagonal(bbox: Any) -> float | None:
    """Diagonal (px) of a BOP ``[x, y, w, h]`` box; None without one."""
    if bbox is None or len(bbox) != 4:
        return None
    return float(math.hypot(float(bbox[2]), float(bbox[3])))

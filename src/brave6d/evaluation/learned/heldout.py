"""Held-out figures of a trained estimator on the train_pbr images it never trained on.

- detection, per object: recall at IoU 0.5 among the detections scoring at least the agents'
  threshold, and AP at IoU 0.5 (all-point interpolated, every detection above 0.05), of the boxes
  the agents use (refined by the coordinate net's mask) and of the detector's own boxes (what the
  refinement buys, beside what it costs per detection);
- pose, per object and overall: BOP19 AR (the project's metrics, the split's own depth for VSD)
  given the true visible box and given the detected box, each RGB-only and refined with the
  split's depth. The detected box is taken as an agent takes it: the top-scoring detection of the
  object's id (at the agents' threshold), whether or not it is the one overlapping the truth.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.evaluation.learned.crops import iou
from brave6d.evaluation.learned.data import MIN_VISIB_FRACT, TrainingData
from brave6d.evaluation.learned.inference import Detection, LearnedEstimator, LearnedRefused, pnp_method
from brave6d.evaluation.learned.presets import DETECTION_THRESHOLD

log = logging.getLogger(__name__)
IOU = 0.5
POSE_VARIANTS = ("true_box_rgb", "true_box_depth", "detected_rgb", "detected_depth")


@dataclass
class HeldoutScores:
    """Per object: detection recall / AP at IoU 0.5; per variant: pose AR overall, per object and
    per metric (``pose_ar_metrics``: vsd, mssd, mspd); refusals per variant by cause; seconds per
    estimate (median). With ``keep_estimates`` (:func:`score_heldout`): the ground truths scored
    against (``gts``) and, per variant, each estimate with the index of its ground truth in ``gts``
    (``estimates``), for benchmarks that score the same poses changed."""

    images: int
    instances: int
    recall: dict[int, float]
    ap: dict[int, float]
    pose_ar: dict[str, float]
    pose_ar_per_object: dict[str, dict[int, float]]
    refusals: dict[str, dict[str, int]] = field(default_factory=dict)
    seconds_per_estimate: float = 0.0
    recall_raw: dict[int, float] = field(default_factory=dict)
    ap_raw: dict[int, float] = field(default_factory=dict)
    seconds_per_detection: dict[str, float] = field(default_factory=dict)
    detect_widths: tuple[int, ...] = ()
    pose_ar_metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    crop_zooms: tuple[float, ...] = ()
    gts: list[Any] | None = None
    estimates: dict[str, list[tuple[int, Any]]] | None = None

    def to_json(self) -> dict[str, Any]:
        return {"images": self.images, "instances": self.instances,
                "detection_recall_iou50": {str(k): v for k, v in self.recall.items()},
                "detection_ap_iou50": {str(k): v for k, v in self.ap.items()},
                "pose_ar": dict(self.pose_ar),
                "pose_ar_per_object": {v: {str(k): x for k, x in d.items()} for v, d in self.pose_ar_per_object.items()},
                "pose_ar_metrics": {v: dict(d) for v, d in self.pose_ar_metrics.items()},
                "refusals": self.refusals, "seconds_per_estimate": self.seconds_per_estimate,
                "detection_recall_iou50_unrefined": {str(k): v for k, v in self.recall_raw.items()},
                "detection_ap_iou50_unrefined": {str(k): v for k, v in self.ap_raw.items()},
                "seconds_per_detection": dict(self.seconds_per_detection),
                "detection_threshold": DETECTION_THRESHOLD, "detect_widths": list(self.detect_widths),
                "crop_zooms": list(self.crop_zooms), "pnp": pnp_method()}

    def detection_summary(self) -> dict[str, Any]:
        """The detection figures the benchmarks tabulate per setting (JSON keys): images, instances,
        recall and AP per object (obj_id as text), the worst object's recall, recall of the
        detector's own boxes and the pose AR given the detected boxes (RGB only, + depth)."""
        return {"images": self.images, "instances": self.instances,
                "recall": {str(k): v for k, v in self.recall.items()},
                "recall_min": min(self.recall.values()) if self.recall else float("nan"),
                "recall_unrefined": {str(k): v for k, v in self.recall_raw.items()},
                "ap": {str(k): v for k, v in self.ap.items()},
                "detected_ar": {k: self.pose_ar[k] for k in ("detected_rgb", "detected_depth") if k in self.pose_ar}}


def average_precision(scores: list[float], hits: list[bool], n_gt: int) -> float:
    """All-point interpolated AP of detections (``scores``, whether each is a true positive) against ``n_gt``."""
    if n_gt == 0:
        return float("nan")
    if not scores:
        return 0.0
    order = np.argsort(-np.asarray(scores), kind="stable")
    tp = np.cumsum(np.asarray(hits, dtype=np.float64)[order])
    fp = np.cumsum(1.0 - np.asarray(hits, dtype=np.float64)[order])
    recall = tp / n_gt
    precision = tp / np.maximum(tp + fp, 1e-12)
    r = np.concatenate([[0.0], recall, [recall[-1]]])
    p = np.concatenate([[1.0], precision, [0.0]])
    p = np.maximum.accumulate(p[::-1])[::-1]
    return float(np.sum((r[1:] - r[:-1]) * p[1:]))


def score_heldout(estimator: LearnedEstimator, data: TrainingData, models_dir: Path | str,
                  max_images: int | None = None, show_progress: bool = True,
                  images: list[int] | None = None, keep_estimates: bool = False) -> HeldoutScores:
    """Score ``estimator`` on the held-out images of ``data`` (module docstring); ``images``: other
    image indices instead (the tests score training images to see what a model learnt);
    ``keep_estimates``: return the ground truths and estimates too (:class:`HeldoutScores`)."""
    import cv2

    from brave6d.core.progress import progress
    from brave6d.evaluation.metrics import DepthRenderer, Estimate, GTInstance, evaluate_bop19, load_models

    images = (data.split(True) if images is None else list(images))[:max_images]
    models = load_models(models_dir, sorted(data.objects))
    obj_ids = sorted(data.objects)
    tallies = {kind: _Tally(obj_ids) for kind in ("refined", "raw")}
    detect_s: dict[str, list[float]] = {"image": [], "refine": []}
    gts: list[Any] = []
    estimates: dict[str, list[tuple[int, Any]]] = {v: [] for v in POSE_VARIANTS}  # (index in gts, estimate)
    refusals: dict[str, dict[str, int]] = {v: {} for v in POSE_VARIANTS}
    times: list[float] = []
    n_instances = 0
    for i in progress(images, total=len(images), desc="learn: held-out", unit="img", disable=not show_progress):
        record = data.images[i]
        rgb, K = record.rgb_crop, record.K_crop
        depth_full_mm = record.read_depth_mm()  # the PNG times the image's depth_scale
        h, w = rgb.shape[:2]
        depth_work = cv2.resize(depth_full_mm, (w, h), interpolation=cv2.INTER_NEAREST) / 1000.0
        t0 = time.perf_counter()
        raw = estimator.detect(rgb, K, min_score=0.05)  # boxes in rgb's (the crops' source) pixels
        t1 = time.perf_counter()
        detections = [estimator.refine_box(rgb, K, d) for d in raw]
        detect_s["image"].append(t1 - t0)
        if raw:
            detect_s["refine"].append((time.perf_counter() - t1) / len(raw))
        instances = [data.instances[k] for k in record.instances]
        n_instances += len(instances)
        tallies["raw"].match(raw, instances)
        tallies["refined"].match(detections, instances)
        first_gt = len(gts)
        for inst in instances:
            gts.append(GTInstance(record.scene_id, record.im_id, inst.obj_id, inst.R, inst.t_mm,
                                  max(inst.visib_fract, MIN_VISIB_FRACT), record.K_full, record.size_full,
                                  depth_full_mm))
        for gt_index, inst in enumerate(instances, start=first_gt):
            # the agents' way: the top-scoring detection of the object (they cannot tell which overlaps the truth)
            matched = next((d for d in detections if d.obj_id == inst.obj_id and d.score >= DETECTION_THRESHOLD), None)
            boxes = {"true_box": (inst.box_crop, 1.0),
                     "detected": (matched.box, matched.score) if matched is not None else None}
            for kind in ("true_box", "detected"):
                if boxes[kind] is None:
                    for mode in ("rgb", "depth"):
                        _count(refusals[f"{kind}_{mode}"], "no-detection")
                    continue
                box, score = boxes[kind]
                t0 = time.perf_counter()
                try:
                    poses = estimator.estimate_both(rgb, K, inst.obj_id, box, depth_work, score)
                except LearnedRefused as exc:
                    for mode in ("rgb", "depth"):
                        _count(refusals[f"{kind}_{mode}"], exc.cause)
                    continue
                times.append(time.perf_counter() - t0)
                for mode, pose in zip(("rgb", "depth"), poses):
                    assert pose is not None
                    estimates[f"{kind}_{mode}"].append((gt_index, Estimate(
                        record.scene_id, record.im_id, inst.obj_id, pose.score, pose.cam_T_obj[:3, :3],
                        pose.cam_T_obj[:3, 3] * 1000.0)))
    renderer = DepthRenderer()
    pose_ar, per_object, per_metric = {}, {}, {}
    for variant in POSE_VARIANTS:
        scores = evaluate_bop19(gts, [e for _, e in estimates[variant]], models, renderer=renderer, keep_errors=False)
        pose_ar[variant] = float(scores.ar)
        per_object[variant] = {int(o): float(s.ar) for o, s in scores.per_object.items()}
        per_metric[variant] = {"vsd": float(scores.ar_vsd), "mssd": float(scores.ar_mssd), "mspd": float(scores.ar_mspd)}
    refined, raw = tallies["refined"], tallies["raw"]
    return HeldoutScores(len(images), n_instances, refined.recall(), refined.ap(), pose_ar, per_object, refusals,
                         float(np.median(times)) if times else 0.0, raw.recall(), raw.ap(),
                         {f"{k}_median_s": float(np.median(v)) if v else 0.0 for k, v in detect_s.items()},
                         tuple(estimator.detect_widths), per_metric, tuple(estimator.crop_zooms),
                         gts if keep_estimates else None, estimates if keep_estimates else None)


def _count(tally: dict[str, int], cause: str) -> None:
    tally[cause] = tally.get(cause, 0) + 1


class _Tally:
    """Detections against true instances, per object: scores and hits for AP, hits above the threshold for recall."""

    def __init__(self, obj_ids: list[int]) -> None:
        self.scores: dict[int, list[float]] = {o: [] for o in obj_ids}
        self.hits: dict[int, list[bool]] = {o: [] for o in obj_ids}
        self.n_gt = {o: 0 for o in obj_ids}
        self.found = {o: 0 for o in obj_ids}

    def match(self, detections: list[Detection], instances: list[Any]) -> None:
        _match_detections(detections, instances, self.scores, self.hits, self.n_gt, self.found)

    def recall(self) -> dict[int, float]:
        return {o: self.found[o] / self.n_gt[o] if self.n_gt[o] else float("nan") for o in self.n_gt}

    def ap(self) -> dict[int, float]:
        return {o: average_precision(self.scores[o], self.hits[o], self.n_gt[o]) for o in self.n_gt}


def _match_detections(detections: list[Detection], instances: list[Any], det_scores: dict[int, list[float]],
                      det_hits: dict[int, list[bool]], n_gt: dict[int, int], found: dict[int, int]) -> None:
    """Greedy matching by score (VOC): each true instance takes the best detection of its object at IoU >= 0.5."""
    taken: set[int] = set()
    for inst in instances:
        n_gt[inst.obj_id] += 1
    for d in detections:  # best first
        best, best_iou = None, IOU
        for k, inst in enumerate(instances):
            if k in taken or inst.obj_id != d.obj_id:
                continue
            overlap = iou(d.box, inst.box_crop)
            if overlap >= best_iou:
                best, best_iou = k, overlap
        hit = best is not None
        if hit:
            taken.add(best)  # type: ignore[arg-type]
            if d.score >= DETECTION_THRESHOLD:
                found[d.obj_id] += 1
        if d.obj_id in det_scores:
            det_scores[d.obj_id].append(d.score)
            det_hits[d.obj_id].append(hit)

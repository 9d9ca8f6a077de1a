"""BOP19 Average Recall (AR_VSD, AR_MSSD, AR_MSPD and AR) of pose estimates against ground truth.

BOP units throughout: millimetres for models, translations and depth; pixels for MSPD.

The procedure is bop_toolkit's ``eval_bop19_pose.py`` (6D localisation, ``n_top = -1``):

1. Targets: GT instances with ``visib_fract >= 0.1``; per (scene, image, object) their number is
   the ``inst_count`` of BOP's ``test_targets_bop19.json``.
2. Per (scene, image, object) with targets, only the ``inst_count`` estimates with the highest
   scores are evaluated (stable sort: ties keep the input order); other estimates are ignored.
3. Errors of each evaluated estimate against every target GT of the same object in the image:
   VSD (delta 15 mm, tau 0.05..0.5 x diameter, step cost, bop19 visibility), MSSD and MSPD over
   the object's symmetries. As bop_toolkit: VSD is 1 without rendering when the projections of
   the bounding spheres do not overlap, MSSD is inf when the centres are a diameter or more apart.
4. For every correctness threshold separately (and every tau for VSD), estimates are matched
   greedily in descending score order: each one takes, among the not yet matched targets, the
   one with the lowest error, if that error is below the threshold (strictly; first GT wins ties).
   Thresholds: VSD error < 0.05..0.5; MSSD / diameter < 0.05..0.5; MSPD * 640 / width < 5..50.
5. Recall = matched targets / targets (0 with no targets). AR_metric = mean of the recalls over
   its thresholds (10 x 10 for VSD, 10 for MSSD and MSPD); AR = mean of the three.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import DataError
from brave6d.core.progress import format_table, progress
from brave6d.evaluation.metrics.bop_metrics import (
    MAX_SYM_DISC_STEP,
    MSPD_REFERENCE_WIDTH,
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VSD_DELTA_MM,
    VSD_TAUS,
    VSD_THRESHOLDS,
    Symmetries,
    mspd,
    mssd,
    overlapping_sphere_projections,
    symmetry_transformations,
    vsd_from_depths,
)
from brave6d.evaluation.metrics.depth_renderer import DepthRenderer

log = logging.getLogger(__name__)

METRICS: tuple[str, ...] = ("vsd", "mssd", "mspd")
DepthSource = NDArray[Any] | Callable[[], NDArray[Any]] | None


# ----------------------------------------------------------------------------- inputs
def _rotation(R: ArrayLike, what: str) -> NDArray[np.float64]:
    arr = np.asarray(R, dtype=np.float64)
    if arr.size != 9:
        raise DataError(f"{what}: R must have 9 values (3x3), got shape {arr.shape}")
    return arr.reshape(3, 3)


def _translation(t: ArrayLike, what: str) -> NDArray[np.float64]:
    arr = np.asarray(t, dtype=np.float64)
    if arr.size != 3:
        raise DataError(f"{what}: t must have 3 values (mm), got shape {arr.shape}")
    return arr.reshape(3)


@dataclass(frozen=True, eq=False)
class Estimate:
    """One pose estimate, a row of a BOP results CSV: ``x_cam = R @ x_model + t`` (t in mm).

    ``time`` is the run time of the method on the whole image in seconds (-1 = unknown).
    """

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    time: float = -1.0

    def __post_init__(self) -> None:
        what = f"estimate (scene {self.scene_id}, image {self.im_id}, object {self.obj_id})"
        object.__setattr__(self, "R", _rotation(self.R, what))
        object.__setattr__(self, "t", _translation(self.t, what))
        if not math.isfinite(float(self.score)):
            raise DataError(f"{what}: score must be finite, got {self.score}")
        object.__setattr__(self, "score", float(self.score))
        object.__setattr__(self, "time", float(self.time))


@dataclass(frozen=True, eq=False)
class GTInstance:
    """One ground-truth object instance in one test image (BOP ``scene_gt`` + ``scene_gt_info``
    + ``scene_camera`` entries): pose (t in mm), visible fraction, camera matrix ``K``,
    ``image_size = (width, height)`` and the test depth image in mm (an array, a zero-argument
    loader returning one, or None when VSD is not evaluated). All instances of one image must
    share ``K`` and ``image_size``; the depth is taken from the first instance that has one.
    The instance's index among its image's instances (input order) is its ``gt_id``.
    """

    scene_id: int
    im_id: int
    obj_id: int
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    visib_fract: float
    K: NDArray[np.float64]
    image_size: tuple[int, int]
    depth: DepthSource = None

    def __post_init__(self) -> None:
        what = f"GT (scene {self.scene_id}, image {self.im_id}, object {self.obj_id})"
        object.__setattr__(self, "R", _rotation(self.R, what))
        object.__setattr__(self, "t", _translation(self.t, what))
        k = np.asarray(self.K, dtype=np.float64)
        if k.size != 9:
            raise DataError(f"{what}: K must have 9 values, got shape {k.shape}")
        k = k.reshape(3, 3)
        if not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise DataError(f"{what}: K must be finite with positive focal lengths, got {k.tolist()}")
        object.__setattr__(self, "K", k)
        w, h = (int(x) for x in self.image_size)
        if w < 1 or h < 1:
            raise DataError(f"{what}: image size must be positive, got {self.image_size}")
        object.__setattr__(self, "image_size", (w, h))
        vf = float(self.visib_fract)
        if not math.isfinite(vf):
            raise DataError(f"{what}: visib_fract must be finite, got {self.visib_fract}")
        object.__setattr__(self, "visib_fract", vf)

    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """An object model in BOP units: points (N, 3) mm (the vertices of the evaluation model),
    faces (M, 3) for VSD rendering, diameter mm, and symmetries as in ``models_info.json``."""

    obj_id: int
    points: NDArray[np.float64]
    diameter: float
    faces: NDArray[np.int64] | None = None
    symmetries_discrete: tuple[tuple[float, ...], ...] = ()
    symmetries_continuous: tuple[Mapping[str, Any], ...] = ()
    _sym_cache: dict[float, Symmetries] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        what = f"object {self.obj_id}"
        pts = np.asarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or not np.all(np.isfinite(pts)):
            raise DataError(f"{what}: points must be a non-empty finite (N, 3) array (mm), got shape {pts.shape}")
        object.__setattr__(self, "points", pts)
        d = float(self.diameter)
        if not (d > 0 and math.isfinite(d)):
            raise DataError(f"{what}: diameter must be positive (mm), got {self.diameter}")
        object.__setattr__(self, "diameter", d)
        if self.faces is not None:
            f = np.asarray(self.faces)
            if f.ndim != 2 or f.shape[1] != 3:
                raise DataError(f"{what}: faces must be (M, 3) vertex indices, got shape {f.shape}")
            object.__setattr__(self, "faces", f.astype(np.int64))
        object.__setattr__(self, "symmetries_discrete", tuple(tuple(float(x) for x in np.ravel(s)) for s in self.symmetries_discrete))
        object.__setattr__(self, "symmetries_continuous", tuple(dict(s) for s in self.symmetries_continuous))
        try:
            self.symmetries()
        except ValueError as exc:
            raise DataError(f"{what}: {exc}") from None

    @classmethod
    def from_models_info(
        cls, obj_id: int, points: ArrayLike, info: Mapping[str, Any], faces: ArrayLike | None = None
    ) -> ObjectModel:
        """From a ``models_info.json`` entry (diameter, optional symmetries) and the model's mesh."""
        if "diameter" not in info:
            raise DataError(f"object {obj_id}: models_info entry has no 'diameter'")
        return cls(
            obj_id=int(obj_id),
            points=np.asarray(points, dtype=np.float64),
            diameter=float(info["diameter"]),
            faces=None if faces is None else np.asarray(faces),
            symmetries_discrete=tuple(info.get("symmetries_discrete", []) or []),
            symmetries_continuous=tuple(info.get("symmetries_continuous", []) or []),
        )

    def models_info(self) -> dict[str, Any]:
        """The symmetry/diameter part of this model's ``models_info.json`` entry."""
        out: dict[str, Any] = {"diameter": self.diameter}
        if self.symmetries_discrete:
            out["symmetries_discrete"] = [list(s) for s in self.symmetries_discrete]
        if self.symmetries_continuous:
            out["symmetries_continuous"] = [dict(s) for s in self.symmetries_continuous]
        return out

    def symmetries(self, max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> Symmetries:
        """Symmetry transformations (identity first), cached per discretisation step."""
        key = float(max_sym_disc_step)
        if key not in self._sym_cache:
            self._sym_cache[key] = symmetry_transformations(self.models_info(), key)
        return self._sym_cache[key]


@dataclass(frozen=True)
class EvalConfig:
    """Parameters of the evaluation; the defaults are BOP19's."""

    metrics: tuple[str, ...] = METRICS
    visib_gt_min: float = 0.1
    vsd_delta: float = VSD_DELTA_MM
    vsd_taus: tuple[float, ...] = VSD_TAUS
    vsd_thresholds: tuple[float, ...] = VSD_THRESHOLDS
    mssd_thresholds: tuple[float, ...] = MSSD_THRESHOLDS
    mspd_thresholds: tuple[float, ...] = MSPD_THRESHOLDS
    max_sym_disc_step: float = MAX_SYM_DISC_STEP
    #: Estimates evaluated per (scene, image, object): -1 = as many as targets (BOP19), 0 = all, k = top k.
    n_top: int = -1

    def __post_init__(self) -> None:
        unknown = [m for m in self.metrics if m not in METRICS]
        if unknown or not self.metrics:
            raise ValueError(f"metrics must be a non-empty subset of {METRICS}, got {self.metrics}")
        for name in ("vsd_taus", "vsd_thresholds", "mssd_thresholds", "mspd_thresholds"):
            if len(getattr(self, name)) == 0:
                raise ValueError(f"{name} must not be empty")


# ----------------------------------------------------------------------------- outputs
@dataclass
class EstimateErrors:
    """Errors of one evaluated estimate against the target GTs of its object in its image.

    ``gt_ids`` index the image's GT instances; ``vsd`` is (G, n_taus), ``mssd`` (G,) in mm and
    ``mspd`` (G,) in pixels of the actual image (not scaled to 640 px); absent metrics are None.
    """

    scene_id: int
    im_id: int
    obj_id: int
    est_index: int
    score: float
    gt_ids: tuple[int, ...]
    vsd: NDArray[np.float64] | None = None
    mssd: NDArray[np.float64] | None = None
    mspd: NDArray[np.float64] | None = None


@dataclass
class MetricScores:
    """Recall of one metric per threshold (VSD: rows = taus, columns = thresholds) and its AR."""

    name: str
    ar: float
    recall: NDArray[np.float64]
    thresholds: tuple[float, ...]
    taus: tuple[float, ...] | None = None
    tp_counts: NDArray[np.int64] | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "ar": self.ar,
            "thresholds": list(self.thresholds),
            "recall": self.recall.tolist(),
        }
        if self.taus is not None:
            out["taus"] = list(self.taus)
        if self.tp_counts is not None:
            out["tp_counts"] = self.tp_counts.tolist()
        return out


@dataclass
class ObjectScores:
    """Per-object breakdown: its targets and its AR per metric (recall over its own targets)."""

    obj_id: int
    n_targets: int
    ar: float
    ar_per_metric: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        return {"obj_id": self.obj_id, "n_targets": self.n_targets, "ar": self.ar, **{f"ar_{k}": v for k, v in self.ar_per_metric.items()}}


@dataclass
class BopScores:
    """Result of :func:`evaluate_bop19`.

    ``ar`` is the mean of the ARs of the evaluated metrics: BOP's AR when all three were
    evaluated (``metrics == ('vsd', 'mssd', 'mspd')``). ``average_time_per_image`` is -1 when
    any evaluated image lacks a time.
    """

    ar: float
    metrics: dict[str, MetricScores]
    n_targets: int
    n_gt: int
    n_images: int
    n_estimates: int
    n_estimates_evaluated: int
    per_object: dict[int, ObjectScores]
    average_time_per_image: float
    config: EvalConfig
    errors: list[EstimateErrors] = field(default_factory=list, repr=False)

    @property
    def ar_vsd(self) -> float | None:
        return self.metrics["vsd"].ar if "vsd" in self.metrics else None

    @property
    def ar_mssd(self) -> float | None:
        return self.metrics["mssd"].ar if "mssd" in self.metrics else None

    @property
    def ar_mspd(self) -> float | None:
        return self.metrics["mspd"].ar if "mspd" in self.metrics else None

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (for ``brave6d.core.atomic.atomic_write_json``); omits per-estimate errors."""
        return {
            "ar": self.ar,
            "ar_vsd": self.ar_vsd,
            "ar_mssd": self.ar_mssd,
            "ar_mspd": self.ar_mspd,
            "metrics_evaluated": list(self.metrics),
            "n_targets": self.n_targets,
            "n_gt": self.n_gt,
            "n_images": self.n_images,
            "n_estimates": self.n_estimates,
            "n_estimates_evaluated": self.n_estimates_evaluated,
            "average_time_per_image": self.average_time_per_image,
            "per_metric": {k: v.to_json() for k, v in self.metrics.items()},
            "per_object": {str(k): v.to_json() for k, v in sorted(self.per_object.items())},
            "config": {
                "visib_gt_min": self.config.visib_gt_min,
                "vsd_delta_mm": self.config.vsd_delta,
                "max_sym_disc_step": self.config.max_sym_disc_step,
                "n_top": self.config.n_top,
            },
        }

    def table(self) -> str:
        """Plain-text table: one row per object and one for all objects."""
        names = list(self.metrics)
        rows: list[list[Any]] = []
        for obj_id, s in sorted(self.per_object.items()):
            rows.append([str(obj_id), s.n_targets, *(s.ar_per_metric[m] for m in names), s.ar])
        rows.append(["all", self.n_targets, *(self.metrics[m].ar for m in names), self.ar])
        return format_table(["object", "targets", *(f"AR_{m.upper()}" for m in names), "AR"], rows)


# ----------------------------------------------------------------------------- matching
def greedy_match(errors: ArrayLike, thresholds: ArrayLike) -> NDArray[np.int64]:
    """Greedy matching of estimates to GTs, independently for every threshold (bop_toolkit's
    ``match_poses``).

    ``errors`` is (E, G, T): estimates already sorted by descending score, G candidate GTs,
    T thresholds (one error per threshold column, e.g. VSD per tau). Each estimate in turn takes
    the not yet matched GT with the lowest error if that error is strictly below the threshold;
    among equal errors the lower GT index wins. NaN errors never match. Returns (E, T) GT
    indices, -1 = unmatched.
    """
    err = np.asarray(errors, dtype=np.float64)
    th = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    if err.ndim != 3 or err.shape[2] != th.size:
        raise ValueError(f"errors must be (E, G, T) with T = {th.size} thresholds, got shape {err.shape}")
    n_est, n_gt, n_th = err.shape
    err = np.where(np.isnan(err), np.inf, err)
    out = np.full((n_est, n_th), -1, dtype=np.int64)
    if n_gt == 0:
        return out
    taken = np.zeros((n_gt, n_th), dtype=bool)
    cols = np.arange(n_th)
    for e in range(n_est):
        cur = np.where(taken, np.inf, err[e])
        best = np.argmin(cur, axis=0)
        ok = cur[best, cols] < th
        out[e, ok] = best[ok]
        taken[best[ok], cols[ok]] = True
    return out


# ----------------------------------------------------------------------------- evaluation
@dataclass
class _Image:
    scene_id: int
    im_id: int
    K: NDArray[np.float64]
    width: int
    height: int
    depth: DepthSource
    gts: list[GTInstance]


def _group_images(gts: Iterable[GTInstance]) -> dict[tuple[int, int], _Image]:
    images: dict[tuple[int, int], _Image] = {}
    for gt in gts:
        key = (int(gt.scene_id), int(gt.im_id))
        img = images.get(key)
        if img is None:
            images[key] = _Image(key[0], key[1], gt.K, gt.width, gt.height, gt.depth, [gt])
            continue
        if gt.image_size != (img.width, img.height) or not np.allclose(gt.K, img.K, rtol=0, atol=1e-9):
            raise DataError(
                f"GT of scene {key[0]} image {key[1]}: instances disagree on K or image size "
                f"({img.K.tolist()} {img.width}x{img.height} vs {gt.K.tolist()} {gt.width}x{gt.height})"
            )
        if img.depth is None and gt.depth is not None:
            img.depth = gt.depth
        img.gts.append(gt)
    return images


def _load_depth(img: _Image) -> NDArray[np.float64]:
    src = img.depth
    where = f"scene {img.scene_id} image {img.im_id}"
    if src is None:
        raise DataError(f"{where}: VSD needs the test depth image, but the GT has none")
    depth = src() if callable(src) else src
    arr = np.asarray(depth, dtype=np.float64)
    if arr.shape != (img.height, img.width):
        raise DataError(f"{where}: depth image is {arr.shape[1::-1]} (w x h), expected {img.width}x{img.height}")
    return arr


def _select_estimates(ests: list[tuple[int, Estimate]], inst_count: int, n_top: int) -> list[tuple[int, Estimate]]:
    ordered = sorted(ests, key=lambda ie: ie[1].score, reverse=True)  # stable: ties keep input order
    if n_top == -1:
        return ordered[:inst_count]
    if n_top == 0:
        return ordered
    return ordered[:n_top]


def _mean(values: NDArray[np.float64]) -> float:
    return float(np.mean(values)) if values.size else 0.0


def evaluate_bop19(
    gts: Sequence[GTInstance],
    estimates: Sequence[Estimate],
    models: Mapping[int, ObjectModel],
    config: EvalConfig | None = None,
    renderer: DepthRenderer | None = None,
    show_progress: bool = False,
    keep_errors: bool = True,
) -> BopScores:
    """BOP19 Average Recall of ``estimates`` against ``gts`` (all images of a test set).

    ``models`` maps every object id with targets to its :class:`ObjectModel` (VSD needs faces).
    A ``renderer`` that already holds the models may be passed to reuse it. Estimates for images
    or objects without targets are ignored, as in BOP. See the module docstring for the rules.
    """
    cfg = config or EvalConfig()
    images = _group_images(gts)
    need_vsd = "vsd" in cfg.metrics

    # Estimates grouped by (scene, image, object), input order kept; run times per image.
    est_groups: dict[tuple[int, int, int], list[tuple[int, Estimate]]] = {}
    image_times: dict[tuple[int, int], list[float]] = {}
    for i, est in enumerate(estimates):
        est_groups.setdefault((int(est.scene_id), int(est.im_id), int(est.obj_id)), []).append((i, est))
        image_times.setdefault((int(est.scene_id), int(est.im_id)), []).append(est.time)

    taus = tuple(cfg.vsd_taus)
    n_taus = len(taus)
    th = {"vsd": np.tile(np.asarray(cfg.vsd_thresholds, dtype=np.float64), n_taus),
          "mssd": np.asarray(cfg.mssd_thresholds, dtype=np.float64),
          "mspd": np.asarray(cfg.mspd_thresholds, dtype=np.float64)}
    n_cols = {m: th[m].size for m in METRICS}

    targets_per_obj: dict[int, int] = {}
    tps_per_obj: dict[str, dict[int, NDArray[np.int64]]] = {m: {} for m in cfg.metrics}
    all_errors: list[EstimateErrors] = []
    n_evaluated = 0
    ren = renderer

    it: Iterable[_Image] = images.values()
    if show_progress:
        it = progress(it, total=len(images), desc="BOP errors", unit="image")
    for img in it:
        depth_test: NDArray[np.float64] | None = None
        gt_depth_cache: dict[int, NDArray[np.float64]] = {}
        # Targets of this image: valid GTs per object, gt_ids in input order.
        valid: dict[int, list[int]] = {}
        for gid, gt in enumerate(img.gts):
            if gt.visib_fract >= cfg.visib_gt_min:
                valid.setdefault(int(gt.obj_id), []).append(gid)
        for obj_id, gt_ids in valid.items():
            targets_per_obj[obj_id] = targets_per_obj.get(obj_id, 0) + len(gt_ids)
            for m in cfg.metrics:
                tps_per_obj[m].setdefault(obj_id, np.zeros(n_cols[m], dtype=np.int64))
            group = est_groups.get((img.scene_id, img.im_id, obj_id), [])
            selected = _select_estimates(group, len(gt_ids), cfg.n_top)
            if not selected:
                continue
            model = models.get(obj_id)
            if model is None:
                raise DataError(f"no object model for object {obj_id} (scene {img.scene_id}, image {img.im_id})")
            n_evaluated += len(selected)
            syms = model.symmetries(cfg.max_sym_disc_step) if ("mssd" in cfg.metrics or "mspd" in cfg.metrics) else None
            if need_vsd:
                if depth_test is None:
                    depth_test = _load_depth(img)
                if ren is None:
                    ren = DepthRenderer()
                if obj_id not in ren:
                    if model.faces is None:
                        raise DataError(f"object {obj_id}: VSD needs the model's faces, the model has none")
                    ren.add_object(obj_id, model.points, model.faces)

            n_e, n_g = len(selected), len(gt_ids)
            err = {m: np.full((n_e, n_g, n_cols[m]), np.inf) for m in cfg.metrics}
            for ei, (est_index, est) in enumerate(selected):
                rec = EstimateErrors(img.scene_id, img.im_id, obj_id, est_index, est.score, tuple(gt_ids))
                depth_est: NDArray[np.float64] | None = None
                if need_vsd:
                    rec.vsd = np.ones((n_g, n_taus))
                if "mssd" in cfg.metrics:
                    rec.mssd = np.full(n_g, np.inf)
                if "mspd" in cfg.metrics:
                    rec.mspd = np.full(n_g, np.inf)
                for gi, gid in enumerate(gt_ids):
                    gt = img.gts[gid]
                    if rec.mssd is not None:
                        if float(np.linalg.norm(est.t - gt.t)) < model.diameter:
                            rec.mssd[gi] = mssd(est.R, est.t, gt.R, gt.t, model.points, syms)
                        err["mssd"][ei, gi, :] = rec.mssd[gi] / model.diameter
                    if rec.mspd is not None:
                        rec.mspd[gi] = mspd(est.R, est.t, gt.R, gt.t, img.K, model.points, syms)
                        err["mspd"][ei, gi, :] = rec.mspd[gi] * (MSPD_REFERENCE_WIDTH / img.width)
                    if rec.vsd is not None and ren is not None and depth_test is not None:
                        if overlapping_sphere_projections(0.5 * model.diameter, est.t, gt.t):
                            if depth_est is None:
                                depth_est = ren.render(obj_id, est.R, est.t, img.K, img.width, img.height)
                            if gid not in gt_depth_cache:
                                gt_depth_cache[gid] = ren.render(obj_id, gt.R, gt.t, img.K, img.width, img.height)
                            rec.vsd[gi] = vsd_from_depths(
                                depth_est, gt_depth_cache[gid], depth_test, img.K, cfg.vsd_delta, taus,
                                True, model.diameter, "step",
                            )
                        err["vsd"][ei, gi, :] = np.repeat(rec.vsd[gi], len(cfg.vsd_thresholds))
                if keep_errors:
                    all_errors.append(rec)
            for m in cfg.metrics:
                matched = greedy_match(err[m], th[m])
                tps_per_obj[m][obj_id] += np.count_nonzero(matched >= 0, axis=0)

    # Scores.
    n_targets = int(sum(targets_per_obj.values()))
    metric_scores: dict[str, MetricScores] = {}
    for m in cfg.metrics:
        tp = np.zeros(n_cols[m], dtype=np.int64)
        for v in tps_per_obj[m].values():
            tp += v
        recall = tp / n_targets if n_targets > 0 else np.zeros(n_cols[m])
        if m == "vsd":
            shape = (n_taus, len(cfg.vsd_thresholds))
            metric_scores[m] = MetricScores(m, _mean(recall), recall.reshape(shape), tuple(cfg.vsd_thresholds), taus,
                                            tp.reshape(shape))
        else:
            ths = tuple(cfg.mssd_thresholds if m == "mssd" else cfg.mspd_thresholds)
            metric_scores[m] = MetricScores(m, _mean(recall), recall, ths, None, tp)
    ar = float(np.mean([s.ar for s in metric_scores.values()]))

    per_object: dict[int, ObjectScores] = {}
    for obj_id, n in sorted(targets_per_obj.items()):
        per_m = {m: (_mean(tps_per_obj[m][obj_id] / n) if n > 0 else 0.0) for m in cfg.metrics}
        per_object[obj_id] = ObjectScores(obj_id, n, float(np.mean(list(per_m.values()))), per_m)

    return BopScores(
        ar=ar,
        metrics=metric_scores,
        n_targets=n_targets,
        n_gt=sum(len(img.gts) for img in images.values()),
        n_images=len(images),
        n_estimates=len(estimates),
        n_estimates_evaluated=n_evaluated,
        per_object=per_object,
        average_time_per_image=_average_time(image_times),
        config=cfg,
        errors=all_errors,
    )


def _average_time(image_times: Mapping[tuple[int, int], list[float]]) -> float:
    """Mean per-image run time over all estimates, as BOP: -1 when any time is negative (unknown);
    the times of one image should agree (BOP refuses > 1 ms apart; here a warning and the largest is used)."""
    if not image_times:
        return -1.0
    per_image = []
    for (scene_id, im_id), times in image_times.items():
        if any(t < 0 for t in times):
            return -1.0
        if max(times) - min(times) > 0.001:
            log.warning("scene %d image %d: estimates report different run times (%.4f..%.4f s); using the largest",
                        scene_id, im_id, min(times), max(times))
        per_image.append(max(times))
    return float(np.mean(per_image))

"""The learned estimator at work: detect, crop (at a few zooms), regress coordinates, one robust PnP
over every crop's correspondences, the distance from the mask's area where the model's mesh is known (:mod:`~brave6d.evaluation.learned.silhouette`),
optionally refine the translation with a depth image.

:class:`LearnedEstimator` takes any RGB image and its K (resized to the model's working width
internally) and answers in the image's own pixels and camera frame. Every failure is a
:class:`LearnedRefused` whose ``cause`` is one of :data:`REFUSAL_CAUSES`; a pose it returns is
finite, in front of the camera and rigid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.evaluation.estimators.protocol import Detection, EstimatorRefused
from brave6d.evaluation.learned.crops import box_crop, crop_size, crop_to_image, iou, normalise, warp_rgb
from brave6d.evaluation.learned.data import resize_to_width
from brave6d.evaluation.learned.model_file import LearnedModel, read_model
from brave6d.evaluation.learned.refine import ICP_MAX_POINTS, Surface, box_points, thinned, icp_refine, \
    sample_surface
from brave6d.evaluation.learned.silhouette import Silhouette, mask_area_scale

Array = NDArray[np.float64]

#: Why an estimate can fail, as :attr:`LearnedRefused.cause` names it.
REFUSAL_CAUSES = ("unknown-object", "no-detection", "few-correspondences", "degenerate-correspondences",
                  "pnp-failed", "bad-input")
#: PnP needs at least this many visible pixels with coordinates.
MIN_CORRESPONDENCES = 6
#: Second singular value of the centred 3D (and 2D) points, relative to the first, below which
#: they are taken as collinear.
MIN_SPREAD = 0.05
#: Detections one image gives at most.
MAX_DETECTIONS = 20
#: A visible mask of fewer cells than this does not refine a detection's box.
MIN_MASK_CELLS = 3
#: The detector looks at each image at these multiples of its training width (never wider than the
#: crops' source) and keeps the best of overlapping detections. (1.0, 1.375) lets a small, far object
#: cover more heatmap cells (held-out recall and AP up) while the training width keeps near objects
#: within the sizes it trained on, for 3x the detection time; the learned agents score the same
#: either way, so the default is one pass. Priced in docs/BENCHMARKS.md
#: (benchmarks/learned_detect_scale.py).
DETECT_SCALES: tuple[float, ...] = (1.0,)
#: The coordinate net looks at a box's crop at these zooms (the crop's side over the box's padded
#: side) and one robust PnP fits the correspondences of all of them (the mask-area distance is the
#: geometric mean of theirs): the net's errors at different scales partly cancel, which pins the
#: rotation down (test-time augmentation, as GDR-Net's dynamic zoom-in trains for). (1.0,): one
#: crop, a third of the time. Priced in docs/BENCHMARKS.md (benchmarks/learned_rgb_distance.py).
CROP_ZOOMS: tuple[float, ...] = (1.0, 0.75, 1.25)
#: Robust PnP's inlier threshold (MSAC's truncation, the Cauchy loss's scale), in the coordinate
#: net's output cells of the zoom-1 crop (a cell spans 3 px of a far object's crop and 15 of a near
#: one's: a threshold in pixels would be loose on one and strict on the other). Priced in
#: docs/BENCHMARKS.md.
PNP_REPROJECTION_CELLS = 1.5
#: Robust PnP's fixed hypothesis set: this many seeded minimal samples of ``PNP_SAMPLE``
#: correspondences each (EPnP), every one scored (no adaptive stopping: the same samples whatever
#: the inputs' values). Priced in docs/BENCHMARKS.md.
PNP_HYPOTHESES = 100
PNP_SAMPLE = 6
PNP_SEED = 0
#: At most this many Levenberg-Marquardt steps of the robust least squares that refines the best hypothesis.
PNP_REFINE_STEPS = 100


def pnp_method() -> str:
    """What :func:`solve_pnp` does, as the held-out figures record it (a card scored by another PnP
    is stale): fixed hypotheses x sample size, MSAC score, Cauchy-loss refinement."""
    return f"msac-{PNP_HYPOTHESES}x{PNP_SAMPLE}-seed{PNP_SEED}+cauchy-lm"
#: Detections of one object overlapping a better one at least this much (IoU) are dropped.
NMS_IOU = 0.5
#: Beside a narrower pass, a wider one keeps only detections whose box (geometric mean of w, h)
#: measures at most this many pixels at the training width: the small objects its extra pixels
#: help, not the near ones grown past the sizes the detector trained on (SNIP's valid ranges).
UPSCALED_MAX_BOX_PX = 24.0


class LearnedRefused(EstimatorRefused):
    """The learned estimator cannot give a pose; ``cause`` is one of :data:`REFUSAL_CAUSES`."""


@dataclass(frozen=True)
class LearnedPose:
    """A pose (``cam_T_obj``, metres, the input image's camera frame), its score, the PnP inliers
    and correspondences, how the mask's area set its distance (``mask_scale``: the factor applied
    to PnP's t; None: PnP's distance kept) and how depth refined it (``depth_scale``: the factor
    applied to t; ``icp``: ICP onto the model's surface kept its result)."""

    cam_T_obj: Array
    score: float
    inliers: int
    correspondences: int
    depth_scale: float | None = None
    icp: bool = False  # depth refined the pose by ICP too
    fit: float | None = None  # fraction of the box's depth points on the posed surface (with depth and a surface)
    mask_scale: float | None = None


class LearnedEstimator:
    """A trained model ready to detect and estimate (see the module docstring)."""

    #: The RGB-only distance from the mask's area against the model's silhouette
    #: (:mod:`~brave6d.evaluation.learned.silhouette`; needs the mesh, given by :meth:`set_surface`);
    #: False: PnP's own distance. Set on an instance, or on the class for every estimator (what
    #: ``benchmarks/learned_rgb_distance.py`` does to price it in the agents).
    mask_area_distance: bool = True
    #: :data:`CROP_ZOOMS` ((1.0,): one crop per estimate); on an instance or the class, as above.
    crop_zooms: tuple[float, ...] = CROP_ZOOMS

    def __init__(self, model: LearnedModel, device: str = "cpu") -> None:
        import torch

        from brave6d.evaluation.learned.networks import CoordinateNet, Detector

        self._init_state(model)
        self.device = torch.device(device)
        classes = len(model.objects)
        self.detector = Detector(classes, int(self.preset["detector_width"]))
        self.detector.load_state_dict(model.detector_state)
        self.pose = CoordinateNet(classes, int(self.preset["pose_width"]))
        self.pose.load_state_dict(model.pose_state)
        self.detector.to(self.device).eval()
        self.pose.to(self.device).eval()

    def _init_state(self, model: LearnedModel) -> None:
        """What the estimator keeps besides its networks (the ONNX Runtime estimator shares it)."""
        self.model = model
        self.preset = model.preset
        #: which library runs the two networks
        self.runtime = "torch"
        self._by_class = {o.class_index: o for o in model.objects.values()}
        self.surfaces: dict[int, Surface] = {}
        self.silhouettes: dict[int, Silhouette] = {}
        #: depth points ICP uses at most (None: all; what it costs and buys: docs/BENCHMARKS.md)
        self.icp_max_points: int | None = ICP_MAX_POINTS
        #: the detector's input widths over the training width (:data:`DETECT_SCALES`; (1.0,): as trained)
        self.detect_scales: tuple[float, ...] = DETECT_SCALES
        #: :data:`UPSCALED_MAX_BOX_PX` (math.inf: an upscaled pass keeps every size)
        self.upscaled_max_box_px: float = UPSCALED_MAX_BOX_PX

    @classmethod
    def load(cls, model_dir: Path | str, device: str = "cpu", models_dir: Path | str | None = None) -> LearnedEstimator:
        """The estimator of ``model_dir/model.pt``; ``models_dir`` (a BOP models folder) gives it the
        surfaces the depth refinement fits (agents give them with :meth:`set_surface`)."""
        estimator = cls(read_model(model_dir), device)
        if models_dir is not None:
            estimator.add_surfaces(models_dir)
        return estimator

    def add_surfaces(self, models_dir: Path | str) -> None:
        """:meth:`set_surface` of every object it knows from a BOP models folder."""
        from brave6d.evaluation.metrics import load_models

        for obj_id, m in load_models(models_dir, self.obj_ids).items():
            if m.faces is not None:
                self.set_surface(obj_id, m.points / 1000.0, m.faces)

    def set_surface(self, obj_id: int, vertices_m: Array, faces: NDArray[np.int64]) -> None:
        """The mesh of ``obj_id`` (metres, model frame): with it the RGB-only distance comes from the
        mask's area and depth refines the pose by ICP too."""
        self._check_object(obj_id)
        self.silhouettes[int(obj_id)] = Silhouette(np.asarray(vertices_m, dtype=np.float64),
                                                   np.asarray(faces, dtype=np.int64))
        self.surfaces[int(obj_id)] = sample_surface(vertices_m, faces, self.model.objects[int(obj_id)].diameter_mm / 1000.0)

    @property
    def obj_ids(self) -> list[int]:
        return self.model.classes

    @property
    def crop_source_width(self) -> int:
        """Width of the images the coordinate net's crops come from (the learned agents' episode width)."""
        return int(self.preset.get("crop_source_width", self.preset["work_width"]))

    @property
    def detect_widths(self) -> list[int]:
        """Widths of the images the detector looks at: the training width times each of
        :attr:`detect_scales`, at most the crops' source width (upsampling past the camera's own
        pixels adds nothing), each once."""
        scales = tuple(self.detect_scales)
        if not scales or not all(math.isfinite(x) and x > 0 for x in scales):
            raise BraveError(f"learned estimator: detect_scales must be positive finite numbers, got {scales}")
        width = int(self.preset["work_width"])
        widths = [max(64, min(round(width * x), max(width, self.crop_source_width))) for x in scales]
        return sorted(set(widths))

    def _work(self, rgb: NDArray[np.uint8], K: Array, width: int | None = None) -> tuple[NDArray[np.uint8], Array, float]:
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or min(rgb.shape[:2]) < 16:
            raise LearnedRefused("bad-input", f"learned estimator: expected an 8-bit RGB image of at least 16x16, "
                                              f"got {rgb.dtype} {rgb.shape}")
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise LearnedRefused("bad-input", "learned estimator: K must be a finite 3x3 matrix with positive focal "
                                              "lengths")
        return resize_to_width(rgb, K, int(self.preset["work_width"]) if width is None else width)

    def detect(self, rgb: NDArray[np.uint8], K: Array, min_score: float = 0.05,
               obj_id: int | None = None) -> list[Detection]:
        """The detections scoring at least ``min_score`` (of ``obj_id`` only, when given), best first,
        at most 20 (boxes in ``rgb``'s pixels): one detector pass per width of :attr:`detect_widths`,
        a detection overlapping a better one of its object by :data:`NMS_IOU` or more dropped."""
        base, widths = int(self.preset["work_width"]), self.detect_widths
        small = self.upscaled_max_box_px * (np.shape(rgb)[1] if np.ndim(rgb) >= 2 else base) / base  # input pixels
        found = []
        for width in widths:
            limit = small if width > widths[0] else math.inf
            found += [d for d in self._detect_at(rgb, K, width, min_score, obj_id) if d.size_px <= limit]
        found.sort(key=lambda d: -d.score)
        kept: list[Detection] = []
        for d in found:
            if all(k.obj_id != d.obj_id or iou(k.box, d.box) < NMS_IOU for k in kept):
                kept.append(d)
                if len(kept) == MAX_DETECTIONS:
                    break
        return kept

    def _detect_at(self, rgb: NDArray[np.uint8], K: Array, width: int, min_score: float,
                   obj_id: int | None) -> list[Detection]:
        """One detector pass on ``rgb`` resized to ``width``: its heatmap peaks (best first, at most 20)."""
        work, _, s = self._work(rgb, K, width)
        idx, scores, size, offset, stride = self._detector_peaks(work, min_score, obj_id)
        out = []
        for (c, gy, gx), score in zip(idx, scores):
            cx = (gx + offset[0, gy, gx]) * stride
            cy = (gy + offset[1, gy, gx]) * stride
            w, h = (math.exp(float(np.clip(v, -5.0, 8.0))) for v in size[:, gy, gx])
            box = ((cx - w / 2) / s, (cy - h / 2) / s, (cx + w / 2) / s, (cy + h / 2) / s)
            if all(math.isfinite(b) for b in box):
                out.append(Detection(self._by_class[int(c)].obj_id, box, float(score)))
        return out

    def _detector_peaks(self, work: NDArray[np.uint8], min_score: float, obj_id: int | None
                        ) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], int]:
        """The detector on the work image: the heatmap's peaks (class, row, column; best first, at most
        20), their scores, the box size and offset maps (2, H, W) and the maps' stride. (torch here;
        ``onnx_export.OnnxEstimator`` does the same in NumPy on ONNX Runtime's maps.)"""
        import torch
        from torch.nn import functional as F

        from brave6d.evaluation.learned.networks import DETECTOR_STRIDE

        with torch.no_grad():
            x = torch.from_numpy(normalise(work)[None]).to(self.device)
            heat, size, offset = self.detector(x)
            p = torch.sigmoid(heat)[0]
            if obj_id is not None:
                keep = torch.zeros_like(p[:, :1, :1])
                keep[self.model.objects[int(obj_id)].class_index] = 1.0
                p = p * keep
            peaks = (p == F.max_pool2d(p[None], 3, 1, 1)[0]) & (p >= min_score)
            scores = p[peaks]
            order = torch.argsort(scores, descending=True)[:MAX_DETECTIONS]
            idx = peaks.nonzero()[order].cpu().numpy()
            scores = scores[order].cpu().numpy()
            size, offset = size[0].cpu().numpy(), offset[0].cpu().numpy()
        return idx, scores, size, offset, DETECTOR_STRIDE

    def best_detection(self, rgb: NDArray[np.uint8], K: Array, obj_id: int, min_score: float = 0.05,
                       refine: bool = True) -> Detection:
        """The highest-scoring detection of ``obj_id`` (refused naming the cause when there is none),
        its box refined by :meth:`refine_box` unless ``refine`` is False."""
        self._check_object(obj_id)
        found = self.detect(rgb, K, min_score, obj_id)
        if not found:
            raise LearnedRefused("no-detection", f"learned estimator: no detection of object {obj_id} scoring "
                                                 f">= {min_score}")
        return self.refine_box(rgb, K, found[0]) if refine else found[0]

    def refine_box(self, rgb: NDArray[np.uint8], K: Array, detection: Detection) -> Detection:
        """``detection`` with its box replaced by the extent of the coordinate net's visible mask on
        the detection's crop (a second stage, as a two-stage detector's box head: the detector's box
        of a 10-20 px object is a few pixels off, the mask's edges are not). A mask that reaches the
        crop's border (the object may go on) is looked at once more around the grown box; a mask of
        fewer than :data:`MIN_MASK_CELLS` cells leaves the box as it was."""
        box = detection.box
        for _ in range(2):
            crop = self._crop_outputs(rgb, K, detection.obj_id, box)
            ys, xs = np.nonzero(crop.visible)
            n = crop.visible.shape[-1]
            if len(xs) < MIN_MASK_CELLS:
                break
            cell = crop.side / n  # work pixels per mask cell
            (x0, y0), (x1, y1) = crop_to_image(np.array([[xs.min(), ys.min()], [xs.max(), ys.max()]], dtype=np.float64),
                                               crop.centre, crop.side, n)
            grown = tuple(float(v) / crop.scale for v in (x0 + 0.5 - cell / 2, y0 + 0.5 - cell / 2,
                                                          x1 + 0.5 + cell / 2, y1 + 0.5 + cell / 2))
            if not all(math.isfinite(b) for b in grown):
                break
            box = grown  # type: ignore[assignment]
            if xs.min() > 0 and ys.min() > 0 and xs.max() < n - 1 and ys.max() < n - 1:
                break
        return Detection(detection.obj_id, box, detection.score)

    def _check_object(self, obj_id: int) -> None:
        if int(obj_id) not in self.model.objects:
            raise LearnedRefused("unknown-object", f"learned estimator: object {obj_id} was not in the training "
                                                   f"split (the model knows {', '.join(map(str, self.obj_ids))})")

    def crop_px(self, rgb_width: int, box: tuple[float, float, float, float]) -> int:
        """Pixels of the coordinate net's crop of ``box`` (pixels of an image ``rgb_width`` wide): the
        box's own size at the crops' source width, within the preset's ``crop_px_min`` .. ``crop_px``
        (:func:`~brave6d.evaluation.learned.crops.crop_size`; a model without ``crop_px_min``: ``crop_px``)."""
        largest = int(self.preset["crop_px"])
        s = self.crop_source_width / max(int(rgb_width), 1)
        return crop_size(box_crop(tuple(float(b) * s for b in box))[1],  # type: ignore[arg-type]
                         int(self.preset.get("crop_px_min", largest)), largest)

    def _crop_outputs(self, rgb: NDArray[np.uint8], K: Array, obj_id: int,
                      box: tuple[float, float, float, float], size: int | None = None) -> _CropOutputs:
        """The coordinate net on the crop around ``box`` (``rgb``'s pixels), at the crops' source width,
        ``size`` pixels (None: :meth:`crop_px` of the box)."""
        self._check_object(obj_id)
        obj = self.model.objects[int(obj_id)]
        work, K_work, s = self._work(rgb, K, self.crop_source_width)
        box_w = tuple(float(b) * s for b in box)
        if not all(math.isfinite(b) for b in box_w) or box_w[2] <= box_w[0] or box_w[3] <= box_w[1]:
            raise LearnedRefused("bad-input", f"learned estimator: box {tuple(box)} is empty or not finite")
        centre, side = box_crop(box_w)  # type: ignore[arg-type]
        crop = warp_rgb(work, centre, side, self.crop_px(work.shape[1], box_w) if size is None else size)
        coords, probability = self._coordinates(crop, obj.class_index)
        return _CropOutputs(coords, probability >= 0.5, centre, side, s, K_work, probability,
                            (work.shape[1], work.shape[0]))

    def _coordinates(self, crop: NDArray[np.uint8], class_index: int) -> tuple[Array, Array]:
        """The coordinate net on one crop: coordinates (3, S, S) and mask probabilities (S, S), float64.
        (torch here; ``onnx_export.OnnxEstimator``: ONNX Runtime.)"""
        import torch

        with torch.no_grad():
            coords, mask = self.pose(torch.from_numpy(normalise(crop)[None]).to(self.device),
                                     torch.tensor([class_index], device=self.device))
        probability = torch.sigmoid(mask[0, 0]).float().cpu().numpy().astype(np.float64)
        return coords[0].cpu().numpy().astype(np.float64), probability

    def estimate(self, rgb: NDArray[np.uint8], K: Array, obj_id: int, box: tuple[float, float, float, float],
                 depth_m: NDArray[np.floating] | None = None, score: float = 1.0) -> LearnedPose:
        """The pose of ``obj_id`` inside ``box`` (``rgb``'s pixels); ``depth_m`` (metres, 0 = none, same
        size as ``rgb``) scales the translation so the object's points meet the measured depth."""
        if depth_m is None:
            return self._poses(rgb, K, obj_id, box, None, score, rgb_distance=True)[0]
        depth_pose = self._poses(rgb, K, obj_id, box, depth_m, score, rgb_distance=False)[1]
        assert depth_pose is not None
        return depth_pose

    def estimate_both(self, rgb: NDArray[np.uint8], K: Array, obj_id: int, box: tuple[float, float, float, float],
                      depth_m: NDArray[np.floating] | None = None,
                      score: float = 1.0) -> tuple[LearnedPose, LearnedPose | None]:
        """(RGB-only pose, pose refined with ``depth_m`` or None without depth) from the same crops and
        one PnP: what :meth:`estimate` gives for each, at half the cost of two calls."""
        return self._poses(rgb, K, obj_id, box, depth_m, score, rgb_distance=True)

    def _poses(self, rgb: NDArray[np.uint8], K: Array, obj_id: int, box: tuple[float, float, float, float],
               depth_m: NDArray[np.floating] | None, score: float,
               rgb_distance: bool) -> tuple[LearnedPose, LearnedPose | None]:
        """:meth:`estimate_both`; ``rgb_distance`` False skips the RGB-only pose's mask-area distance
        (its silhouette) when only the depth pose is wanted, which starts from PnP's translation."""
        zooms = self._zooms()
        size = self.crop_px(np.shape(rgb)[1], box) if np.ndim(rgb) >= 2 else None  # the box's, for every zoom
        crops = [self._crop_outputs(rgb, K, obj_id, zoomed(box, z), size) for z in zooms]  # refuses unknown objects
        crop = crops[0]
        obj = self.model.objects[int(obj_id)]
        points_2d, points_3d = [], []
        for c in crops:
            ys, xs = np.nonzero(c.visible)
            points_2d.append(crop_to_image(np.stack([xs, ys], axis=1).astype(np.float64), c.centre, c.side,
                                           c.visible.shape[-1]))
            points_3d.append((c.coords[:, ys, xs].T * obj.radius_mm + obj.centre_mm) / 1000.0)
        points_2d, points_3d = np.concatenate(points_2d), np.concatenate(points_3d)  # type: ignore[assignment]
        cell_px = crop.side / zooms[0] / crop.visible.shape[-1]  # a cell of the zoom-1 crop, whatever zooms[0] is
        R, t, inliers = solve_pnp(points_3d, points_2d, crop.K_work, obj_id,
                                  reprojection_px=PNP_REPROJECTION_CELLS * cell_px)
        ratio = len(inliers) / max(len(points_3d), 1)
        pose_score = float(np.clip(score * ratio, 0.0, 1.0))
        silhouette = self.silhouettes.get(int(obj_id)) if self.mask_area_distance and rgb_distance else None
        mask_scale = None if silhouette is None else _mean_scale(
            [mask_area_scale(c.probability, silhouette, R, t, c.K_work, c.centre, c.side, c.image_size) for c in crops])
        t_rgb = t if mask_scale is None else t * mask_scale
        rgb_pose = LearnedPose(_rigid(R, t_rgb), pose_score, len(inliers), len(points_3d), mask_scale=mask_scale)
        if depth_m is None:
            return rgb_pose, None
        s = crop.scale
        t_d, depth_scale = _depth_scaled(R, t, points_3d[inliers], (points_2d[inliers] + 0.5) / s - 0.5, depth_m)
        cam_T_obj, refined, fit = _rigid(R, t_d), False, None
        surface = self.surfaces.get(int(obj_id))
        if surface is not None and depth_scale is not None:
            d = surface.diameter_m
            points = box_points(depth_m, np.asarray(K, dtype=np.float64), box, t_d[2] - d, t_d[2] + d)
            cam_T_obj, refined, fit = icp_refine(cam_T_obj, points, surface, max_points=self.icp_max_points)
        return rgb_pose, LearnedPose(cam_T_obj, pose_score, len(inliers), len(points_3d), depth_scale, refined, fit)

    def _zooms(self) -> tuple[float, ...]:
        zooms = tuple(self.crop_zooms)
        if not zooms or not all(math.isfinite(z) and 0.25 <= z <= 4.0 for z in zooms):
            raise BraveError(f"learned estimator: crop_zooms must be finite numbers in [0.25, 4], got {zooms}")
        return zooms

    def refine_views(self, obj_id: int, ref_T_obj: Array,
                     views: list[tuple[Array, Array, NDArray[np.floating], tuple[float, float, float, float]]]
                     ) -> tuple[Array, bool, float]:
        """ICP of ``ref_T_obj`` (a pose in a reference camera's frame) onto the depth points in the
        boxes of several views at once, each ``(ref_T_cam, K, depth_m, box)``: the sides that one view
        cannot see pin the rotation down. (pose, refined?, fit) as :func:`icp_refine`; unchanged
        without the object's surface or with too few points."""
        self._check_object(obj_id)
        surface = self.surfaces.get(int(obj_id))
        if surface is None:
            return np.asarray(ref_T_obj, dtype=np.float64), False, 0.0
        d = surface.diameter_m
        clouds, eyes = [], []
        for ref_T_cam, K, depth_m, box in views:
            ref_T_cam = np.asarray(ref_T_cam, dtype=np.float64)
            z = float((np.linalg.inv(ref_T_cam) @ ref_T_obj)[2, 3])
            points = thinned(box_points(depth_m, np.asarray(K, dtype=np.float64), box, z - d, z + d),
                                   self.icp_max_points)
            clouds.append(points @ ref_T_cam[:3, :3].T + ref_T_cam[:3, 3])
            eyes.append(ref_T_cam[:3, 3])
        return icp_refine(np.asarray(ref_T_obj, dtype=np.float64), np.concatenate(clouds) if clouds else np.zeros((0, 3)),
                          surface, max_points=None, eyes=np.asarray(eyes))


@dataclass(frozen=True)
class _CropOutputs:
    """The coordinate net's answer on one crop: coordinates (3, S, S) in [-1, 1], the visible mask
    (S, S), the crop's centre and side (work pixels), the work image's scale and K, the mask's
    probabilities (S, S) and the work image's (width, height)."""

    coords: Array
    visible: NDArray[np.bool_]
    centre: tuple[float, float]
    side: float
    scale: float
    K_work: Array
    probability: Array
    image_size: tuple[int, int]


def zoomed(box: tuple[float, float, float, float], zoom: float) -> tuple[float, float, float, float]:
    """``box`` scaled by ``zoom`` about its centre."""
    x0, y0, x1, y1 = box
    cx, cy, hw, hh = (x0 + x1) / 2.0, (y0 + y1) / 2.0, zoom * (x1 - x0) / 2.0, zoom * (y1 - y0) / 2.0
    return (cx - hw, cy - hh, cx + hw, cy + hh)


def _mean_scale(scales: list[float | None]) -> float | None:
    """The geometric mean of the crops' mask-area scales that were set (None: none was)."""
    kept = [s for s in scales if s is not None]
    return float(np.exp(np.mean(np.log(kept)))) if kept else None


def _rigid(R: Array, t: Array) -> Array:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def solve_pnp(points_3d: Array, points_2d: Array, K: Array, obj_id: int = 0,
              reprojection_px: float = 2.0) -> tuple[Array, Array, NDArray[np.int64]]:
    """Robust PnP that is continuous in its inputs: rotation, translation (the units of
    ``points_3d``) and inlier indices (reprojection error within ``reprojection_px``); refused with
    a named cause when the correspondences are too few, degenerate (collinear), or no finite pose in
    front of the camera comes out.

    A fixed set of :data:`PNP_HYPOTHESES` seeded minimal samples (EPnP on :data:`PNP_SAMPLE`
    points; no adaptive stopping) is scored by MSAC's truncated quadratic cost, and the best
    hypotheses are refined by a smooth robust least squares over all correspondences
    (:func:`_robust_refine`, Cauchy loss at ``reprojection_px``; no hard inlier set inside the fit).
    So float noise of 1e-6 on the inputs moves the pose by about as much, where an inlier count's
    consensus (PnP-RANSAC) flips between poses on integer ties now and then."""
    import cv2

    n = len(points_3d)
    if n < MIN_CORRESPONDENCES:
        raise LearnedRefused("few-correspondences", f"learned estimator: object {obj_id}: {n} correspondences, "
                                                    f"PnP needs at least {MIN_CORRESPONDENCES}")
    if not (math.isfinite(reprojection_px) and reprojection_px > 0):
        raise BraveError(f"solve_pnp: reprojection_px must be a positive finite number of pixels, got {reprojection_px}")
    p3 = np.asarray(points_3d, dtype=np.float64).reshape(n, 3)
    p2 = np.asarray(points_2d, dtype=np.float64).reshape(n, 2)
    K = np.asarray(K, dtype=np.float64)
    if not (np.all(np.isfinite(p3)) and np.all(np.isfinite(p2))):
        raise LearnedRefused("bad-input", f"learned estimator: object {obj_id}: non-finite correspondences")
    for what, pts in (("3D", p3), ("2D", p2)):
        sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if not sv[0] > 0 or sv[1] < MIN_SPREAD * sv[0]:
            raise LearnedRefused("degenerate-correspondences",
                                 f"learned estimator: object {obj_id}: the {what} points are collinear or coincide "
                                 f"(spread {sv[1] / sv[0] if sv[0] > 0 else 0.0:.3g} < {MIN_SPREAD})")
    rng = np.random.default_rng(PNP_SEED)
    hypotheses = []
    for _ in range(PNP_HYPOTHESES):
        sample = rng.choice(n, size=PNP_SAMPLE, replace=False)
        try:
            ok, rvec, tvec = cv2.solvePnP(p3[sample], p2[sample], K, None, flags=cv2.SOLVEPNP_EPNP)
        except cv2.error:  # a degenerate sample
            continue
        if ok and np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)):
            hypotheses.append(np.concatenate([rvec.reshape(3), tvec.reshape(3)]))
    threshold2 = reprojection_px ** 2
    if hypotheses:
        costs = np.minimum(_squared_errors(np.array(hypotheses), p3, p2, K), threshold2).sum(axis=1)
        best = hypotheses[int(np.argmin(costs))]
        if int((_squared_errors(best[None], p3, p2, K)[0] < threshold2).sum()) >= MIN_CORRESPONDENCES:
            x = _robust_refine(best, p3, p2, K, reprojection_px)
            inliers = np.flatnonzero(_squared_errors(x[None], p3, p2, K)[0] < threshold2).astype(np.int64)
            if len(inliers) >= MIN_CORRESPONDENCES:
                R, t = cv2.Rodrigues(x[:3])[0], x[3:].copy()
                if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))) or t[2] <= 0:
                    raise LearnedRefused("pnp-failed", f"learned estimator: object {obj_id}: PnP gave no finite pose "
                                                       f"in front of the camera (t = {t.tolist()})")
                return R, t, inliers
    raise LearnedRefused("pnp-failed", f"learned estimator: object {obj_id}: robust PnP found no pose with "
                                       f">= {MIN_CORRESPONDENCES} inliers among {n} correspondences")


def _squared_errors(poses: Array, p3: Array, p2: Array, K: Array) -> Array:
    """Squared reprojection errors (px^2, (H, N)) of ``poses`` (H, 6: rotation vector, translation);
    a point on or behind the camera's plane counts as infinitely far."""
    from scipy.spatial.transform import Rotation

    cam = np.matmul(p3, Rotation.from_rotvec(poses[:, :3]).as_matrix().transpose(0, 2, 1)) + poses[:, None, 3:]
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * cam[..., 0] / z + K[0, 2] - p2[:, 0]
        v = K[1, 1] * cam[..., 1] / z + K[1, 2] - p2[:, 1]
        errors = u * u + v * v
    return np.where((z > 1e-12) & np.isfinite(errors), errors, np.inf)


def _robust_refine(x0: Array, p3: Array, p2: Array, K: Array, scale_px: float) -> Array:
    """Pose ``x0`` (rotation vector, translation) refined over every correspondence by Levenberg-
    Marquardt on the Cauchy loss of its reprojection error (scale ``scale_px``: weights
    1 / (1 + e^2 / scale^2), iteratively reweighted; the Jacobian from OpenCV's ``projectPoints``),
    a step kept only where it lowers the loss, run to a step of 1e-12 so the result depends smoothly
    on the inputs (no inlier set inside the fit); ``x0`` where nothing lowers the loss."""
    import cv2

    s2 = scale_px ** 2

    def loss(x: Array) -> float:  # a point behind the camera counts as 1e6 px off
        return float(np.log1p(np.minimum(_squared_errors(x[None], p3, p2, K)[0], 1e12) / s2).sum())

    x, current, damping = np.asarray(x0, dtype=np.float64).copy(), loss(x0), 1e-3
    for _ in range(PNP_REFINE_STEPS):
        uv, jac = cv2.projectPoints(p3, x[:3], x[3:], K, None)
        r = (uv.reshape(-1, 2) - p2).ravel()
        J = jac[:, :6]
        in_front = p3 @ cv2.Rodrigues(x[:3])[0][2] + x[5] > 1e-12
        w = np.repeat(np.where(in_front, 1.0 / (1.0 + (r.reshape(-1, 2) ** 2).sum(axis=1) / s2), 0.0), 2)
        if not np.all(np.isfinite(r[w > 0])):
            break
        r, J = np.where(w > 0, r, 0.0), np.where(w[:, None] > 0, J, 0.0)
        A, g = J.T @ (w[:, None] * J), J.T @ (w * r)
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(g))):
            break
        while damping < 1e12:
            try:
                step = np.linalg.solve(A + damping * np.diag(np.diag(A) + 1e-12), -g)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            trial = x + step
            value = loss(trial) if np.all(np.isfinite(trial)) else math.inf
            if value <= current:
                x, current, damping = trial, value, max(damping / 10.0, 1e-9)
                break
            damping *= 10.0
        else:
            break  # no step lowers the loss: a minimum to float precision
        if np.abs(step).max() < 1e-12:
            break
    return x


def _depth_scaled(R: Array, t: Array, points_3d: Array, points_2d: Array,
                  depth_m: NDArray[np.floating]) -> tuple[Array, float | None]:
    """``t`` scaled along its ray so the inliers' depths meet ``depth_m`` (median ratio), and the
    factor; unchanged (None) where the depth has nothing at those pixels."""
    depth = np.asarray(depth_m, dtype=np.float64)
    u = np.rint(points_2d[:, 0]).astype(np.int64)
    v = np.rint(points_2d[:, 1]).astype(np.int64)
    inside = (u >= 0) & (v >= 0) & (u < depth.shape[1]) & (v < depth.shape[0])
    if not inside.any():
        return t, None
    z_obs = depth[v[inside], u[inside]]
    z_pred = (points_3d[inside] @ R.T + t)[:, 2]
    good = np.isfinite(z_obs) & (z_obs > 0) & (z_pred > 0)
    if good.sum() < MIN_CORRESPONDENCES:
        return t, None
    ratio = float(np.median(z_obs[good] / z_pred[good]))
    if not (math.isfinite(ratio) and 0.5 < ratio < 2.0):
        return t, None
    return t * ratio, ratio

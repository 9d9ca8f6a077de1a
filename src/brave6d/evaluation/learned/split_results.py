"""The learned estimator over a BOP split, as the BOP results CSV bop_toolkit evaluates
(``brave6d learn bop-results``): BOP's 6D localisation task, on any split annotation's split
reader reads (a test split, a held-out train_pbr; JPEG or PNG, any ``depth_scale``).

Per image: the targets are BOP19's (the objects with instances at least 10 % visible, and their
counts: ``test_targets_bop19.json``'s ``inst_count``, derived from ``scene_gt_info.json`` as
bop_toolkit's ``enumerate_test_targets.py`` does), or, for a test split whose ground truth is
withheld, read from the dataset's ``test_targets_bop19.json`` itself (only the images it lists).
Targets of objects the model was not trained on are counted as ``unknown-object`` refusals. The image is resized to the crops' source width,
as the held-out scoring (:mod:`~brave6d.evaluation.learned.heldout`) and the agents see it; the
detector runs once, each detection's box is refined by the coordinate net's mask, and each target
object takes its ``inst_count`` best detections scoring at least the agents' threshold, each
estimated RGB-only or, with depth, refined with the image's depth (mm by its ``depth_scale``). One
detection of an object per target is what the held-out figures' ``detected`` variants estimate,
so a single-instance split gives their poses.

``time`` of every estimate of an image is the image's wall time from its decoded colour (and
depth) to its last estimate: resize, detection, box refinement and every estimate (BOP wants one
time per image); reading the files is not counted. Refusals leave no line (BOP scores a missing
estimate as a miss) and are counted by cause.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from brave6d.core.errors import DataError
from brave6d.evaluation.learned.data import MIN_VISIB_FRACT, resize_to_width
from brave6d.evaluation.learned.inference import LearnedEstimator, LearnedRefused
from brave6d.evaluation.learned.presets import DETECTION_THRESHOLD
from brave6d.evaluation.metrics import Estimate


@dataclass
class SplitResults:
    """What :func:`estimate_split` did: the estimates (BOP units), refusals by cause, images, targets
    (instances to find) and the seconds per image."""

    estimates: list[Estimate] = field(default_factory=list)
    refusals: Counter[str] = field(default_factory=Counter)
    images: int = 0
    targets: int = 0
    seconds: list[float] = field(default_factory=list)
    image_ids: list[tuple[int, int]] = field(default_factory=list)  # (scene_id, im_id) of every image read

    @property
    def median_ms_per_image(self) -> float:
        return float(np.median(self.seconds) * 1000.0) if self.seconds else 0.0


def bop19_targets(infos: tuple, gts: tuple) -> dict[int, int]:
    """``{obj_id: inst_count}`` of one image: its instances at least :data:`MIN_VISIB_FRACT` visible."""
    counts: Counter[int] = Counter()
    for gt, info in zip(gts, infos):
        if info.visib_fract >= MIN_VISIB_FRACT:
            counts[gt.obj_id] += 1
    return dict(counts)


def estimate_split(estimator: LearnedEstimator, split_dir: Path | str, with_depth: bool = False,
                   max_images: int | None = None, progress: Callable[[str], None] | None = None,
                   targets_file: Path | str | None = None) -> SplitResults:
    """Estimate every BOP19 target of ``split_dir`` (module docstring); ``with_depth``: refine with
    the split's depth; ``max_images``: the first n images only; ``targets_file``: the targets from
    ``test_targets_bop19.json`` instead of the split's ground truth (a test split whose
    ``scene_gt.json`` is withheld: only the images it lists are read)."""
    import cv2

    from brave6d.annotation import read_split_scene, read_split_targets, split_scene_folders

    out = SplitResults()
    listed: dict[tuple[int, int], dict[int, int]] | None = None
    if targets_file is not None:
        images, listed = read_split_targets(split_dir, targets_file)
    else:
        scenes = split_scene_folders(split_dir)
        for scene in scenes:
            if not (scene / "scene_gt.json").is_file() and (scene / "scene_camera.json").is_file():
                raise DataError(f"{scene / 'scene_gt.json'}: not found: a test split without ground truth is "
                                "estimated from its targets file (--targets test_targets_bop19.json)")
        images = [image for scene in scenes for image in read_split_scene(scene)]  # read_bop_split's order
    images = images[:max_images]
    width = estimator.crop_source_width
    for image in images:
        out.image_ids.append((image.scene_id, image.im_id))
        wanted = listed[(image.scene_id, image.im_id)] if listed is not None else bop19_targets(image.infos, image.gts)
        targets = {o: n for o, n in wanted.items() if o in estimator.obj_ids}
        unknown = sum(n for o, n in wanted.items() if o not in estimator.obj_ids)
        if unknown:
            out.refusals["unknown-object"] += unknown
        if not targets:
            continue
        full = image.read_rgb()
        depth_mm = image.read_depth_mm() if with_depth else None
        t0 = time.perf_counter()
        rgb, K, _ = resize_to_width(full, image.camera.cam_K, width)
        depth_m = None
        if depth_mm is not None:
            h, w = rgb.shape[:2]
            depth_m = cv2.resize(depth_mm, (w, h), interpolation=cv2.INTER_NEAREST) / 1000.0
        detections = [estimator.refine_box(rgb, K, d) for d in estimator.detect(rgb, K, min_score=DETECTION_THRESHOLD)]
        found = []
        for obj_id, count in sorted(targets.items()):
            out.targets += count
            mine = [d for d in detections if d.obj_id == obj_id][:count]
            out.refusals["no-detection"] += count - len(mine)
            for d in mine:
                try:
                    pose = estimator.estimate(rgb, K, obj_id, d.box, depth_m, d.score)
                except LearnedRefused as exc:
                    out.refusals[exc.cause] += 1
                    continue
                found.append((obj_id, pose))
        seconds = time.perf_counter() - t0
        out.images += 1
        out.seconds.append(seconds)
        out.estimates += [Estimate(image.scene_id, image.im_id, obj_id, pose.score, pose.cam_T_obj[:3, :3],
                                   pose.cam_T_obj[:3, 3] * 1000.0, seconds) for obj_id, pose in found]
        if progress is not None:
            progress(f"scene {image.scene_id} image {image.im_id}: {len(found)}/{sum(targets.values())} "
                     f"estimated in {seconds * 1000:.0f} ms")
    return out

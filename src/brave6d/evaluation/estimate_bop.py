"""The single-frame estimator over a BOP split: one estimate per ground-truth box, as a BOP results CSV.

For every image of every scene folder of a BOP split (``test/000002/...``): the depth
(``depth/{im_id:06d}.png`` at the image's ``depth_scale``, which must be given), the colour image when there is one
(``rgb/{im_id:06d}.png`` or ``.jpg``: with models that have vertex colours it tells a flip apart), ``cam_K`` (``scene_camera.json``, read by
``annotation``), and one hint per instance of ``scene_gt.json`` whose ``visib_fract`` reaches BOP19's
0.1, its box from ``scene_gt_info.json`` (``bbox_visib``, or ``bbox_obj``). The boxes and object ids
come from the ground truth: an oracle detector, as BOP's "GT boxes" runs use; a method with its own
detections calls :func:`brave6d.evaluation.agents.estimate_pose` with them.

Refusals are counted by cause and leave no line (BOP scores a missing estimate as a miss). Every
estimate of one image reports the image's total estimation time (BOP wants one time per image).
The CSV is written by the one owner of that format, :func:`brave6d.evaluation.metrics.write_bop_results`.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError
from brave6d.evaluation.agents.frame import (
    BoxHint,
    EstimateRefused,
    FrameOptions,
    estimate_pose,
    prepare_model,
    read_depth_png,
)
from brave6d.evaluation.agents.model import ModelCloud
from brave6d.evaluation.metrics.recall import Estimate

#: BOP19 targets: instances at least this visible.
MIN_VISIB_FRACT = 0.1
HINT_BOXES = ("bbox_visib", "bbox_obj")


@dataclass
class SplitRun:
    """What :func:`estimate_bop_split` did: the estimates (BOP units), the refusals by cause and the
    ``(scene_id, im_id, obj_id, cause, message)`` of each, the images and instances seen."""

    estimates: list[Estimate] = field(default_factory=list)
    refusals: list[tuple[int, int, int, str, str]] = field(default_factory=list)
    images: int = 0
    instances: int = 0
    skipped_no_model: int = 0

    @property
    def refused_by_cause(self) -> dict[str, int]:
        return dict(Counter(r[3] for r in self.refusals))


def scene_folders(split_dir: Path | str, scene_ids: Iterable[int] | None = None) -> list[Path]:
    """The six-digit scene folders of a BOP split folder (all, or those of ``scene_ids``)."""
    from brave6d.annotation import split_scene_folders

    d = Path(split_dir)
    scenes = split_scene_folders(d)
    if scene_ids is not None:
        wanted = {int(s) for s in scene_ids}
        missing = wanted - {int(p.name) for p in scenes}
        if missing:
            raise DataError(f"{d}: no scene folder for scene id(s) {sorted(missing)}")
        scenes = [p for p in scenes if int(p.name) in wanted]
    return scenes


def estimate_bop_split(split_dir: Path | str, models_dir: Path | str, *, scene_ids: Iterable[int] | None = None,
                       im_ids: Iterable[int] | None = None, obj_ids: Iterable[int] | None = None,
                       hint_box: str = "bbox_visib", options: FrameOptions = FrameOptions(), model_points: int = 2000,
                       progress: Callable[[str], None] | None = None) -> SplitRun:
    """Estimate every visible ground-truth instance of a BOP split (see the module docstring).

    ``models_dir``: ``models_info.json`` (diameters) and ``obj_{id:06d}.ply`` in mm; ``scene_ids`` /
    ``im_ids`` / ``obj_ids`` restrict the run; ``hint_box``: which ``scene_gt_info`` box is the hint."""
    from brave6d.annotation import model_file, read_models_info, read_scene_camera, read_scene_gt, read_scene_gt_info
    from brave6d.annotation import find_rgb_file, read_split_rgb

    if hint_box not in HINT_BOXES:
        raise DataError(f"hint_box must be one of {HINT_BOXES}, got {hint_box!r}")
    mdir = Path(models_dir)
    info = read_models_info(mdir / "models_info.json")
    wanted_objs = None if obj_ids is None else {int(o) for o in obj_ids}
    wanted_ims = None if im_ids is None else {int(i) for i in im_ids}
    clouds: dict[int, ModelCloud] = {}
    run = SplitRun()
    for scene in scene_folders(split_dir, scene_ids):
        scene_id = int(scene.name)
        cams = read_scene_camera(scene / "scene_camera.json", require_depth_scale=True)  # depth is read
        gt = read_scene_gt(scene / "scene_gt.json")
        gt_info = read_scene_gt_info(scene / "scene_gt_info.json")
        for im_id in sorted(gt):
            if wanted_ims is not None and im_id not in wanted_ims:
                continue
            if im_id not in cams or im_id not in gt_info or len(gt_info[im_id]) != len(gt[im_id]):
                raise DataError(f"{scene}: image {im_id} of scene_gt.json lacks a matching scene_camera.json "
                                "or scene_gt_info.json entry")
            targets = [(g, gi) for g, gi in zip(gt[im_id], gt_info[im_id])
                       if gi.visib_fract >= MIN_VISIB_FRACT and (wanted_objs is None or g.obj_id in wanted_objs)]
            if not targets:
                continue
            cam = cams[im_id]
            depth = read_depth_png(scene / "depth" / f"{im_id:06d}.png", cam.depth_scale)
            # colour tells a flip apart when the models have it (PNG or JPEG, as annotation's split reader finds it)
            rgb_path = find_rgb_file(scene, im_id)
            rgb = read_split_rgb(rgb_path) if rgb_path is not None else None
            run.images += 1
            image_estimates: list[tuple[int, float, NDArray[np.float64], NDArray[np.float64]]] = []
            t_image = time.perf_counter()
            for g, gi in targets:
                run.instances += 1
                if g.obj_id not in info:
                    run.skipped_no_model += 1
                    continue
                box = getattr(gi, hint_box)
                if box is None:
                    raise DataError(f"{scene / 'scene_gt_info.json'}: image {im_id}: an instance of object "
                                    f"{g.obj_id} has no {hint_box}")
                if g.obj_id not in clouds:
                    clouds[g.obj_id] = prepare_model(model_file(mdir, g.obj_id), "mm", obj_id=g.obj_id,
                                                     diameter=float(info[g.obj_id]["diameter"]), points=model_points)
                try:
                    pose = estimate_pose(depth, cam.cam_K, clouds[g.obj_id], BoxHint(*(float(v) for v in box)),
                                         rgb=rgb, options=options)
                except EstimateRefused as exc:
                    run.refusals.append((scene_id, im_id, g.obj_id, exc.cause, str(exc)))
                    continue
                image_estimates.append((g.obj_id, pose.score, pose.R, pose.t_mm))
            seconds = time.perf_counter() - t_image
            run.estimates += [Estimate(scene_id, im_id, obj_id, score, R, t, seconds)
                              for obj_id, score, R, t in image_estimates]
            if progress is not None:
                progress(f"scene {scene_id} image {im_id}: {len(image_estimates)}/{len(targets)} estimated "
                         f"in {seconds:.1f} s")
    return run


def score_results_csv(csv: Path | str, split: Path | str, models: Path | str, scenes: Iterable[int] | None = None,
                      images: Iterable[int] | None = None, objects: Iterable[int] | None = None) -> str:
    """One line: BOP19 AR of a BOP results CSV against a split's ground truth (optionally restricted
    to scenes, images and objects; always to the objects with a model), the CSV read through its one
    reader. ``brave6d estimate bop --score`` and ``brave6d evaluate RESULTS.csv`` print it."""
    from brave6d.annotation import read_models_info
    from brave6d.evaluation.metrics import evaluate_bop19, load_models, load_scene_gt_instances, read_bop_results

    image_ids = None if images is None else set(images)
    object_ids = None if objects is None else set(objects)
    known = read_models_info(Path(models) / "models_info.json")
    gts = [g for s in scene_folders(split, scenes) for g in load_scene_gt_instances(s)
           if (image_ids is None or g.im_id in image_ids) and (object_ids is None or g.obj_id in object_ids)
           and g.obj_id in known]
    if not gts:
        raise DataError(f"{split}: no ground-truth instance to score (with a model in {models})")
    models_by_id = load_models(Path(models), sorted({g.obj_id for g in gts}))
    scores = evaluate_bop19(gts, read_bop_results(Path(csv)), models_by_id)
    parts = ", ".join(f"AR_{name.upper()} {m.ar:.3f}" for name, m in scores.metrics.items())
    return f"AR {scores.ar:.3f} ({parts}) over {scores.n_targets} targets in {scores.n_images} images"

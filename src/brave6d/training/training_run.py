"""``train``: one training run in memory, from loaded views to a trained model.

Initial points (COLMAP, depth frames or random; see :func:`brave6d.training.colmap_init.initial_points`)
-> the scene's training frame (:mod:`brave6d.training.scene_frame`: the views and the points moved and
scaled once, so that the scene's extent is 1 whatever its units) -> :class:`brave6d.training.trainer.Trainer`
-> the trained :class:`~brave6d.training.model.GaussianModel` back in the world, its curve and the holdout
scores taken during training. Nothing is written unless asked:
``scene`` lets the initialisation write ``sparse/0``, ``checkpoint_dir`` makes the trainer write
checkpoints. :func:`brave6d.training.pipeline.train_scene` (``brave6d train``) and the report's view
sweep both train through this function, so there is one training code path.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from brave6d.core.layout import SceneDir
from brave6d.training.colmap_init import ColmapOptions, initial_points
from brave6d.training.views import TrainingData
from brave6d.training.device import resolve_device
from brave6d.training.holdout_eval import HoldoutMetrics, evaluate_holdout
from brave6d.training.model import GaussianModel
from brave6d.training.ply import SplatData
from brave6d.training.presets import Preset
from brave6d.training.scene_frame import SceneFrame
from brave6d.training.scene_pose_check import check_scene_poses
from brave6d.training.trainer import Trainer, TrainResult, list_checkpoints, set_seed

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HoldoutPoint:
    """The holdout scores at one step of a run (taken every ``preset.schedule.eval_every`` steps)."""

    step: int
    time_s: float  # training seconds up to this step (evaluation excluded)
    gaussians: int
    psnr: float
    ssim: float
    eval_s: float  # seconds this evaluation took


@dataclass
class TrainedSplat:
    """What :func:`train` returns: the model, the run's record and where it started from."""

    model: GaussianModel  # in the world (the scene's units)
    result: TrainResult
    init: dict[str, Any]  # where the initial points came from: {"source", "points", ...} or {"source": "checkpoint"}
    init_seconds: float  # initial points and model construction
    holdout_curve: list[HoldoutPoint] = field(default_factory=list)
    pose_check: str | None = None  # the pose check's one-line result, or why it was skipped or not run
    frame: SceneFrame | None = None  # the training frame it was trained in (None: not made by train)
    frame_model: GaussianModel | None = None  # the model as trained, in that frame
    frame_data: TrainingData | None = None  # the views in that frame

    def holdout(self, image_dir: Path | None = None) -> HoldoutMetrics:
        """The holdout scores of the trained model, taken in its training frame (as during training: the
        same numbers, whatever the scene's units); with ``image_dir``, the render | truth PNGs."""
        if self.frame_model is None or self.frame_data is None:
            raise ValueError("holdout: this TrainedSplat has no training frame (made by train())")
        return evaluate_holdout(self.frame_model, self.frame_data, image_dir)

    @property
    def steps(self) -> int:
        return self.result.steps

    @property
    def num_gaussians(self) -> int:
        return self.result.num_gaussians

    def to_splat(self) -> SplatData:
        """The trained Gaussians as PLY data (what ``write_ply`` and ``SplatRenderer.from_splat`` take)."""
        return self.model.to_splat()


def train(
    data: TrainingData,
    preset: Preset,
    device: str | torch.device = "auto",
    *,
    scene: SceneDir | None = None,
    init_method: str = "auto",
    colmap: ColmapOptions | None = None,
    checkpoint_dir: Path | None = None,
    resume: bool = False,
    checkpoint_hook: Callable[[Trainer], None] | None = None,
    show_progress: bool = False,
    check_poses: bool = True,
    budget_started_at: float | None = None,
) -> TrainedSplat:
    """Train a splat on ``data.train`` with ``preset``; the holdout is scored every
    ``preset.schedule.eval_every`` steps.

    ``scene``: the scene the views come from (COLMAP reuses and writes its ``sparse/0``; None:
    nothing is written and COLMAP is skipped unless ``data`` has undistorted image files).
    ``resume``: continue from the newest checkpoint in ``checkpoint_dir`` (the model comes
    from it; without a checkpoint there a new run starts). ``checkpoint_hook`` is called after
    each checkpoint is written. ``check_poses``: first check that the cameras see the scene
    (:func:`brave6d.training.check_scene_poses`; a :class:`~brave6d.training.PoseCheckError` names the
    views that do not). ``budget_started_at``: the ``time.perf_counter()`` the preset's time budget
    counts from (``brave6d train``: the command's start); None: now, so that the initial points count.

    Training happens in the scene's training frame (:class:`~brave6d.training.scene_frame.SceneFrame`
    of ``data``'s cameras, :meth:`~brave6d.training.views.TrainingData.training_frame`): ``data`` and the
    initial points are moved into it once, the model comes back to the world once; the holdout scores
    during training are taken in it.
    """
    started = time.perf_counter() if budget_started_at is None else budget_started_at
    pose_check = "pose check: not run (--skip-pose-check)"
    if check_poses:
        checked = check_scene_poses(data, scene)
        pose_check = checked.summary() if checked is not None else (
            "pose check: skipped (no imported points, no capture target, and the optical axes do not meet)")
    dev = resolve_device(device)
    set_seed(preset.seed)
    t0 = time.perf_counter()
    frame = data.training_frame()
    continuing = resume and checkpoint_dir is not None and bool(list_checkpoints(checkpoint_dir))
    init_info: dict[str, Any]
    if continuing:
        # the model comes from the checkpoint; a placeholder keeps the constructor simple
        model = GaussianModel.from_points([[0.0, 0.0, 0.0]], sh_degree=preset.initialisation.sh_degree, device=dev)
        init_info = {"source": "checkpoint"}
    else:
        start = preset.initialisation
        init = initial_points(scene, data, colmap or ColmapOptions(), start.max_init_points, preset.seed, init_method)
        model = GaussianModel.from_points(frame.points(init.points), init.colors, start.sh_degree, start.init_opacity,
                                          start.init_scale, device=dev)
        log.info("initial points: %d from %s", len(init), init.source)
        init_info = {"source": init.source, "points": len(init), **init.details}
    init_seconds = time.perf_counter() - t0
    log.info("training frame: the scene's extent is %.6g world units (near plane %.3g), centred at %s",
             frame.unit, frame.to_json()["near_plane"], [round(c, 6) for c in frame.centre])
    data = data.in_frame(frame)
    curve: list[HoldoutPoint] = []

    def score_holdout(trainer: Trainer) -> float:
        t = time.perf_counter()
        h = evaluate_holdout(trainer.model, data)
        curve.append(HoldoutPoint(trainer.step, trainer.elapsed, trainer.model.num_gaussians, h.psnr, h.ssim,
                                  time.perf_counter() - t))
        return h.psnr

    trainer = Trainer(data, model, preset, checkpoint_dir, dev, show_progress=show_progress,
                      eval_callback=score_holdout, checkpoint_hook=checkpoint_hook, budget_started_at=started)
    result = trainer.train(resume=continuing)
    return TrainedSplat(trainer.model.in_world(frame), result, init_info, init_seconds, curve, pose_check, frame,
                        trainer.model, data)

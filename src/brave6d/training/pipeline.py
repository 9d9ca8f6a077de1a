"""``train_scene``: the whole training stage on one scene directory.

Frames + calibrated poses -> initial points (COLMAP, ``sparse/0``) -> training -> holdout
evaluation -> ``splat/point_cloud.ply`` (Inria layout), ``splat/point_cloud_viewer.ply`` (the same
Gaussians for other 3DGS viewers: the 3D filter baked in), ``splat/holdout.json`` (the views held
out: :mod:`brave6d.training.holdout`), ``splat/metrics.json``, ``splat/curves.png``,
``splat/holdout/<view>.png`` (render | ground truth) and ``splat/checkpoints/``.

Nothing of a previous training is deleted. The inputs are checked first; a new training (not
``--resume``) then writes its checkpoints to a hidden staging folder, and only once the first one
is written are the previous outputs (:func:`training_outputs`) moved aside to
``<name>.old-<stamp>`` siblings and the staging folder renamed to ``splat/checkpoints``. A run
that fails earlier leaves the previous training exactly as it was. ``--resume`` continues the
training in ``splat/checkpoints`` and rewrites its outputs.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from brave6d.core.atomic import move_aside
from brave6d.core.errors import BraveError
from brave6d.core.layout import SceneDir
from brave6d.training.colmap_init import ColmapOptions
from brave6d.training.device import resolve_device
from brave6d.training.holdout import HOLDOUT_PROTOCOL, write_holdout
from brave6d.training.holdout_eval import peak_memory_mb, plot_curves, write_metrics
from brave6d.training.ply import write_ply, write_viewer_ply
from brave6d.training.presets import Preset
from brave6d.training.trainer import Trainer, TrainResult, list_checkpoints
from brave6d.training.training_run import train
from brave6d.training.views import TrainingData, load_scene

log = logging.getLogger(__name__)

def training_outputs(scene: SceneDir) -> tuple[Path, ...]:
    """What a training run writes into ``splat/``: a new run moves the previous run's aside."""
    return (scene.checkpoints_dir, scene.splat_ply_path, scene.splat_viewer_ply_path, scene.holdout_split_path,
            scene.metrics_path, scene.curves_path, scene.holdout_images_dir)


def move_previous_outputs(scene: SceneDir) -> list[Path]:
    """Move each existing :func:`training_outputs` entry of ``scene`` aside; returns the new paths.

    An empty folder is simply removed (nothing to keep).
    """
    moved = []
    for path in training_outputs(scene):
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()
        elif path.exists() or path.is_symlink():
            moved.append(move_aside(path))
            log.info("kept the previous training's %s as %s", path.name, moved[-1])
    return moved


class NewRun:
    """A training that takes the place of the previous one in ``splat/`` only once it has a checkpoint.

    Its checkpoints go to :attr:`staging`; :meth:`take_place` (called at the first checkpoint, and
    before the other outputs are written) moves the previous outputs aside and makes the staging
    folder ``splat/checkpoints``. :meth:`close` removes the staging folder of a run that never
    took place.
    """

    def __init__(self, scene: SceneDir) -> None:
        scene.splat_dir.mkdir(parents=True, exist_ok=True)
        self.scene = scene
        self.staging = Path(tempfile.mkdtemp(prefix=".checkpoints.new-", dir=scene.splat_dir))
        self.moved: list[Path] | None = None  # None until the run took its place

    def take_place(self, trainer: Trainer) -> None:
        """Move the previous outputs aside and the trainer's checkpoints to ``splat/checkpoints`` (once)."""
        if self.moved is not None:
            return
        self.moved = move_previous_outputs(self.scene)
        trainer.move_checkpoints(self.scene.checkpoints_dir)

    def finish(self) -> None:
        """Take the previous run's place after training, if no checkpoint did so already."""
        if self.moved is not None:
            return
        self.moved = move_previous_outputs(self.scene)
        os.rename(self.staging, self.scene.checkpoints_dir)

    def close(self) -> None:
        """Remove the staging folder of a run that never took its place (the previous one is untouched)."""
        if self.moved is None:
            shutil.rmtree(self.staging, ignore_errors=True)


def train_scene(
    scene: SceneDir,
    preset: Preset,
    device: str = "auto",
    resume: bool = False,
    skip_bad_frames: bool = False,
    init_method: str = "auto",
    colmap: ColmapOptions | None = None,
    show_progress: bool = True,
    check_poses: bool = True,
) -> dict[str, Any]:
    """Train ``scene`` with ``preset`` and write the ``splat/`` outputs; returns the metrics.

    See the module docstring for what happens to a previous training. ``check_poses``: refuse
    cameras that do not see the scene (:func:`brave6d.training.check_scene_poses`) before training.
    """
    t_start = time.perf_counter()
    dev = resolve_device(device)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    ckpt_dir = scene.checkpoints_dir
    data = load_scene(scene, preset.downscale, skip_bad_frames)  # the inputs, before anything is moved
    preset, budget = photo_set_preset(preset, data)
    t_loaded = time.perf_counter()
    log.info("images: %s", data.undistortion)
    continuing = resume and bool(list_checkpoints(ckpt_dir))
    if resume and not continuing:
        log.warning("--resume: no checkpoint in %s; starting a new training", ckpt_dir)
    run = None if continuing else NewRun(scene)
    try:
        trained = train(data, preset, dev, scene=scene, init_method=init_method, colmap=colmap,
                        checkpoint_dir=ckpt_dir if run is None else run.staging, resume=continuing,
                        checkpoint_hook=None if run is None else run.take_place, show_progress=show_progress,
                        check_poses=check_poses, budget_started_at=t_start)
        if run is not None:
            run.finish()  # a run without any checkpoint (no steps) still replaces the outputs
    finally:
        if run is not None:
            run.close()
    if run is not None and run.moved:
        log.info("the previous training is kept beside the new one: %s", ", ".join(p.name for p in run.moved))
    t_init = t_loaded - t_start + trained.init_seconds
    result = trained.result
    model = trained.model
    splat = model.to_splat()
    ply_path = write_ply(scene.splat_ply_path, splat)
    write_viewer_ply(scene.splat_viewer_ply_path, splat)
    t_eval = time.perf_counter()
    shutil.rmtree(scene.holdout_images_dir, ignore_errors=True)  # --resume: no stale views from an earlier split
    holdout = trained.holdout(scene.holdout_images_dir)  # in the training frame, as during training
    t_eval = time.perf_counter() - t_eval
    if result.curve:
        result.curve[-1]["holdout_psnr"] = holdout.psnr
        plot_curves(scene.curves_path, result.curve,
                    f"{scene.root.name}: preset {preset.name}, {result.steps} steps, holdout {holdout.psnr:.2f} dB")
    metrics: dict[str, Any] = {
        "preset": preset.name,
        "device": str(dev),
        "steps": result.steps,
        "planned_steps": preset.steps,
        "stopped_by": result.stopped_by,
        "time_budget": budget_record(result),
        "resumed_from_step": result.resumed_from,
        "train_time_s": result.train_seconds,
        "train_cpu_s": result.train_cpu_seconds,
        "threads": {"torch": torch.get_num_threads(), "numba": _numba_threads()},
        "init_time_s": t_init,
        "eval_time_s": t_eval,
        "total_time_s": time.perf_counter() - t_start,
        "num_gaussians": result.num_gaussians,
        "gaussian_budget": budget,
        "memory": peak_memory_mb(dev),
        "holdout": holdout.to_json(),
        "n_train_views": len(data.train),
        "n_holdout_views": len(data.test),
        "holdout_protocol": HOLDOUT_PROTOCOL,
        "skipped_frames": [{"index": s.index, "view_id": s.view_id, "reason": s.reason} for s in data.skipped],
        "images": {"undistorted_once": True, "how": data.undistortion, "width": data.camera.width,
                   "height": data.camera.height, "downscale": data.downscale,
                   "metrics_resolution": f"{data.camera.width}x{data.camera.height}"},
        "poses": ("world_T_cam imported (capture/import.json; handeye.json is the identity)"
                  if scene.import_record_path.is_file() else
                  "base_T_tcp (robot) @ tcp_T_cam (calibrated, calibration/handeye.json)"),
        "init": trained.init,
        "scene_frame": trained.frame.to_json() if trained.frame is not None else None,
        "pose_check": trained.pose_check,
        "outputs": {"ply": str(ply_path), "curves": str(scene.curves_path),
                    "holdout_split": str(scene.holdout_split_path),
                    "holdout_images": str(scene.holdout_images_dir), "checkpoints": str(ckpt_dir),
                    "colmap_model": str(scene.sparse_model_dir),
                    "previous_training": [str(p) for p in (run.moved or [])] if run is not None else []},
        "preset_config": preset.to_json(),
        "curve": result.curve,
    }
    write_holdout(scene, data.test)  # the split, once, just before the metrics that score it
    write_metrics(scene.metrics_path, metrics)
    return metrics


#: What a preset's time budget counts (``metrics.json``'s ``time_budget.counts``, the summary, the docs).
BUDGET_COUNTS = ("the whole train command from its start: loading the images, the pose check, the initial points "
                 "(COLMAP) and the training steps; the holdout evaluation and the writing after the last step come on top")


def budget_record(result: TrainResult) -> dict[str, Any] | None:
    """``metrics.json``'s ``time_budget``: the budget, what it counts and how much of it the run used."""
    if result.budget_s is None:
        return None
    return {"budget_s": result.budget_s, "counts": BUDGET_COUNTS, "used_s": result.budget_used_s,
            "stopped_training": result.stopped_by == "time budget"}


def photo_set_preset(preset: Preset, data: TrainingData) -> tuple[Preset, dict[str, Any] | None]:
    """``preset`` with a photo set's Gaussian cap (:meth:`Densification.photo_set_cap`) when no
    training view has depth, and what was applied (None: the preset as it is)."""
    dens = preset.densification
    if dens.photo_set_pixels_per_gaussian is None or any(v.depth_path is not None for v in data.train):
        return preset, None
    pixels = len(data.train) * data.camera.width * data.camera.height
    cap = dens.photo_set_cap(pixels)
    if cap == dens.max_gaussians:
        return preset, None
    log.info("a photo set (no depth in its %d training views, %d pixels): at most %d Gaussians, one per %g "
             "training pixels (the preset's cap: %s)", len(data.train), pixels, cap,
             dens.photo_set_pixels_per_gaussian, dens.max_gaussians)
    return preset.with_values(max_gaussians=cap), {
        "reason": "photo set: no training view has depth", "training_pixels": pixels,
        "pixels_per_gaussian": dens.photo_set_pixels_per_gaussian, "max_gaussians": cap,
        "preset_max_gaussians": dens.max_gaussians}


def _numba_threads() -> int | None:
    try:
        import numba

        return int(numba.get_num_threads())
    except Exception:  # noqa: BLE001 - numba is the CPU rasterizer's dependency; absent on some CUDA installs
        return None


def require_capture(scene: SceneDir) -> None:
    """Fail early, naming what is missing, before anything heavy is imported or started."""
    for path, what in ((scene.frames_path, "the capture (run the capture stage)"),
                       (scene.intrinsics_path, "the intrinsics (run the calibration stage)"),
                       (scene.handeye_path, "the hand-eye transform (run the calibration stage)")):
        if not Path(path).exists():
            raise BraveError(f"{path}: missing; training needs {what}")

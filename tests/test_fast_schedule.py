"""The CPU ``fast`` schedule on hard cases: the Gaussian budget holds at every step, and tiny or
huge Gaussians and constant images train without NaN/inf."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from brave6d.core.camera import PinholeCamera
from brave6d.training.views import TrainingData, View
from brave6d.training.holdout_eval import evaluate_holdout
from brave6d.training.model import GaussianModel
from brave6d.training.presets import get_preset
from brave6d.training.toy_scenes import random_gaussians, render_views, ring_poses
from brave6d.training.trainer import Trainer, base_lrs

CAM = PinholeCamera(48, 36, 40.0, 40.0, 23.5, 17.5)
BUDGET = 260


def _views(images: list[np.ndarray]) -> TrainingData:
    poses = ring_poses([0.35, 0.45], 5, elevation_deg=40)
    views = [View(i, f"v{i:02d}", lvl, d, pose, img) for i, ((lvl, d, pose), img) in enumerate(zip(poses, images))]
    return TrainingData(CAM, [v for i, v in enumerate(views) if i not in (2, 7)], [views[2], views[7]])


@pytest.fixture(scope="module")
def scene_views() -> TrainingData:
    gt = random_gaussians(200, seed=4, extent=0.08)
    return _views(render_views(gt, CAM, [p for _, _, p in ring_poses([0.35, 0.45], 5, elevation_deg=40)]))


def _fast(steps: int = 60, **overrides: object):
    """The shipped ``fast`` schedule scaled to ``steps`` (every step-based setting scales with it), a
    small budget that growth must hit, and full-resolution tiny images."""
    preset = get_preset("fast").with_steps(steps)
    return preset.with_overrides(downscale=1, max_gaussians=BUDGET, grow_grad2d=1e-6, time_budget_s=None,
                                 **overrides)


def _model(n: int, log_scale: float, seed: int = 0) -> GaussianModel:
    rng = np.random.default_rng(seed)
    model = GaussianModel.from_points(rng.normal(0, 0.04, (n, 3)), None, sh_degree=2, init_opacity=0.3)
    with torch.no_grad():
        model.params["scales"].fill_(log_scale)
    return model


def _train_checked(data: TrainingData, model: GaussianModel, preset) -> tuple[Trainer, list[int]]:
    counts: list[int] = []

    def check(trainer: Trainer, step: int) -> None:
        counts.append(trainer.model.num_gaussians)
        assert not trainer.model.non_finite(), f"non-finite parameters at step {step}"

    trainer = Trainer(data, model, preset, None, show_progress=False, step_callback=check)
    trainer.train()
    return trainer, counts


def test_the_gaussian_budget_holds_at_every_step(scene_views: TrainingData) -> None:
    preset = _fast()
    assert preset.schedule.coarse_steps > 0  # the schedule under test trains coarse-to-fine
    rates = preset.learning_rates
    assert rates.lr_decay_final < 1.0 and rates.lr_decay_start < preset.steps  # and anneals its rates
    trainer, counts = _train_checked(scene_views, _model(120, float(np.log(0.01))), preset)
    assert len(counts) == preset.steps
    final_scales_lr = trainer.optimizers["scales"].param_groups[0]["lr"]
    assert final_scales_lr < base_lrs(preset)["scales"]  # the annealed phase was trained through
    assert max(counts) <= BUDGET
    assert max(counts) == BUDGET  # growth was asked for more and stopped at the budget
    assert np.isfinite(evaluate_holdout(trainer.model, scene_views).psnr)


@pytest.mark.parametrize("log_scale", [float(np.log(1e-7)), float(np.log(5.0))], ids=["tiny", "huge"])
def test_tiny_and_huge_gaussians_train_without_nan(scene_views: TrainingData, log_scale: float) -> None:
    trainer, counts = _train_checked(scene_views, _model(150, log_scale), _fast())
    assert max(counts) <= BUDGET
    result = evaluate_holdout(trainer.model, scene_views)
    assert np.isfinite(result.psnr) and np.isfinite(result.ssim)


@pytest.mark.parametrize("level", [0, 128, 255])
def test_constant_images_train_without_nan(level: int) -> None:
    """Flat images: zero-variance SSIM windows, constant gradients; the fit must not get worse."""
    data = _views([np.full((CAM.height, CAM.width, 3), level, np.uint8) for _ in range(10)])
    model = _model(100, float(np.log(0.02)))
    before = evaluate_holdout(model, data).psnr
    trainer, counts = _train_checked(data, model, _fast(steps=80))
    assert max(counts) <= BUDGET
    result = evaluate_holdout(trainer.model, data)
    assert np.isfinite(result.psnr) and np.isfinite(result.ssim)
    assert result.psnr >= before - 0.1

"""Learning-rate annealing of quats, scales, opacities and SH (``LearningRates.lr_decay_final`` /
``lr_decay_start`` of a preset): the factor's schedule, its validation, and that a training step applies it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.training.views import TrainingData, View
from brave6d.training.model import GaussianModel
from brave6d.training.presets import get_preset
from brave6d.training.toy_scenes import random_gaussians, render_views, ring_poses
from brave6d.training.trainer import Trainer, base_lrs, other_lr_factor

FAST = get_preset("fast")


def test_fast_anneals_from_its_first_full_resolution_step() -> None:
    rates = FAST.learning_rates
    assert rates.lr_decay_start == FAST.schedule.coarse_steps and rates.lr_decay_final == pytest.approx(0.1)
    assert other_lr_factor(0, FAST) == 1.0
    assert other_lr_factor(rates.lr_decay_start, FAST) == 1.0
    mid = (rates.lr_decay_start + FAST.steps) // 2
    assert other_lr_factor(mid, FAST) == pytest.approx(math.sqrt(0.1), rel=1e-3)  # log-linear
    assert other_lr_factor(FAST.steps, FAST) == pytest.approx(0.1)
    assert other_lr_factor(10 * FAST.steps, FAST) == pytest.approx(0.1)  # held after the last step
    assert other_lr_factor(1234, get_preset("default")) == 1.0  # Inria's rates stay constant


@settings(max_examples=200, deadline=None)
@given(final=st.floats(min_value=1e-12, max_value=1.0), steps=st.integers(1, 10**6),
       start_frac=st.floats(0.0, 1.0), step=st.integers(-10, 2 * 10**6))
def test_factor_is_finite_monotone_and_bounded(final: float, steps: int, start_frac: float, step: int) -> None:
    preset = FAST.with_overrides(steps=steps, coarse_steps=0, lr_decay_final=final,
                                 lr_decay_start=int(start_frac * steps))
    f = other_lr_factor(step, preset)
    assert math.isfinite(f) and final * (1 - 1e-9) <= f <= 1.0
    assert other_lr_factor(step + 1, preset) <= f  # never rises


@pytest.mark.parametrize("field, value, message", [
    ("lr_decay_final", 0.0, r"learning_rates\.lr_decay_final must be in \(0, 1\], got 0\.0"),
    ("lr_decay_final", 1.5, r"learning_rates\.lr_decay_final must be in"),
    ("lr_decay_final", float("nan"), r"learning_rates\.lr_decay_final must be in"),
    ("learning_rates.lr_decay_start", -1, r"learning_rates\.lr_decay_start must be >= 0, got -1"),
])
def test_bad_annealing_settings_name_the_field(field: str, value: float, message: str) -> None:
    with pytest.raises(BraveError, match=f"preset fast: {message}"):
        FAST.with_overrides(**{field: value})


def test_a_start_past_the_last_step_means_constant_rates() -> None:
    late = FAST.with_overrides(steps=100, coarse_steps=0)  # lr_decay_start 600 > 100 steps
    assert [other_lr_factor(s, late) for s in (0, 50, 100, 1000)] == [1.0] * 4


def test_the_start_scales_with_the_run_length() -> None:
    short = FAST.with_steps(FAST.steps // 10)
    assert short.learning_rates.lr_decay_start == FAST.learning_rates.lr_decay_start // 10
    assert other_lr_factor(short.steps, short) == pytest.approx(0.1)


def test_a_training_step_sets_the_annealed_rates() -> None:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
    poses = [p for _, _, p in ring_poses([0.35], 4, elevation_deg=40)]
    images = render_views(random_gaussians(60, seed=1, extent=0.06), cam, poses)
    views = [View(i, f"v{i}", 0, 0.35, pose, img) for i, (pose, img) in enumerate(zip(poses, images))]
    data = TrainingData(cam, views[:3], views[3:])
    preset = FAST.with_steps(20).with_overrides(downscale=1, coarse_steps=0, lr_decay_start=5, time_budget_s=None)
    model = GaussianModel.from_points(np.random.default_rng(0).normal(0, 0.03, (50, 3)), None, sh_degree=2)
    trainer = Trainer(data, model, preset, None, show_progress=False)
    for _ in range(12):
        trainer.train_step()
    last = trainer.step - 1  # the rates in force were set for the last step taken
    factor = other_lr_factor(last, preset)
    assert factor < 0.6  # the schedule has visibly started
    for name, lr in base_lrs(preset).items():
        assert trainer.optimizers[name].param_groups[0]["lr"] == pytest.approx(lr * factor), name
    assert not model.non_finite()

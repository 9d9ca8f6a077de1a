"""Gaussian model initialisation and the densification strategy (gsplat 1.5.3 fix)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.training.model import GaussianModel, initial_log_scales
from brave6d.training.ply import SH_C0
from brave6d.training.presets import BENCHMARK_PRESETS, FAST, PRESETS, Densification, get_preset
from brave6d.training.strategy import DensifyStrategy


def test_init_from_points_follows_inria() -> None:
    pts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1], [0.1, 0.1, 0.1]], float)
    m = GaussianModel.from_points(pts, np.full((5, 3), 0.75), sh_degree=3, init_opacity=0.1)
    assert m.num_gaussians == 5
    assert torch.allclose(m.opacities(), torch.full((5,), 0.1))
    assert torch.equal(m.quats, torch.tensor([[1.0, 0, 0, 0]]).expand(5, 4))
    assert m.params["shN"].shape == (5, 15, 3) and not m.params["shN"].any()
    assert torch.allclose(0.5 + SH_C0 * m.params["sh0"][:, 0], torch.tensor(0.75))
    # origin: 3 nearest neighbours at 0.1 -> scale 0.1 on every axis
    assert torch.allclose(m.scales()[0], torch.full((3,), 0.1), rtol=1e-5)


@pytest.mark.parametrize("points", [
    np.zeros((1, 3)),  # a single point
    np.zeros((50, 3)),  # coincident points
    np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]),
    np.array([[0, 0, 0], [1e-12, 0, 0], [5.0, 5, 5]]),
])
def test_degenerate_point_sets_give_finite_scales(points: np.ndarray) -> None:
    m = GaussianModel.from_points(points)
    assert not m.non_finite()
    assert torch.all(m.scales() > 0)


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 40), seed=st.integers(0, 100), spread=st.sampled_from([0.0, 1e-9, 1e-3, 10.0]))
def test_initial_scales_always_finite(n: int, seed: int, spread: float) -> None:
    pts = np.random.default_rng(seed).standard_normal((n, 3)) * spread
    s = initial_log_scales(pts)
    assert s.shape == (n, 3) and np.isfinite(s).all()


def test_sh_coeffs_copy_only_the_degree_in_use() -> None:
    model = GaussianModel.from_points(np.random.default_rng(0).normal(size=(7, 3)), sh_degree=3)
    with torch.no_grad():
        model.params["shN"].copy_(torch.arange(7 * 15 * 3, dtype=torch.float32).reshape(7, 15, 3))
    full = torch.cat([model.params["sh0"], model.params["shN"]], dim=1)
    for d in range(4):
        coeffs = model.sh_coeffs(d)
        assert coeffs.shape == (7, (d + 1) ** 2, 3)
        assert torch.equal(coeffs, full[:, : (d + 1) ** 2])
    assert torch.equal(model.sh_coeffs(), full)
    assert model.sh_coeffs(0).data_ptr() == model.params["sh0"].data_ptr()  # degree 0: no copy
    model.sh_coeffs(2).sum().backward()  # gradient reaches both parameters, only where used
    assert torch.equal(model.params["shN"].grad[:, :8], torch.ones(7, 8, 3))
    assert torch.equal(model.params["shN"].grad[:, 8:], torch.zeros(7, 7, 3))
    with pytest.raises(ValueError, match="degree must be in 0..3"):
        model.sh_coeffs(4)


def test_nan_points_are_refused() -> None:
    with pytest.raises(ValueError, match="NaN"):
        GaussianModel.from_points(np.array([[0.0, np.nan, 0.0]]))


def _fake_info(n: int, grad: torch.Tensor) -> dict:
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = grad.reshape(1, n, 2)
    return {"means2d": means2d, "radii": torch.full((1, n, 2), 3, dtype=torch.int32), "width": 100,
            "height": 100, "n_cameras": 1, "gaussian_ids": None}


def _params_and_opts(n: int) -> tuple:
    m = GaussianModel.from_points(np.random.default_rng(0).random((n, 3)), sh_degree=1, init_opacity=0.9)
    opts = {k: torch.optim.Adam([m.params[k]], lr=1e-3) for k in m.params}
    return m, opts


def test_opacity_reset_happens_despite_gsplat_1_5_3_bug() -> None:
    n = 20
    m, opts = _params_and_opts(n)
    strat = DensifyStrategy(Densification(refine_start=1000, refine_stop=5000, reset_every=30))
    state = strat.initialize_state(scene_scale=1.0)
    info = _fake_info(n, torch.zeros(n, 2))
    strat.step_post_backward(m.params, opts, state, 29, info)
    assert torch.allclose(m.opacities(), torch.full((n,), 0.9))
    strat.step_post_backward(m.params, opts, state, 30, _fake_info(n, torch.zeros(n, 2)))
    assert torch.all(m.opacities() <= 0.01 + 1e-6)  # Inria: min(opacity, 0.01)
    # no reset once refinement has stopped
    m2, opts2 = _params_and_opts(n)
    strat.step_post_backward(m2.params, opts2, strat.initialize_state(), 6000, _fake_info(n, torch.zeros(n, 2)))
    assert torch.allclose(m2.opacities(), torch.full((n,), 0.9))


def test_growth_cap_keeps_the_highest_gradients() -> None:
    n = 30
    m, opts = _params_and_opts(n)
    strat = DensifyStrategy(Densification(refine_start=0, refine_every=1, reset_every=10_000, grow_grad2d=1e-6,
                                          max_gaussians=n + 5, prune_opa=0.0))
    state = strat.initialize_state(scene_scale=1000.0)  # all "small": growth duplicates
    grads = torch.zeros(n, 2)
    grads[:, 0] = torch.linspace(1e-3, 3e-2, n)  # every Gaussian qualifies
    strat.step_post_backward(m.params, opts, state, 1, _fake_info(n, grads))
    assert m.num_gaussians == n + 5
    before = m.params["means"].detach()[:n]
    # duplicates append copies of the selected (highest-gradient) Gaussians
    dup = m.params["means"].detach()[n:]
    assert all(any(torch.equal(d, before[i]) for i in range(n - 5, n)) for d in dup)


def test_presets_are_typed_and_scale_with_steps() -> None:
    assert set(PRESETS) == {"fast", "default", "quality"}
    d = get_preset("default")
    rates, densify = d.learning_rates, d.densification
    assert (d.steps, rates.means_lr_init, rates.means_lr_final, densify.refine_stop, densify.reset_every,
            densify.grow_grad2d) == (30_000, 1.6e-4, 1.6e-6, 15_000, 3000, 2e-4)
    half = d.with_steps(15_000)
    assert (half.densification.refine_stop, half.densification.reset_every,
            half.schedule.sh_degree_interval) == (7500, 1500, 500)
    assert FAST.time_budget_s is not None and FAST.time_budget_s <= 15 * 60
    with pytest.raises(Exception, match="unknown preset"):
        get_preset("turbo")
    assert math.isclose(rates.shN_lr * 20, rates.sh0_lr)
    # the fast schedule before issue 22 stays reachable for benchmarks, not as a user preset
    with pytest.raises(Exception, match="unknown preset 'fast-3000'"):
        get_preset("fast-3000")
    old = get_preset("fast-3000", BENCHMARK_PRESETS)
    assert (old.steps, old.schedule.coarse_steps, old.densification.max_gaussians, old.learning_rates.sh0_lr) == \
        (3000, 0, 150_000, rates.sh0_lr)
    assert FAST.schedule.coarse_steps > 0 and FAST.steps < old.steps
    assert FAST.densification.max_gaussians < old.densification.max_gaussians
    # and fast before its learning-rate annealing: the same schedule with constant rates
    unannealed = get_preset("fast-2000", BENCHMARK_PRESETS)
    assert (unannealed.learning_rates.lr_decay_final, FAST.learning_rates.lr_decay_final) == (1.0, 0.1)
    assert unannealed.with_values(name="fast", lr_decay_final=0.1, lr_decay_start=600, depth_lambda=FAST.loss.depth_lambda,
                                  antialiasing=FAST.antialias.antialiasing) == FAST


def test_the_strategy_reads_the_presets_own_options() -> None:
    """No copies under other names: the trainer's strategy holds ``preset.densification`` itself."""
    from brave6d.training.trainer import Trainer
    from brave6d.training.toy_scenes import random_gaussians, render_views, ring_poses
    from brave6d.training.views import TrainingData, View
    from brave6d.core.camera import PinholeCamera

    cam = PinholeCamera(16, 12, 15.0, 15.0, 7.5, 5.5)
    poses = [p for _, _, p in ring_poses([0.35], 2, elevation_deg=40)]
    images = render_views(random_gaussians(5, seed=0, extent=0.05), cam, poses)
    views = [View(i, f"v{i}", 0, 0.35, pose, img) for i, (pose, img) in enumerate(zip(poses, images))]
    model = GaussianModel.from_points(np.zeros((3, 3)) + np.arange(3)[:, None] * 0.01, None, sh_degree=1)
    preset = FAST.with_overrides(max_gaussians=1234)
    trainer = Trainer(TrainingData(cam, views[:1], views[1:]), model, preset, None, show_progress=False)
    assert trainer.strategy.options is preset.densification
    assert trainer.strategy.options.max_gaussians == 1234

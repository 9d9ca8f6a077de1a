"""The trainer's lean step (issue #46 item 2), proven on the CPU: the step a GPU runs without waiting
for the device (cameras checked once, no per-render value checks, the depth loss as masked sums, a
divergence flag kept on the device and read at curve points), forced on here with ``lean=True``.

Its GPU timing and host-sync count are `benchmarks/gpu_checks.py`'s; here: it trains to the same
model as the host-checked step, its pieces equal the host forms, and a NaN still stops training with
the step it first appeared at.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.training.depth_targets import DepthTarget, depth_loss
from brave6d.training.losses import psnr, psnr_tensor
from brave6d.training.model import GaussianModel
from brave6d.training.presets import get_preset
from brave6d.training.rasterizer import rasterize
from brave6d.training.toy_scenes import random_gaussians, render_views, ring_poses
from brave6d.training.trainer import Trainer, TrainingDiverged
from brave6d.training.views import TrainingData, View

FAST = get_preset("fast")


def _data() -> TrainingData:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
    poses = [p for _, _, p in ring_poses([0.35], 5, elevation_deg=40)]
    images = render_views(random_gaussians(60, seed=1, extent=0.06), cam, poses)
    views = [View(i, f"v{i}", 0, 0.35, pose, img) for i, (pose, img) in enumerate(zip(poses, images))]
    return TrainingData(cam, views[:4], views[4:])


def _trainer(lean: bool, steps: int = 40) -> Trainer:
    preset = FAST.with_steps(steps).with_overrides(downscale=1, coarse_steps=5, time_budget_s=None,
                                                   curve_every=10)
    model = GaussianModel.from_points(np.random.default_rng(0).normal(0, 0.03, (50, 3)), None, sh_degree=2)
    return Trainer(_data(), model, preset, None, show_progress=False, lean=lean)


def test_lean_trains_to_the_host_checked_model() -> None:
    """Without depth the two steps do the same arithmetic: the same parameters, bit for bit."""
    host = _trainer(False)  # each built and trained in turn: the trainer seeds torch's generator
    r_host = host.train()
    lean = _trainer(True)
    r_lean = lean.train()
    assert not host.lean and lean.lean
    assert r_host.steps == r_lean.steps == 40
    for name, p in host.model.params.items():
        assert torch.equal(p.detach(), lean.model.params[name].detach()), name
    for a, b in zip(r_host.curve, r_lean.curve):
        assert a["step"] == b["step"] and a["num_gaussians"] == b["num_gaussians"]
        assert b["train_psnr"] == pytest.approx(a["train_psnr"], abs=1e-3, nan_ok=True)  # float32 on the device
        assert b["loss"] == pytest.approx(a["loss"], rel=1e-5, nan_ok=True)


def test_the_default_is_lean_only_off_the_cpu() -> None:
    assert not Trainer(_data(), GaussianModel.from_points(np.zeros((5, 3)), None), FAST, None,
                       show_progress=False).lean


def test_a_nan_stops_the_lean_run_naming_the_step_it_appeared_at() -> None:
    trainer = _trainer(True, steps=40)
    original = trainer.strategy.step_post_backward

    def diverging(params, optimizers, state, step, info, packed=False):  # noqa: ANN001 - the strategy's
        original(params, optimizers, state, step, info, packed=packed)
        if step == 13:  # the 14th step's update goes wrong inside the step
            with torch.no_grad():
                params["opacities"][3] = float("nan")

    trainer.strategy.step_post_backward = diverging
    with pytest.raises(TrainingDiverged, match=r"at step 14: parameters hold NaN/inf \(now in [a-z, ]*opacities[a-z, ]*\), "
                                               r"first at this step"):
        trainer.train()
    assert trainer.step == 13  # read at the curve point of step 20, reported as it happened


def test_cameras_are_checked_once_at_the_start() -> None:
    data = _data()
    data.train[2].base_T_cam[0, 3] = float("nan")
    model = GaussianModel.from_points(np.zeros((5, 3)), None)
    with pytest.raises(DataError, match="training cameras: viewmats are not finite"):
        Trainer(data, model, FAST, None, show_progress=False, lean=True)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), share=st.floats(0.0, 1.0), alpha_min=st.floats(0.0, 1.0))
def test_masked_depth_loss_equals_the_gathered_one(seed: int, share: float, alpha_min: float) -> None:
    """Same value, same gradient, finite even where the render's depth is huge or the target 0."""
    g = torch.Generator().manual_seed(seed)
    h, w = 9, 7
    valid = torch.rand(h, w, generator=g) < share
    depth = torch.where(valid, 0.2 + torch.rand(h, w, generator=g), torch.zeros(h, w))
    target = DepthTarget(depth, valid)
    alpha = torch.rand(h, w, 1, generator=g)
    rendered = (0.2 + torch.rand(h, w, 1, generator=g)).masked_fill(alpha < 0.1, 1e30)
    grads = []
    for masked in (False, True):
        d = rendered.clone().requires_grad_(True)
        loss = depth_loss(d, alpha, target, alpha_min, masked_sums=masked)
        loss.backward()
        grads.append((float(loss), d.grad))
    (v_host, g_host), (v_lean, g_lean) = grads
    assert math.isfinite(v_lean) and torch.isfinite(g_lean).all()
    assert v_lean == pytest.approx(v_host, rel=1e-5, abs=1e-7)
    torch.testing.assert_close(g_lean, g_host, rtol=1e-5, atol=1e-7)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), share=st.floats(0.0, 1.0), constant=st.booleans())
def test_psnr_on_the_device_equals_the_host_psnr(seed: int, share: float, constant: bool) -> None:
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(6, 5, 3, generator=g)
    b = a.clone() if constant else torch.rand(6, 5, 3, generator=g)
    valid = torch.rand(6, 5, generator=g) < share
    for mask in (None, valid):
        got = psnr_tensor(a, b, mask)
        assert got.dim() == 0 and torch.isfinite(got)
        assert float(got) == pytest.approx(psnr(a, b, mask), abs=1e-3)


def test_rasterize_without_value_checks_renders_the_same() -> None:
    p = random_gaussians(40, seed=3, extent=0.05)
    viewmat = torch.eye(4)[None]
    viewmat[0, 2, 3] = 0.3
    K = torch.tensor([[[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]]])
    args = (p["means"], p["quats"], torch.exp(p["scales"]), torch.sigmoid(p["opacities"]),
            torch.rand(40, 3), viewmat, K, 32, 24)
    checked = rasterize(*args)
    unchecked = rasterize(*args, validate=False)
    for a, b in zip(checked[:3], unchecked[:3]):
        assert torch.equal(a, b)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_lean_step_waits_for_the_device_at_most_4_times_per_step(record_property) -> None:
    """Issue #46's target, counted with CUDA's sync debug mode over 30 steps past the coarse phase."""
    import warnings

    preset = FAST.with_steps(120).with_overrides(downscale=1, coarse_steps=5, time_budget_s=None)
    model = GaussianModel.from_points(np.random.default_rng(0).normal(0, 0.03, (50, 3)), None, sh_degree=2)
    trainer = Trainer(_data(), model, preset, None, device="cuda", show_progress=False)
    assert trainer.lean
    trainer.train(max_steps=40)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            for _ in range(30):
                trainer.train_step()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    syncs = sum("synchroniz" in str(w.message) for w in caught) / 30
    record_property("host_syncs_per_step", syncs)
    assert syncs <= 4
    trainer.raise_if_flagged()
    assert not trainer.model.non_finite()

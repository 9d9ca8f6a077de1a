"""Mip-Splatting's 3D smoothing filter: its value from the training cameras, how it changes the
Gaussians, the PLY property that carries it, and training with ``antialiasing: mip`` (issue 34)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, DataError
from brave6d.training import apply_filter_3d, compute_filter_3d, read_ply, write_ply
from brave6d.training.filter3d import scale_range
from brave6d.training.holdout_eval import render_view
from brave6d.training.model import GaussianModel
from brave6d.training.presets import Preset, get_preset
from brave6d.training.toy_scenes import gaussian_ring_data, random_gaussians
from brave6d.training.trainer import Trainer
from brave6d.training.views import TrainingData

F, W, H = 100.0, 64, 48
K = torch.tensor([[F, 0.0, 31.5], [0.0, F, 23.5], [0.0, 0.0, 1.0]])


def _cam_at(z: float) -> torch.Tensor:
    """A camera on the optical axis at world z = -z looking along +z (world_T_cam = translation)."""
    vm = torch.eye(4)
    vm[2, 3] = z
    return vm


def test_filter_is_set_by_the_closest_camera_that_sees_the_gaussian() -> None:
    means = torch.tensor([[0.0, 0.0, 0.0],     # seen by both cameras at 1 m and 2 m
                          [0.05, 0.0, 0.0],     # in view
                          [100.0, 0.0, 0.0],    # outside every view: the widest filter of those seen
                          [0.0, 0.0, -5.0]])    # behind both cameras: likewise
    viewmats = torch.stack([_cam_at(2.0), _cam_at(1.0)])
    f3d = compute_filter_3d(means, viewmats, K, W, H, scale=0.2)
    assert f3d[0] == pytest.approx(math.sqrt(0.2) * 1.0 / F, rel=1e-6)
    assert f3d[1] == pytest.approx(math.sqrt(0.2) * 1.0 / F, rel=1e-6)
    assert f3d[2] == pytest.approx(float(f3d[:2].max()), rel=1e-6)
    assert f3d[3] == pytest.approx(float(f3d[:2].max()), rel=1e-6)
    only_far = compute_filter_3d(means[:2], viewmats[:1], K, W, H, scale=0.2)
    assert only_far[0] == pytest.approx(math.sqrt(0.2) * 2.0 / F, rel=1e-6)
    assert torch.all(compute_filter_3d(means[3:], viewmats, K, W, H) == 0), "unseen by all: no filter"


def test_apply_filter_3d_widens_and_keeps_the_integral() -> None:
    s, f, o = 0.003, 0.004, 0.8
    scales, opac = apply_filter_3d(torch.full((1, 3), s), torch.tensor([o]), torch.tensor([f]))
    assert float(scales[0, 0]) == pytest.approx(0.005, rel=1e-6)
    # opacity * sqrt(det S / det(S + f^2 I)) = o * (s^2 / (s^2 + f^2))^(3/2): peak * volume is kept
    assert float(opac[0]) == pytest.approx(o * (9 / 25) ** 1.5, rel=1e-6)
    unfiltered = (torch.full((1, 3), s), torch.tensor([o]))
    same = apply_filter_3d(*unfiltered, None)
    assert same[0] is unfiltered[0] and same[1] is unfiltered[1]
    with pytest.raises(ValueError, match="one value per Gaussian"):
        apply_filter_3d(torch.ones(2, 3), torch.ones(2), torch.ones(3))


def _finite_values_and_gradients(scale: list[float], opacity: float, filt: float) -> tuple[torch.Tensor, torch.Tensor]:
    scales = torch.tensor([scale], dtype=torch.float32, requires_grad=True)
    opac = torch.tensor([opacity], requires_grad=True)
    s_eff, o_eff = apply_filter_3d(scales, opac, torch.tensor([filt]))
    (s_eff.sum() + o_eff.sum()).backward()
    assert bool(torch.isfinite(s_eff).all() and torch.isfinite(o_eff).all()), (s_eff, o_eff)
    assert bool(torch.isfinite(scales.grad).all() and torch.isfinite(opac.grad).all()), (scales.grad, opac.grad)
    assert 0.0 <= float(o_eff.detach()) <= opacity + 1e-7
    assert bool((s_eff >= filt * (1 - 1e-6)).all())
    return s_eff.detach(), o_eff.detach()


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(st.floats(0.0, 1e4, width=32), st.floats(0.0, float(torch.finfo(torch.float32).max), width=32)), min_size=3, max_size=3),
       st.floats(0.0, 1.0), st.floats(0.0, 10.0))
def test_apply_filter_3d_is_finite_for_tiny_and_huge_gaussians(scale, opacity, filt) -> None:
    """Gaussians far smaller than the filter, zero and subnormal scales, scales up to float32's
    largest: finite values and gradients, opacity factor in [0, 1], scales never below the filter,
    and within the filter's scale range exactly ``sqrt(scale^2 + filter^2)`` (no silent change)."""
    s_eff, _ = _finite_values_and_gradients(scale, opacity, filt)
    lo, hi = scale_range(torch.float32)
    f32 = float(torch.tensor(filt, dtype=torch.float32))
    for axis, s in enumerate(scale):
        if lo <= s <= hi:
            assert float(s_eff[0, axis]) == pytest.approx(math.hypot(s, f32), rel=1e-6)


def test_apply_filter_3d_gradients_stay_finite_at_subnormal_and_overflowing_scales() -> None:
    """Hypothesis's find in CI: a subnormal square (1.1e-20 squared) with no filter made
    ``1 / (s^2 + f^2)`` overflow and the scale's gradient NaN; squares past float32's largest
    made the values inf and NaN."""
    for scale, filt in [([0.0, 0.0, 1.0865952303180257e-20], 0.0), ([1e-20] * 3, 1e-20),
                        ([1e-45] * 3, 1e-45), ([3e38, 1.0, 1e-3], 0.01), ([1e20] * 3, 1.0)]:
        s_eff, o_eff = _finite_values_and_gradients(scale, 0.5, filt)
        assert float(s_eff.max()) <= scale_range(torch.float32)[1] * (1 + 1e-6)
    _, o_eff = _finite_values_and_gradients([0.0, 0.0, 0.0], 0.5, 0.01)
    assert float(o_eff) < 1e-18, "a zero-size Gaussian under a filter keeps (almost) none of its opacity"


def test_ply_carries_the_filter_and_an_older_ply_reads_as_none(tmp_path: Path) -> None:
    model = GaussianModel.from_points(np.random.default_rng(0).normal(size=(20, 3)), sh_degree=1)
    plain = read_ply(model.save_ply(tmp_path / "plain.ply"))
    assert plain.filter_3d is None
    assert not GaussianModel.from_splat(plain).antialiased
    model.filter_3d = torch.linspace(0.001, 0.002, 20)
    back = read_ply(model.save_ply(tmp_path / "mip.ply"))
    np.testing.assert_array_equal(back.filter_3d, model.filter_3d.numpy())
    loaded = GaussianModel.from_splat(back)
    assert loaded.antialiased
    torch.testing.assert_close(loaded.filter_3d, model.filter_3d)
    bad = model.to_splat()
    bad.filter_3d = -bad.filter_3d
    with pytest.raises(DataError, match=r"bad\.ply.*filter_3d"):
        read_ply(write_ply(tmp_path / "bad.ply", bad))


def test_presets_default_classic_fast_and_quality_mip_and_bad_values_named() -> None:
    assert get_preset("default").antialias.antialiasing == "classic"
    assert get_preset("fast").antialias.antialiasing == "mip"
    assert get_preset("quality").antialias.antialiasing == "mip"
    assert Preset(name="x").with_values(antialiasing="mip", filter_3d_scale=0.1).to_json()["antialiasing"] == "mip"
    with pytest.raises(BraveError, match="antialias.antialiasing"):
        Preset(name="x").with_values(antialiasing="msaa")
    with pytest.raises(BraveError, match="antialias.filter_3d_scale"):
        Preset(name="x").with_values(filter_3d_scale=-1.0)


CAM = PinholeCamera(48, 36, 40.0, 40.0, 23.5, 17.5)


def _tiny_data() -> TrainingData:
    return gaussian_ring_data(CAM)


def test_training_with_mip_keeps_the_filter_in_step_with_densification(tmp_path: Path) -> None:
    data = _tiny_data()
    pts = random_gaussians(150, seed=1, extent=0.08)["means"].numpy()
    preset = Preset(name="tiny").with_values(
        steps=40, sh_degree=1, refine_start=10, refine_stop=35, refine_every=8, reset_every=30,
        grow_grad2d=1e-4, max_gaussians=400, antialiasing="mip", filter_3d_every=10)
    trainer = Trainer(data, GaussianModel.from_points(pts, None, sh_degree=1, init_opacity=0.3), preset,
                      show_progress=False)
    trainer.train()
    m = trainer.model
    assert m.num_gaussians != 150, "densification did not run: the test is vacuous"
    assert m.filter_3d is not None and m.filter_3d.shape == (m.num_gaussians,)
    # the exported filter is that of the final means and the training cameras
    expected = compute_filter_3d(m.means, trainer.viewmats, trainer.K, CAM.width, CAM.height, 0.2)
    torch.testing.assert_close(m.filter_3d, expected)
    assert bool((m.filter_3d > 0).all())
    # the holdout render applies both filters; without them the picture differs
    with_filters = render_view(m, data.test[0], data)
    f3d, m.filter_3d = m.filter_3d, None
    without = render_view(m, data.test[0], data)
    m.filter_3d = f3d
    assert float((with_filters - without).abs().max()) > 1e-3

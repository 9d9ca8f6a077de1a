"""Undistortion's border pixels (no raw data) neither train nor score."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.training.views import valid_pixels
from brave6d.training.losses import fill_invalid, photometric_loss, psnr

BARREL = PinholeCamera(160, 100, 115.0, 115.0, 79.5, 49.5, (0.05, -0.16, 0.0, 0.0, 0.23))


def test_no_distortion_means_every_pixel_is_valid() -> None:
    assert valid_pixels(BARREL.without_distortion(), 160, 100) is None


def test_distorted_camera_loses_its_corners_only() -> None:
    valid = valid_pixels(BARREL, 160, 100)
    assert valid is not None and valid.shape == (100, 160)
    assert not valid[0, 0] and not valid[-1, -1] and valid[50, 80]
    assert 0 < (~valid).sum() < 0.2 * valid.size
    half = valid_pixels(BARREL, 80, 50)
    assert half is not None and half.shape == (50, 80) and not half[0, 0] and half[25, 40]


def test_what_the_border_holds_changes_neither_loss_nor_gradient() -> None:
    valid = torch.from_numpy(valid_pixels(BARREL, 160, 100))
    torch.manual_seed(0)
    target = torch.rand(100, 160, 3)
    render = torch.rand(100, 160, 3)
    results = []
    for border in (torch.zeros_like(target), torch.ones_like(target), torch.rand_like(target)):
        gt = torch.where(valid[..., None], target, border)
        r = render.clone().requires_grad_(True)
        loss, _, _ = photometric_loss(r, fill_invalid(gt, r, valid), 0.2)
        loss.backward()
        results.append((float(loss.detach()), r.grad.clone(), psnr(r, gt, valid)))
    for loss, grad, value in results[1:]:
        assert loss == results[0][0] and value == results[0][2]
        assert torch.equal(grad, results[0][1])


def test_a_perfect_render_scores_perfectly_despite_black_borders() -> None:
    valid = torch.from_numpy(valid_pixels(BARREL, 160, 100))
    target = torch.rand(100, 160, 3, generator=torch.Generator().manual_seed(1))
    black_borders = torch.where(valid[..., None], target, torch.zeros_like(target))
    loss, _, _ = photometric_loss(target, fill_invalid(black_borders, target, valid), 0.2)
    assert float(loss) < 1e-6
    assert psnr(target, black_borders, valid) >= 99.0
    assert psnr(target, black_borders) < 20.0  # without the mask the borders dominate


@settings(max_examples=25)
@given(k1=st.floats(-0.3, 0.3), k2=st.floats(-0.3, 0.3), k3=st.floats(-0.5, 0.5), scale=st.sampled_from([1, 2, 4]))
def test_mask_is_finite_and_keeps_the_centre(k1: float, k2: float, k3: float, scale: int) -> None:
    cam = PinholeCamera(160, 100, 115.0, 115.0, 79.5, 49.5, (k1, k2, 0.0, 0.0, k3))
    valid = valid_pixels(cam, 160 // scale, 100 // scale)
    if valid is not None:
        assert valid.dtype == np.bool_ and valid[50 // scale, 80 // scale]
        t = torch.rand(100 // scale, 160 // scale, 3)
        value = psnr(t, torch.zeros_like(t), torch.from_numpy(valid))
        assert np.isfinite(value)

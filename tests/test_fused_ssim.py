"""The CPU training loss's fused SSIM against the torch reference (Inria's SSIM): value and gradient."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from brave6d.training.fused_ssim import blur_planes, can_fuse, fused_ssim
from brave6d.training.losses import gaussian_window, photometric_loss, ssim


def _value_and_grad(fn, render: torch.Tensor, target: torch.Tensor) -> tuple[float, torch.Tensor]:
    x = render.clone().requires_grad_(True)
    value = fn(x, target)
    value.backward()
    return float(value.detach()), x.grad


def _assert_matches_reference(render: torch.Tensor, target: torch.Tensor) -> None:
    """Against the torch reference in float64, to within the float32 torch reference's own error
    (E[x^2] - mu^2 cancels in float32 on flat images) plus a small floor."""
    ref_value, ref_grad = _value_and_grad(ssim, render.double(), target.double())
    f32_value, f32_grad = _value_and_grad(ssim, render, target)
    value, grad = _value_and_grad(fused_ssim, render, target)
    assert np.isfinite(value) and torch.isfinite(grad).all()
    assert abs(value - ref_value) <= max(5e-5, 3.0 * abs(f32_value - ref_value))
    grad_err, f32_grad_err = (float((g.double() - ref_grad).abs().max()) for g in (grad, f32_grad))
    assert grad_err <= 2e-3 * float(ref_grad.abs().max()) + max(3e-6, 3.0 * f32_grad_err)


@given(h=st.integers(1, 40), w=st.integers(1, 40), channels=st.sampled_from([1, 3]), seed=st.integers(0, 2**31 - 1))
def test_value_and_gradient_equal_the_reference_at_any_size(h: int, w: int, channels: int, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    _assert_matches_reference(torch.rand(h, w, channels, generator=g), torch.rand(h, w, channels, generator=g))


@given(level=st.floats(0.0, 1.0), other=st.floats(0.0, 1.0), h=st.integers(1, 24), w=st.integers(1, 24))
def test_constant_images_stay_finite_and_match(level: float, other: float, h: int, w: int) -> None:
    """Zero variance inside, a cut window at the border: the C1/C2 terms keep every denominator
    positive."""
    render = torch.full((h, w, 3), level)
    _assert_matches_reference(render, torch.full((h, w, 3), other))
    _assert_matches_reference(render, render.clone())


@given(level=st.floats(0.0, 1.0), other=st.floats(0.0, 1.0), h=st.integers(1, 24), w=st.integers(1, 24))
def test_flat_images_have_no_float32_cancellation(level: float, other: float, h: int, w: int) -> None:
    """On flat images the variances are E[x^2] - mu^2 of two equal numbers near 0.6; in float32 that
    cancellation left errors of 5e-5 against C2 = 9e-4 (hypothesis found 0.78125 vs 0.9036 at 16x19).
    The moments are blurred in float64, so the value is the float64 reference's to float32 rounding."""
    render, target = torch.full((h, w, 3), level), torch.full((h, w, 3), other)
    value = float(fused_ssim(render, target))
    assert abs(value - float(ssim(render.double(), target.double()))) <= 1e-6


def test_identical_images_score_one_with_zero_gradient() -> None:
    img = torch.rand(30, 50, 3, generator=torch.Generator().manual_seed(1))
    value, grad = _value_and_grad(fused_ssim, img, img.clone())
    assert value == pytest.approx(1.0, abs=1e-6)
    assert float(grad.abs().max()) < 1e-6


def test_blur_is_the_zero_padded_gaussian_window() -> None:
    """One plane with a single bright pixel next to the border: the blur is the window, cut at the border."""
    src = np.zeros((1, 9, 12), np.float32)
    src[0, 1, 10] = 1.0
    out = np.empty_like(src)
    taps = gaussian_window().numpy().astype(np.float32)
    blur_planes(src, taps, out)
    g = taps.astype(np.float64)
    expected = np.zeros((9, 12))
    for i in range(9):
        for j in range(12):
            di, dj = i - 1 + 5, j - 10 + 5
            if 0 <= di < 11 and 0 <= dj < 11:
                expected[i, j] = g[di] * g[dj]
    np.testing.assert_allclose(out[0], expected, atol=1e-7)


def test_the_training_loss_uses_it_on_the_cpu_and_gives_the_reference_gradient() -> None:
    g = torch.Generator().manual_seed(3)
    render, target = torch.rand(20, 30, 3, generator=g), torch.rand(20, 30, 3, generator=g)
    assert can_fuse(render, target)
    x = render.clone().requires_grad_(True)
    loss, _, s = photometric_loss(x, target, 0.2)
    loss.backward()
    y = render.clone().requires_grad_(True)
    ref = 0.8 * (y - target).abs().mean() + 0.2 * (1.0 - ssim(y, target))
    ref.backward()
    assert float(loss) == pytest.approx(float(ref), abs=1e-6)
    assert float((x.grad - y.grad).abs().max()) <= 1e-4 * float(y.grad.abs().max())


def test_inputs_it_does_not_cover_are_refused_by_name() -> None:
    img = torch.rand(8, 8, 3)
    assert not can_fuse(img.double(), img.double()) and not can_fuse(img[None], img[None])
    assert not can_fuse(img, img.clone().requires_grad_(True))
    with pytest.raises(ValueError, match="float32 CPU images"):
        fused_ssim(img.double(), img.double())

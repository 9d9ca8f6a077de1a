"""SSIM (Inria: 11x11 Gaussian window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2), L1 and PSNR."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.training.losses import gaussian_window, l1_loss, photometric_loss, psnr, ssim, ssim_map


def reference_ssim_map(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Direct per-pixel SSIM (H, W, C) in float64: explicit weighted sums over the 11x11 window,
    pixels outside the image counting as zero (Inria's zero padding)."""
    h, w, c = x.shape
    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5**2))
    win = np.outer(g, g) / np.outer(g, g).sum()
    xp = np.zeros((h + 10, w + 10, c))
    yp = np.zeros((h + 10, w + 10, c))
    xp[5:-5, 5:-5] = x
    yp[5:-5, 5:-5] = y
    out = np.zeros((h, w, c))
    c1, c2 = 0.01**2, 0.03**2
    for i in range(h):
        for j in range(w):
            px, py = xp[i:i + 11, j:j + 11], yp[i:i + 11, j:j + 11]
            for ch in range(c):
                a, b = px[..., ch], py[..., ch]
                mx, my = (win * a).sum(), (win * b).sum()
                vx = (win * a * a).sum() - mx * mx
                vy = (win * b * b).sum() - my * my
                cxy = (win * a * b).sum() - mx * my
                out[i, j, ch] = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return out


def test_window_is_normalised_gaussian() -> None:
    g = gaussian_window()
    assert g.shape == (11,)
    assert math.isclose(float(g.sum()), 1.0, rel_tol=1e-6)
    assert math.isclose(float(g[5] / g[4]), math.exp(1 / (2 * 1.5**2)), rel_tol=1e-5)


@settings(max_examples=20, deadline=None)
@given(h=st.integers(1, 24), w=st.integers(1, 24), seed=st.integers(0, 2**31 - 1))
def test_identical_images_give_one(h: int, w: int, seed: int) -> None:
    img = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(seed))
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_direct_formula(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = rng.random((13, 17, 3))
    y = np.clip(x + 0.2 * rng.standard_normal(x.shape), 0, 1)
    got = ssim_map(torch.from_numpy(x).float(), torch.from_numpy(y).float())[0].permute(1, 2, 0).numpy()
    want = reference_ssim_map(x, y)
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert float(ssim(torch.from_numpy(x).float(), torch.from_numpy(y).float())) == pytest.approx(want.mean(), abs=2e-6)


def test_constant_images_are_finite_and_sensible() -> None:
    a = torch.full((20, 20, 3), 0.3)
    b = torch.full((20, 20, 3), 0.7)
    zero = torch.zeros(20, 20, 3)
    for u, v in ((a, a), (a, b), (zero, zero), (zero, b)):
        s = float(ssim(u, v))
        assert math.isfinite(s) and -1.0 <= s <= 1.0 + 1e-6
    # interior pixels of two constants: (2ab + C1) / (a^2 + b^2 + C1)
    centre = float(ssim_map(a, b)[0, 0, 10, 10])
    assert centre == pytest.approx((2 * 0.3 * 0.7 + 1e-4) / (0.09 + 0.49 + 1e-4), rel=1e-3)  # float32 variances
    assert float(ssim(zero, zero)) == pytest.approx(1.0)


def test_batched_equals_single() -> None:
    g = torch.Generator().manual_seed(3)
    x, y = torch.rand(2, 9, 11, 3, generator=g), torch.rand(2, 9, 11, 3, generator=g)
    both = ssim_map(x, y)
    assert torch.allclose(both[1], ssim_map(x[1], y[1])[0])


def test_loss_gradients_are_finite() -> None:
    x = torch.rand(16, 16, 3, requires_grad=True)
    loss, l1, s = photometric_loss(x, torch.full((16, 16, 3), 0.5))
    loss.backward()
    assert torch.isfinite(x.grad).all()
    assert float(loss.detach()) == pytest.approx(0.8 * float(l1.detach()) + 0.2 * (1 - float(s.detach())), rel=1e-6)


def test_shape_mismatch_raises() -> None:
    with pytest.raises(ValueError, match="shapes differ"):
        ssim(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))


def test_psnr_and_l1_values() -> None:
    a = torch.zeros(8, 8, 3)
    b = torch.full((8, 8, 3), 0.1)
    assert psnr(a, b) == pytest.approx(20.0, abs=1e-4)
    assert float(l1_loss(a, b)) == pytest.approx(0.1)
    assert psnr(a, a) == pytest.approx(100.0)

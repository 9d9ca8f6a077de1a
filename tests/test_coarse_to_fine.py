"""Coarse-to-fine training (``Schedule.coarse_steps`` of a preset): the first steps train on 2x2-averaged images
with matching intrinsics, then the training resolution; exact geometry, finite results."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.training import GaussianModel, get_preset, load_scene
from brave6d.training.toy_scenes import plane_views, write_scene
from brave6d.training.trainer import CoarseLevel, Trainer, half_image, half_intrinsics

CAM = PinholeCamera.from_hfov(64, 48, 60.0)
finite = st.floats(-1e3, 1e3, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(fx=st.floats(1.0, 5e3), fy=st.floats(1.0, 5e3), cx=finite, cy=finite, x=finite, y=finite,
       z=st.floats(1e-3, 1e3))
def test_half_intrinsics_keep_pixel_centres(fx: float, fy: float, cx: float, cy: float, x: float, y: float,
                                            z: float) -> None:
    """A point at full-resolution pixel u lands at (u + 0.5) / 2 - 0.5 in the half-resolution image."""
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float64)
    H = half_intrinsics(K)
    p = torch.tensor([x, y, z], dtype=torch.float64)
    full, half = (K @ p)[:2] / z, (H @ p)[:2] / z
    assert torch.all(torch.isfinite(half))
    torch.testing.assert_close(half, (full + 0.5) / 2 - 0.5, rtol=1e-12, atol=1e-9)


def test_half_image_averages_blocks_and_drops_an_odd_edge() -> None:
    image = torch.arange(5 * 7 * 3, dtype=torch.int64).reshape(5, 7, 3).to(torch.uint8)
    small = half_image(image)
    assert small.shape == (2, 3, 3) and small.dtype == torch.uint8
    assert int(small[1, 2, 0]) == round(float(image[2:4, 4:6, 0].float().mean()))
    constant = torch.full((4, 4, 3), 200, dtype=torch.uint8)
    assert torch.all(half_image(constant) == 200)  # a constant image stays constant (no drift, no overflow)


def test_coarse_valid_mask_needs_all_four_pixels() -> None:
    valid = torch.ones(4, 6, dtype=torch.bool)
    valid[0, 0] = False
    level = CoarseLevel.of([torch.zeros(4, 6, 3, dtype=torch.uint8)], torch.eye(3), valid)
    assert level.valid is not None and level.valid.tolist() == [[False, True, True], [True, True, True]]
    assert (level.width, level.height) == (3, 2)
    with pytest.raises(BraveError, match="at least 2x2"):
        CoarseLevel.of([torch.zeros(1, 6, 3, dtype=torch.uint8)], torch.eye(3), None)


def test_trainer_renders_coarse_first_then_full(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "scene", CAM, plane_views(CAM, [0.3, 0.45], per_ring=5))
    preset = get_preset("fast").with_steps(6).with_overrides(downscale=1, coarse_steps=3, max_init_points=500,
                                                             time_budget_s=None)
    data = load_scene(scene, 1)
    rng = np.random.default_rng(0)
    start = preset.initialisation
    model = GaussianModel.from_points(rng.uniform(-0.05, 0.05, (300, 3)), rng.uniform(0, 1, (300, 3)),
                                      start.sh_degree, start.init_opacity, start.init_scale, device="cpu")
    trainer = Trainer(data, model, preset, None, "cpu", show_progress=False)
    sizes = []
    original = trainer.render

    def spy(viewmat, sh_degree=None, level=None, validate=True):  # records the size each step renders at
        out = original(viewmat, sh_degree, level, validate)
        sizes.append(tuple(out[0].shape[:2]))
        return out

    trainer.render = spy  # type: ignore[method-assign]
    result = trainer.train()
    assert result.steps == 6
    assert sizes == [(24, 32)] * 3 + [(48, 64)] * 3
    assert all(bool(torch.isfinite(p).all()) for p in trainer.model.params.values())


def test_coarse_steps_are_validated_and_scaled() -> None:
    with pytest.raises(BraveError, match="coarse_steps must be in 0..steps"):
        get_preset("fast").with_overrides(coarse_steps=10**6)
    fast = get_preset("fast")
    assert fast.with_overrides(coarse_steps=1000).with_steps(fast.steps // 10).schedule.coarse_steps == 100

"""Training with the captured depth (``Loss.depth_lambda``): targets left out where the sensor has no
data or a depth edge, a relative L1 on the rendered depth, and a trained plane whose depth follows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, DataError
from brave6d.training import GaussianModel, get_preset, load_scene
from brave6d.training.depth_targets import (DepthTarget, block_average, depth_loss, depth_target, drop_edges,
                                            load_depth_targets)
from brave6d.training.toy_scenes import plane_views, write_scene
from brave6d.training.trainer import Trainer

CAM = PinholeCamera.from_hfov(64, 48, 60.0)


def test_block_average_leaves_out_holes_and_edges() -> None:
    depth = np.full((4, 6), 0.30, np.float32)
    depth[0, 0] = 0.0  # a hole: its block has no target
    depth[2:4, 4] = 0.50  # a depth step inside the last block of the second row
    mean, keep = block_average(depth, 2)
    assert keep.tolist() == [[False, True, True], [True, True, False]]
    assert mean[0, 1] == pytest.approx(0.30) and mean[0, 0] == 0.0 and mean[1, 2] == 0.0


def test_drop_edges_removes_both_sides_of_a_step_and_the_rim_of_a_hole() -> None:
    depth = np.full((5, 5), 0.3, np.float32)
    depth[:, 3:] = 0.4
    valid = np.ones((5, 5), bool)
    valid[0, 0] = False
    keep = drop_edges(depth, valid)
    assert not keep[:, 2].any() and not keep[:, 3].any()  # both sides of the step
    assert not keep[0, 1] and not keep[1, 0] and not keep[1, 1]  # next to the hole
    assert keep[3, 0] and keep[3, 4]


def test_depth_target_needs_an_integer_factor_and_says_which_sizes() -> None:
    with pytest.raises(DataError, match="64x48 depth image does not shrink to 30x20"):
        depth_target(np.ones((48, 64), np.float32), 30, 20)
    assert depth_target(None, 32, 24) is None
    assert depth_target(np.zeros((48, 64), np.float32), 32, 24) is None  # an all-invalid frame: no target


@settings(max_examples=60, deadline=None)
@given(depth=arrays(np.float32, (8, 12), elements=st.one_of(
    st.just(0.0), st.just(np.inf), st.just(np.nan), st.floats(2**-20, 2**20, width=32))))
def test_targets_of_any_depth_image_are_finite_and_positive_where_valid(depth: np.ndarray) -> None:
    """Holes, NaN, inf, depths far outside any range: the target is finite and > 0 where valid, 0 elsewhere."""
    target = depth_target(depth, 6, 4)
    if target is None:
        return
    d, v = target.depth.numpy(), target.valid.numpy()
    assert np.isfinite(d).all() and (d[v] > 0).all() and (d[~v] == 0).all()


@settings(max_examples=40, deadline=None)
@given(scale=st.floats(1e-4, 1e4), alpha=st.floats(0.0, 1.0))
def test_depth_loss_is_finite_and_zero_without_pixels(scale: float, alpha: float) -> None:
    target = DepthTarget(torch.full((4, 4), 0.3), torch.ones(4, 4, dtype=torch.bool))
    render = torch.full((4, 4, 1), 0.3 * scale, requires_grad=True)
    loss = depth_loss(render, torch.full((4, 4, 1), alpha), target)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(render.grad).all()
    if alpha < 0.5:
        assert float(loss.detach()) == 0.0  # a transparent render has no defined depth: no term
    else:
        assert float(loss.detach()) == pytest.approx(abs(scale - 1.0), rel=1e-5, abs=1e-6)  # float32 depths


def test_depth_lambda_is_checked() -> None:
    with pytest.raises(BraveError, match="depth_lambda must be a finite number >= 0"):
        get_preset("fast").with_overrides(depth_lambda=-1.0)
    with pytest.raises(BraveError, match="depth_edge_ratio must be in"):
        get_preset("fast").with_overrides(depth_edge_ratio=0.0)


def _train(scene: Path, depth_lambda: float, steps: int = 150) -> Trainer:
    preset = get_preset("fast").with_steps(steps).with_overrides(
        downscale=1, coarse_steps=steps // 4, max_init_points=500, time_budget_s=None, depth_lambda=depth_lambda,
        refine_start=10**6, refine_stop=10**6)
    data = load_scene(scene, 1)
    rng = np.random.default_rng(0)
    start = preset.initialisation
    # Gaussians spread 4 cm above and below the plane z = 0: only depth says where the plane is
    points = np.c_[rng.uniform(-0.12, 0.12, (600, 2)), rng.uniform(-0.04, 0.04, 600)]
    model = GaussianModel.from_points(points, rng.uniform(0, 1, (600, 3)), start.sh_degree, 0.5, 1.0, device="cpu")
    trainer = Trainer(data, model, preset, None, "cpu", show_progress=False)
    trainer.train()
    return trainer


def _depth_error(trainer: Trainer) -> float:
    """Median |rendered depth - plane depth| (m) over the training views' opaque pixels."""
    errors = []
    targets = load_depth_targets(trainer.data, 0.02)
    with torch.no_grad():
        for i, target in enumerate(targets):
            assert target is not None
            _, alpha, info = trainer.render(trainer.viewmats[i])
            use = target.valid & (alpha[..., 0] > 0.5)
            errors.append((info["render_depth"][..., 0][use] - target.depth[use]).abs())
    return float(torch.cat(errors).median())


def test_depth_loss_pulls_the_rendered_depth_onto_the_plane(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "scene", CAM, plane_views(CAM, [0.3, 0.45], per_ring=4))
    without, with_depth = _train(scene, 0.0), _train(scene, 2.0)
    assert all(bool(torch.isfinite(p).all()) for p in with_depth.model.params.values())
    assert _depth_error(with_depth) < 0.3 * _depth_error(without)


def test_views_without_depth_train_on_colour(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    scene = write_scene(tmp_path / "scene", CAM, plane_views(CAM, [0.3], per_ring=4), with_depth=False)
    trainer = _train(scene, 1.0, steps=8)
    assert trainer.step == 8
    assert "none of the" in caplog.text and "has usable depth" in caplog.text

"""The rasterizer's median depth (``rasterize(..., median_depth=True)``): the depth of the Gaussian that
takes a pixel's transmittance across 0.5, checked against the pure-torch reference, never between
a foreground and a background surface, and free for callers that do not ask for it."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.training.rasterizer import rasterize
from brave6d.training.rasterizer.reference import rasterize_reference
from test_rasterizer import FORWARD_CASES, make_scene


def _median(fn, scene):
    with torch.no_grad():
        kwargs = {"median_depth": True} if fn is rasterize else {}
        _, depth, alpha, info = fn(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                   scene["colors"], scene["viewmats"], scene["Ks"], scene["width"],
                                   scene["height"], sh_degree=scene["sh_degree"], **kwargs)
    return info["median_depth"], depth, alpha, info


@pytest.mark.parametrize("case", ["rgb", "rgb-odd-size", "opaque-dense", "single-camera-large"])
def test_median_depth_matches_the_reference(case: str) -> None:
    scene = make_scene(**FORWARD_CASES[case])
    med, _, alpha, _ = _median(rasterize, scene)
    med_r, _, alpha_r, _ = _median(rasterize_reference, scene)
    assert med.shape == alpha.shape
    # pixels whose transmittance ends within float32 noise of 0.5 may cross on either side
    clear = (alpha_r - 0.5).abs() > 1e-4
    assert torch.allclose(med[clear], med_r[clear].float(), atol=1e-5)
    assert bool(((med > 0) == (alpha > 0.5))[clear].all())  # a value exactly where the pixel is opaque


def test_median_depth_is_only_there_when_asked() -> None:
    scene = make_scene(seed=0)
    info = rasterize(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                     scene["viewmats"], scene["Ks"], scene["width"], scene["height"])[3]
    assert "median_depth" not in info


@settings(max_examples=40, deadline=None)
@given(front=st.floats(0.2, 2.0), gap=st.floats(0.01, 2.0), opacity=st.floats(0.55, 0.99))
def test_an_edge_pixel_reports_one_surface_not_a_blend(front: float, gap: float, opacity: float) -> None:
    """Two overlapping opaque discs at different depths: the expected depth blends them where the
    front one thins out; the median depth is always one of the two."""
    width = height = 32
    f = 40.0
    back = front + gap
    means = torch.tensor([[0.0, 0.0, front], [0.0, 0.0, back]])
    scales = torch.tensor([[4.0 * front / f] * 3, [40.0 * back / f] * 3])
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    opac = torch.tensor([opacity, 0.999])
    K = torch.tensor([[[f, 0, 15.5], [0, f, 15.5], [0, 0, 1]]])
    _, depth, alpha, info = rasterize(means, quats, scales, opac, torch.rand(2, 3), torch.eye(4)[None], K,
                                      width, height, median_depth=True)
    med = info["median_depth"]
    assert torch.isfinite(med).all() and torch.isfinite(depth).all()
    is_front = (med - front).abs() < 1e-4 * back
    is_back = (med - back).abs() < 1e-4 * back
    assert bool((is_front | is_back | (med == 0))[alpha > 0.5].all())
    assert bool(is_front[0, 16, 16, 0])  # the centre sees the front disc


def test_bundles_record_the_depth_they_serve_and_older_ones_stay_expected() -> None:
    from brave6d.core.errors import DataError
    from brave6d.serve.bundle import RenderDefaults

    new = RenderDefaults(640, 400)
    assert new.depth_mode == "median" and RenderDefaults.from_json(new.to_json()) == new
    older = {"width": 640, "height": 400, "near": 0.01, "far": 100.0, "background": [0, 0, 0], "depth_alpha_min": 0.5}
    assert RenderDefaults.from_json(older).depth_mode == "expected"
    with pytest.raises(DataError, match="depth_mode must be one of"):
        RenderDefaults.from_json({**older, "depth_mode": "mean"})


def test_the_renderer_refuses_an_unknown_depth_mode() -> None:
    """A misspelt mode used to render the expected depth without a word."""
    import numpy as np

    from brave6d.core.camera import PinholeCamera
    from brave6d.core.errors import BraveError
    from brave6d.serve.renderer import SplatRenderer
    from brave6d.training import SplatData

    n = 4
    splat = SplatData(means=np.array([[0, 0, 1.0], [0.01, 0, 1.0], [0, 0.01, 1.0], [0, 0, 1.1]], np.float32),
                      quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
                      scales=np.full((n, 3), np.log(0.01), np.float32), opacities=np.full(n, 3.0, np.float32),
                      sh0=np.zeros((n, 1, 3), np.float32), shN=np.zeros((n, 0, 3), np.float32))
    renderer = SplatRenderer.from_splat(splat, "cpu")
    camera = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
    assert renderer.render(np.eye(4), camera, depth_mode="expected").depth.max() > 0
    with pytest.raises(BraveError, match="depth_mode must be one of median, expected, got 'medain'"):
        renderer.render(np.eye(4), camera, depth_mode="medain")

"""Batched renders (issue #46 item 4): N cameras in one rasterizer call give each camera the
views :meth:`SplatRenderer.render` gives it alone, including empty views and a Gaussian that
covers the whole image. Each check runs twice: with the CPU's grouping of cameras as it is, and
with every camera forced into one call (``CPU_BATCH_OVERLAP`` unbounded)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.transforms import look_at
from brave6d.serve import SplatRenderer
from brave6d.serve import renderer as renderer_module
from brave6d.serve.renderer import RenderOutput
from brave6d.serve.toy_scene import synthetic_splat
from brave6d.training.ply import SplatData

CAMERA = PinholeCamera.from_hfov(96, 72, 70.0)
TARGET = (0.46, 0.0, 0.01)
VIEWS = [look_at((0.25, -0.15, 0.30), TARGET), look_at((0.9, 0.5, 0.6), TARGET), look_at((0.46, -0.05, 0.10), TARGET)]
AWAY = look_at((0.46, 0.0, 0.5), (0.46, 0.0, 3.0))  # looks up, away from the scene: no Gaussian in view


@pytest.fixture(scope="module")
def renderer() -> SplatRenderer:
    return SplatRenderer.from_splat(synthetic_splat(4000, sh_degree=1, seed=5), device="cpu")


def one_big_gaussian() -> SplatRenderer:
    """A single Gaussian 1 m wide at the origin: seen from 0.3 m it covers every pixel."""
    splat = SplatData(means=np.zeros((1, 3), np.float32), sh0=np.full((1, 1, 3), 0.4, np.float32),
                      shN=np.zeros((1, 0, 3), np.float32), opacities=np.array([2.0], np.float32),
                      scales=np.full((1, 3), np.log(1.0), np.float32),
                      quats=np.array([[1.0, 0.0, 0.0, 0.0]], np.float32))
    return SplatRenderer.from_splat(splat, device="cpu")


def assert_same_view(batched: RenderOutput, single: RenderOutput) -> None:
    """The same pixels, depth and alpha, bit for bit (each camera composites the same Gaussians
    in the same order: the union's extra Gaussians cannot reach its image), and the same culled count."""
    np.testing.assert_array_equal(batched.rgb, single.rgb)
    np.testing.assert_array_equal(batched.depth, single.depth)
    np.testing.assert_array_equal(batched.alpha, single.alpha)
    assert batched.gaussians_drawn == single.gaussians_drawn


def check_batch(r: SplatRenderer, poses: list[np.ndarray], camera: PinholeCamera = CAMERA) -> list[RenderOutput]:
    """render_batch equals render per pose, grouped as the CPU groups and all in one call."""
    singles = [r.render(T, camera) for T in poses]
    for overlap in (renderer_module.CPU_BATCH_OVERLAP, float("inf")):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(renderer_module, "CPU_BATCH_OVERLAP", overlap)
            batched = r.render_batch(poses, camera)
        assert len(batched) == len(poses)
        for out, single in zip(batched, singles):
            assert np.all(np.isfinite(out.depth)) and np.all(np.isfinite(out.alpha))
            assert out.rgb.shape == (camera.height, camera.width, 3) and out.rgb.dtype == np.uint8
            assert_same_view(out, single)
    return batched


def test_cpu_groups_cameras_that_share_gaussians(renderer: SplatRenderer) -> None:
    """Nearby views share one call; views from opposite sides of the scene are drawn apart."""
    near = [look_at((0.25 + 0.002 * k, -0.15, 0.30), TARGET) for k in range(4)]
    culled = renderer._culled(*_cameras(renderer, near))
    assert renderer._groups(culled, 4) == [[0, 1, 2, 3]]
    apart = [look_at((0.46, -0.3, 0.05), (0.46, 0.3, 0.05)), look_at((0.46, 0.3, 0.05), (0.46, -0.3, 0.05))]
    culled = renderer._culled(*_cameras(renderer, apart))
    assert renderer._groups(culled, 2) == [[0], [1]]
    assert renderer._groups(None, 3) == [[0, 1, 2]]


def _cameras(r: SplatRenderer, poses: list[np.ndarray]) -> tuple:  # type: ignore[type-arg]
    """The arguments of ``_culled`` for ``poses`` seen through CAMERA."""
    import torch

    viewmats = torch.as_tensor(np.stack([np.linalg.inv(T) for T in poses]), dtype=torch.float32)
    return viewmats, torch.as_tensor(CAMERA.K, dtype=torch.float32), CAMERA, 0.01, 100.0


@pytest.mark.parametrize("n", [1, 3])
def test_batch_equals_one_by_one(renderer: SplatRenderer, n: int) -> None:
    outs = check_batch(renderer, VIEWS[:n])
    assert all(o.alpha.max() > 0.5 for o in outs)  # the scene is in view


def test_view_with_no_gaussian_in_a_batch(renderer: SplatRenderer) -> None:
    empty, seen = check_batch(renderer, [AWAY, VIEWS[0]])
    assert empty.alpha.max() == 0.0 and not empty.depth.any() and not empty.rgb.any()
    assert seen.alpha.max() > 0.5
    (alone,) = check_batch(renderer, [AWAY])
    assert alone.alpha.max() == 0.0


def test_one_gaussian_covering_the_image() -> None:
    r = one_big_gaussian()
    poses = [look_at((0.0, -0.1, 0.3), (0.0, 0.0, 0.0)), look_at((0.2, 0.1, 0.25), (0.0, 0.0, 0.0)),
             look_at((0.0, 0.0, 0.5), (0.0, 0.0, 2.0))]
    covered, covered2, _ = check_batch(r, poses)
    assert covered.alpha.min() > 0.5 and covered2.alpha.min() > 0.5
    assert np.all(covered.depth > 0.0)


def test_poses_are_checked(renderer: SplatRenderer) -> None:
    with pytest.raises(BraveError, match=r"\[C, 4, 4\]"):
        renderer.render_batch([], CAMERA)
    with pytest.raises(BraveError, match=r"\[C, 4, 4\]"):
        renderer.render_batch(np.eye(3)[None], CAMERA)
    bad = VIEWS[0].copy()
    bad[0, 3] = np.nan
    with pytest.raises(BraveError, match="NaN"):
        renderer.render_batch([bad], CAMERA)


def test_batch_of_an_unculled_renderer_equals_one_by_one() -> None:
    r = SplatRenderer.from_splat(synthetic_splat(1500, seed=7), device="cpu", cull=False)
    check_batch(r, [VIEWS[0], AWAY, VIEWS[2]])


eyes = st.tuples(st.floats(-0.3, 1.2), st.floats(-0.6, 0.6), st.floats(0.05, 0.9))
targets = st.tuples(st.floats(0.2, 0.7), st.floats(-0.2, 0.2), st.floats(-0.05, 0.1))


@settings(max_examples=15, deadline=None)
@given(st.lists(st.tuples(eyes, targets), min_size=1, max_size=4))
def test_random_poses_batched_equal_single(renderer: SplatRenderer,
                                           views: list[tuple[tuple[float, ...], tuple[float, ...]]]) -> None:
    poses = []
    for eye, target in views:
        if np.linalg.norm(np.subtract(eye, target)) < 1e-2:
            continue
        poses.append(look_at(eye, target))
    if poses:
        check_batch(renderer, poses)


def _cuda_available() -> bool:
    import torch

    return bool(torch.cuda.is_available())


@pytest.mark.skipif(not _cuda_available(), reason="needs a CUDA GPU (benchmarks/gpu_checks.sh runs it)")
def test_cuda_render_batch_matches_cpu(record_property: Any) -> None:
    """gsplat's batched cameras against the CPU kernels one view at a time (float tolerance:
    different arithmetic order; the median depth of an ambiguous pixel may pick its neighbour)."""
    splat = synthetic_splat(4000, sh_degree=1, seed=5)
    cpu, gpu = SplatRenderer.from_splat(splat, device="cpu"), SplatRenderer.from_splat(splat, device="cuda")
    poses = [*VIEWS, AWAY]
    worst = {"rgb": 0.0, "alpha": 0.0, "depth_bad_fraction": 0.0}
    for out, T in zip(gpu.render_batch(poses, CAMERA), poses):
        ref = cpu.render(T, CAMERA)
        worst["rgb"] = max(worst["rgb"], float(np.abs(out.rgb.astype(int) - ref.rgb.astype(int)).max()))
        worst["alpha"] = max(worst["alpha"], float(np.abs(out.alpha - ref.alpha).max()))
        bad = float(np.mean(np.abs(out.depth - ref.depth) > 1e-3))
        worst["depth_bad_fraction"] = max(worst["depth_bad_fraction"], bad)
    for k, v in worst.items():
        record_property(f"render_batch_{k}", v)
    assert worst["rgb"] <= 1 and worst["alpha"] < 1e-4 and worst["depth_bad_fraction"] < 0.005, worst


@pytest.mark.parametrize("cull", [True, False])
def test_a_batch_larger_than_a_call_holds_is_split_and_unchanged(monkeypatch: pytest.MonkeyPatch, cull: bool) -> None:
    """More cameras x Gaussians than ``MAX_PAIRS_PER_CALL``: several rasterizer calls, the same views."""
    r = SplatRenderer.from_splat(synthetic_splat(4000, sh_degree=1, seed=5), device="cpu", cull=cull)
    poses = [VIEWS[0], VIEWS[0], VIEWS[1], VIEWS[0], AWAY]
    singles = [r.render(T, CAMERA) for T in poses]
    calls: list[int] = []
    draw = r._rasterize

    def counted(args, viewmats, *rest):  # noqa: ANN001, ANN202 - the renderer's own signature
        calls.append(int(viewmats.shape[0]))
        return draw(args, viewmats, *rest)

    monkeypatch.setattr(r, "_rasterize", counted)
    monkeypatch.setattr(renderer_module, "CPU_BATCH_OVERLAP", float("inf"))  # one group: only the cap splits
    batched = r.render_batch(poses, CAMERA)
    whole = list(calls)
    calls.clear()
    monkeypatch.setattr(renderer_module, "MAX_PAIRS_PER_CALL", 2 * 4000)
    split = r.render_batch(poses, CAMERA)
    assert len(whole) == 1 and len(calls) >= 3 and sum(calls) == len(poses) and max(calls) <= 2
    for a, b, single in zip(batched, split, singles):
        assert_same_view(b, single)
        assert_same_view(a, single)

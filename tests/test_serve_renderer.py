"""The server's renderer: lossless culling and SH trimming, depth conventions, device choice, in-memory splats."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.transforms import look_at
from brave6d.core.errors import DataError
from brave6d.serve import SplatRenderer
from brave6d.serve.renderer import effective_sh_degree
from brave6d.training import read_ply, resolve_device
from brave6d.serve.toy_scene import synthetic_splat

CAMERA = PinholeCamera.from_hfov(160, 120, 70.0)


@pytest.fixture(scope="module")
def splat_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.training.ply import write_ply

    splat = synthetic_splat(6000, sh_degree=1, seed=3)
    n = splat.num_gaussians
    # a few Gaussians that can never be drawn (opacity < 1/255): dropped at load
    splat.opacities[:5] = -8.0
    assert n > 6000 - 100
    path = tmp_path_factory.mktemp("splat") / "point_cloud.ply"
    write_ply(path, splat)  # padded to degree 3 with zero coefficients
    return path


@pytest.mark.parametrize("eye", [(0.25, -0.15, 0.30), (0.46, 0.0, 0.12), (0.9, 0.5, 0.6), (0.2, 0.0, 0.05)])
def test_culling_is_lossless(splat_path: Path, eye: tuple[float, float, float]) -> None:
    culled = SplatRenderer(splat_path, device="cpu", cull=True)
    full = SplatRenderer(splat_path, device="cpu", cull=False)
    T = look_at(eye, (0.46, 0.0, 0.01))
    a, b = culled.render(T, CAMERA), full.render(T, CAMERA)
    assert a.gaussians_drawn <= b.gaussians_drawn
    np.testing.assert_allclose(a.alpha, b.alpha, atol=2e-5)
    assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max() <= 1  # float rounding only
    np.testing.assert_allclose(a.depth, b.depth, atol=1e-5)


def test_culling_saves_work_in_close_views(splat_path: Path) -> None:
    r = SplatRenderer(splat_path, device="cpu")
    out = r.render(look_at((0.46, -0.05, 0.10), (0.46, 0.0, 0.01)), CAMERA)
    assert out.gaussians_drawn < 0.5 * r.num_gaussians


def test_load_drops_invisible_gaussians_and_trims_sh(splat_path: Path) -> None:
    r = SplatRenderer(splat_path, device="cpu")
    assert r.n_pruned == 5 and r.num_gaussians == r.n_loaded - 5
    assert r.sh_degree == 1 and r.colors.shape[1] == 4  # the zero-padded bands are not evaluated


def test_effective_sh_degree() -> None:
    sh = np.zeros((3, 15, 3), np.float32)
    assert effective_sh_degree(sh) == 0
    sh[1, 7, 2] = 0.1  # a degree-2 coefficient
    assert effective_sh_degree(sh) == 2
    sh[0, 14, 0] = 1e-9
    assert effective_sh_degree(sh) == 3
    assert effective_sh_degree(np.zeros((2, 0, 3), np.float32)) == 0


def test_depth_and_background(splat_path: Path) -> None:
    r = SplatRenderer(splat_path, device="cpu")
    # looking up into the empty sky: nothing drawn, background colour, depth 0 (no data)
    T = look_at((0.46, 0.0, 0.3), (0.46, 0.0, 1.0))
    out = r.render(T, CAMERA, background=(0.0, 1.0, 0.0))
    assert out.depth.dtype == np.float32 and np.all(out.depth == 0)
    assert np.all(out.rgb[..., 1] == 255) and np.all(out.rgb[..., 0] == 0)
    # looking down at the table from 30 cm: depth about 0.29 m at the centre
    T = look_at((0.30, -0.2, 0.30), (0.30, -0.2, 0.0), up=(1, 0, 0))
    out = r.render(T, CAMERA)
    assert abs(float(out.depth[60, 80]) - 0.30) < 0.005
    assert out.render_ms > 0


def test_device_choice() -> None:
    import torch

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(BraveError, match="'tpu'"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(BraveError, match="no CUDA GPU"):
            resolve_device("cuda")
        with pytest.raises(BraveError, match="no CUDA GPU"):
            SplatRenderer.from_splat(synthetic_splat(10, seed=1), device="cuda")
    assert SplatRenderer.from_splat(synthetic_splat(10, seed=1), device="cpu").device == "cpu"


def test_distorted_camera_is_refused(splat_path: Path) -> None:
    r = SplatRenderer(splat_path, device="cpu")
    cam = PinholeCamera(160, 120, 100.0, 100.0, 80.0, 60.0, (0.1, 0.0, 0.0, 0.0))
    with pytest.raises(BraveError, match="undistorted"):
        r.render(np.eye(4), cam)


@pytest.mark.parametrize("point", [(0.013, -0.021, 0.0), (-0.0417, 0.0263, 0.011), (0.0, 0.0, -0.02)])
def test_served_gaussian_is_centred_at_its_opencv_projection(tmp_path: Path, point: tuple[float, ...]) -> None:
    """The server's image of one small Gaussian is centred (alpha centroid) at the camera's
    OpenCV projection of its mean, within 0.05 px, as the simulator's images are; the old code
    served it 0.5 px up and left (K handed unconverted to gsplat's +0.5 pixel centres)."""
    from brave6d.training.ply import SplatData, write_ply

    camera = PinholeCamera(160, 120, 150.0, 150.0, 78.3, 61.7)
    X = np.array([point], np.float32)
    sigma_m = 0.0025  # about 1.5 px at 0.25 m
    splat = SplatData(means=X, sh0=np.zeros((1, 1, 3), np.float32), shN=np.zeros((1, 0, 3), np.float32),
                      opacities=np.array([1.5], np.float32), scales=np.full((1, 3), np.log(sigma_m), np.float32),
                      quats=np.array([[1.0, 0.0, 0.0, 0.0]], np.float32))
    path = write_ply(tmp_path / "one.ply", splat)
    world_T_cam = look_at((0.05, -0.04, 0.25), (0.0, 0.0, 0.0))
    out = SplatRenderer(path, device="cpu").render(world_T_cam, camera)
    expected = camera.project((np.linalg.inv(world_T_cam) @ np.append(X[0], 1.0))[None, :3]).uv[0]
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    a = out.alpha.astype(np.float64)
    centroid = np.array([(a * u).sum(), (a * v).sum()]) / a.sum()
    assert np.abs(centroid - expected).max() < 0.05, centroid - expected


def test_from_splat_renders_the_pixels_of_the_same_splat_loaded_from_its_ply(splat_path: Path) -> None:
    """The report renders subsets from memory: the same pixels, depth and counts as the server's PLY path."""
    from_file = SplatRenderer(splat_path, device="cpu")
    in_memory = SplatRenderer.from_splat(read_ply(splat_path), device="cpu")
    assert (in_memory.n_loaded, in_memory.n_pruned, in_memory.sh_degree) == \
        (from_file.n_loaded, from_file.n_pruned, from_file.sh_degree)
    for eye in ((0.25, -0.15, 0.30), (0.9, 0.5, 0.6)):
        T = look_at(eye, (0.46, 0.0, 0.01))
        a, b = in_memory.render(T, CAMERA), from_file.render(T, CAMERA)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.alpha, b.alpha)
        assert a.gaussians_drawn == b.gaussians_drawn


def test_from_splat_refuses_a_broken_splat_naming_its_source() -> None:
    splat = synthetic_splat(50, seed=2)
    splat.means[7, 1] = np.nan
    with pytest.raises(DataError, match="subset of scene A.*NaN"):
        SplatRenderer.from_splat(splat, device="cpu", source="subset of scene A")

"""COLMAP initialisation with known poses, the sparse/ model, and the fallbacks."""

from __future__ import annotations

import importlib.util
import json
import logging
import shutil
import sqlite3
import struct
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.training.colmap_init import (
    ColmapOptions,
    colmap_pinhole_params,
    extract_features,
    initial_points,
    match_pairs,
    nearest_camera_pairs,
    random_points,
    triangulate_database,
    voxel_downsample,
)
from brave6d.training.views import load_scene
from brave6d.training.toy_scenes import plane_views, write_scene

CAM = PinholeCamera(320, 200, 250.0, 250.0, 159.5, 99.5)
OPTS = ColmapOptions(max_features=2048, neighbours=5, min_points=200)


@pytest.fixture(scope="module")
def plane_scene(tmp_path_factory: pytest.TempPathFactory):
    """A textured plane z = 0 seen by 2 rings x 8 cameras; COLMAP run once for the module (its
    tests are marked slow, so `-m "not slow"` never builds it)."""
    root = tmp_path_factory.mktemp("colmap") / "scene"
    tcp_T_cam = np.eye(4)
    tcp_T_cam[:3, 3] = [0.0, -0.05, 0.02]
    scene = write_scene(root, CAM, plane_views(CAM, [0.45, 0.6], 8), tcp_T_cam=tcp_T_cam)
    data = load_scene(scene)
    init = initial_points(scene, data, OPTS, max_points=50_000)
    return scene, data, init


@pytest.mark.slow
def test_triangulated_points_lie_on_the_plane(plane_scene) -> None:
    _, _, init = plane_scene
    assert init.source == "colmap"
    assert len(init) >= 500
    z = np.abs(init.points[:, 2])
    assert np.median(z) < 0.002  # pixels are ~2 mm on the plane
    assert np.quantile(z, 0.9) < 0.006
    assert np.all(np.abs(init.points[:, :2]) < 0.32)  # on the textured square (0.6 m)
    assert init.colors.shape == init.points.shape and init.colors.max() <= 1.0
    assert init.colors.std() > 0.05  # real colours from the images, not a constant


def _centre(image: pycolmap.Image) -> np.ndarray:
    return np.asarray(image.projection_center())


@pytest.mark.slow
def test_sparse_model_loads_with_pycolmap_and_keeps_the_calibrated_centres(plane_scene) -> None:
    scene, data, init = plane_scene
    model = scene.sparse_dir / "0"
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (model / name).is_file()
    rec = pycolmap.Reconstruction(str(model))
    assert rec.num_cameras() == 1
    cam = rec.cameras[1]
    assert cam.model == pycolmap.CameraModelId.PINHOLE
    np.testing.assert_allclose(cam.params, [CAM.fx, CAM.fy, CAM.cx + 0.5, CAM.cy + 0.5])  # COLMAP's pixel centres
    by_name = {im.name: im for im in rec.images.values()}
    assert len(by_name) == len(data.views)  # holdout views included (poses only)
    for v in data.views:
        np.testing.assert_allclose(_centre(by_name[v.rgb_path.name]), v.base_T_cam[:3, 3], atol=1e-6)
        R_cw = by_name[v.rgb_path.name].cam_from_world().rotation.matrix()
        np.testing.assert_allclose(R_cw, v.base_T_cam[:3, :3].T, atol=1e-9)
    assert rec.num_points3D() >= len(init)
    holdout = (scene.sparse_dir / "holdout.txt").read_text().split()
    assert holdout and holdout == [v.rgb_path.name for v in data.test]
    # held-out images contributed no observations
    assert all(by_name[n].num_points3D == 0 for n in holdout)


@pytest.mark.slow
def test_sparse_model_is_classic_colmap_binary(plane_scene) -> None:
    """Readers of other 3DGS tools (Inria's read_extrinsics_binary) parse the classic layout."""
    scene, data, _ = plane_scene
    raw = (scene.sparse_dir / "0" / "cameras.bin").read_bytes()
    n, cam_id, model_id, w, h = struct.unpack("<QiiQQ", raw[:32])
    params = struct.unpack("<4d", raw[32:64])
    assert (n, cam_id, model_id, w, h) == (1, 1, 1, 320, 200)  # model 1 = PINHOLE
    assert params == (CAM.fx, CAM.fy, CAM.cx + 0.5, CAM.cy + 0.5)
    raw = (scene.sparse_dir / "0" / "images.bin").read_bytes()
    (n_images,) = struct.unpack("<Q", raw[:8])
    assert n_images == len(data.views)
    _, qw, qx, qy, qz, _, _, _, camera_id = struct.unpack("<idddddddi", raw[8:72])
    name = raw[72:raw.index(b"\0", 72)].decode()
    assert camera_id == 1 and name.endswith(".png")
    assert abs(qw * qw + qx * qx + qy * qy + qz * qz - 1) < 1e-9


@pytest.mark.slow
def test_colmap_camera_projects_where_opencv_does_plus_half_a_pixel(plane_scene) -> None:
    """COLMAP's pixel (0, 0) is centred at (0.5, 0.5), OpenCV's (the project's K) at (0, 0):
    pycolmap's model of the exported camera (the one the features were triangulated with)
    projects every point to the OpenCV projection + 0.5 px, and a centred OpenCV camera
    ((W - 1) / 2) is COLMAP's own centred camera (W / 2). The old export wrote K unchanged
    (0.5 px off, this test failed)."""
    scene, _, _ = plane_scene
    cam = pycolmap.Reconstruction(str(scene.sparse_dir / "0")).cameras[1]
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.2, 0.2, (50, 2)), rng.uniform(0.3, 1.0, 50)])
    np.testing.assert_allclose(cam.img_from_cam(points), CAM.project(points).uv + 0.5, atol=1e-9)
    centred = PinholeCamera(CAM.width, CAM.height, CAM.fx, CAM.fy, (CAM.width - 1) / 2, (CAM.height - 1) / 2)
    default = pycolmap.Camera.create_from_model_name(1, "PINHOLE", CAM.fx, CAM.width, CAM.height)
    np.testing.assert_allclose(default.params[2:], colmap_pinhole_params(centred)[2:])


@pytest.mark.slow
def test_triangulation_of_opencv_images_is_not_biased(plane_scene) -> None:
    """The plane's images are OpenCV-convention warps (texel and pixel centres at integers):
    with the camera converted for COLMAP, the points lie on the plane (median 0.3 mm, mean
    reprojection error 0.19 px); the old export (K unchanged) put them 1.8 mm off at 0.37 px."""
    scene, _, init = plane_scene
    assert np.median(np.abs(init.points[:, 2])) < 0.0008
    rec = pycolmap.Reconstruction(str(scene.sparse_dir / "0"))
    assert np.mean([p.error for p in rec.points3D.values()]) < 0.28


def test_pairs_link_nearest_cameras() -> None:
    centres = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0]], float)
    assert nearest_camera_pairs(centres, 1) == [(0, 1), (1, 2), (2, 3)]
    assert nearest_camera_pairs(centres[:1], 3) == []


def test_depth_fallback_when_colmap_finds_nothing(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    scene = write_scene(tmp_path / "blank", cam, plane_views(cam, [0.45], 6, blank=True))
    data = load_scene(scene)
    with caplog.at_level(logging.WARNING):
        init = initial_points(scene, data, ColmapOptions(max_features=256, neighbours=2), max_points=3000)
    assert init.source == "depth"
    assert "falling back to depth" in caplog.text
    assert 100 < len(init) <= 3000
    assert np.abs(init.points[:, 2]).max() < 2e-3  # depth is quantised to whole millimetres
    rec = pycolmap.Reconstruction(str(scene.sparse_dir / "0"))
    assert rec.num_points3D() >= len(init)  # the same points in sparse/ for other tools


def test_random_fallback_warns(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    scene = write_scene(tmp_path / "nodepth", cam, plane_views(cam, [0.45], 4, blank=True), with_depth=False)
    data = load_scene(scene)
    with caplog.at_level(logging.WARNING):
        init = initial_points(scene, data, method="depth", max_points=500)
    assert init.source == "random" and len(init) == 500
    assert "RANDOM" in caplog.text


def test_without_the_model_the_same_points_come_without_pycolmap(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``write_sparse=False`` (the GPU checks' benchmarks): the same random start, no ``sparse/0``, and
    pycolmap never imported; with the model, pycolmap's absence is a named error."""
    import sys

    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    scene = write_scene(tmp_path / "s", cam, plane_views(cam, [0.45], 4))
    data = load_scene(scene)
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # as on the GPU machine
    bare = initial_points(scene, data, method="random", max_points=300, write_sparse=False)
    assert bare.source == "random" and len(bare) == 300 and not (scene.sparse_dir / "0").exists()
    with pytest.raises(BraveError, match="pycolmap is needed"):
        initial_points(scene, data, method="random", max_points=300)
    monkeypatch.delitem(sys.modules, "pycolmap")
    full = initial_points(scene, data, method="random", max_points=300)
    assert (scene.sparse_dir / "0").is_dir()
    np.testing.assert_array_equal(full.points, bare.points)
    np.testing.assert_array_equal(full.colors, bare.colors)


def test_voxel_downsample_and_random_points() -> None:
    rng = np.random.default_rng(0)
    pts = rng.random((20_000, 3))
    p, _, voxel = voxel_downsample(pts, rng.random((20_000, 3)).astype(np.float32), 1000)
    assert len(p) <= 1000 and voxel > 0 and np.all((p >= 0) & (p <= 1))
    r = random_points(np.zeros(3), np.ones(3) * 2, 50, seed=3)
    assert r.points.shape == (50, 3) and np.all((r.points >= 0) & (r.points <= 2))


@pytest.mark.slow
def test_unchanged_model_is_reused(plane_scene, monkeypatch: pytest.MonkeyPatch) -> None:
    import brave6d.training.colmap_init as ci

    scene, data, init = plane_scene

    def boom(*a, **k):  # type: ignore[no-untyped-def]
        raise AssertionError("triangulated again")

    monkeypatch.setattr(ci, "triangulate", boom)
    again = initial_points(scene, data, OPTS, max_points=50_000)
    assert again.source == "colmap" and "reused" in again.details
    np.testing.assert_array_equal(again.points, init.points)  # same order: same training
    np.testing.assert_array_equal(again.colors, init.colors)


@pytest.mark.slow
def test_new_image_contents_are_triangulated_again(plane_scene, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    import brave6d.training.colmap_init as ci
    from brave6d.core.atomic import read_png, write_png
    from brave6d.core.layout import SceneDir

    scene = SceneDir(shutil.copytree(plane_scene[0].root, tmp_path / "recaptured"))
    raw = scene.capture_dir / "rgb" / "000003.png"
    write_png(raw, 255 - read_png(raw, "rgb"))  # recaptured: same name and pose, other content
    calls = []

    def counted(*a, **k):  # type: ignore[no-untyped-def]
        calls.append(1)
        raise RuntimeError("stop here")

    monkeypatch.setattr(ci, "triangulate", counted)
    initial_points(scene, load_scene(scene), OPTS, max_points=1000)
    assert calls == [1]


@pytest.mark.slow
def test_triangulation_does_not_depend_on_the_worlds_units(plane_scene, tmp_path: Path) -> None:
    """The same matches triangulated with the world scaled by 0.07, 1 and 100: the same points, scaled
    (COLMAP works in the cameras' training frame, issue 67; in world units the shipped fox got 4912 to
    4915 points at scales 0.1 to 10, and the splats trained from them 27.64 to 27.92 dB)."""
    _, data, _ = plane_scene
    images = [(v.rgb_path.name, v.base_T_cam) for v in data.train]
    image_dir = data.undistorted_root / "rgb"
    features = tmp_path / "features.db"
    extract_features(features, image_dir, data.full_camera or data.camera, [n for n, _ in images], OPTS)
    match_pairs(features, images, tmp_path / "pairs.txt", OPTS)

    def points(factor: float) -> np.ndarray:
        db = tmp_path / f"{factor:g}.db"
        shutil.copy(features, db)
        scaled = []
        for name, T in images:
            T = T.copy()
            T[:3, 3] *= factor
            scaled.append((name, T))
        rec = triangulate_database(db, image_dir, scaled, tmp_path / f"tri-{factor:g}", OPTS)
        return np.array([p.xyz for _, p in sorted(rec.points3D.items())])

    base = points(1.0)
    assert len(base) > 500
    for factor in (0.07, 100.0):
        other = points(factor) / factor
        assert other.shape == base.shape, f"scale {factor:g}: {len(other)} points, {len(base)} at scale 1"
        np.testing.assert_allclose(other, base, rtol=0, atol=1e-9 * np.abs(base).max(), err_msg=f"scale {factor:g}")


def _colmap_threads_benchmark():  # type: ignore[no-untyped-def]
    path = Path(__file__).resolve().parent.parent / "benchmarks" / "colmap_threads.py"
    spec = importlib.util.spec_from_file_location("colmap_threads_benchmark", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_matching_the_same_features_again_gives_the_same_matches(plane_scene, tmp_path: Path) -> None:
    """The default matching (one thread, seeded RANSAC) is repeatable on one database; several
    matching threads were not always (see match_pairs), which the fresh-process training test met."""
    scene, data, _ = plane_scene
    images = [(v.rgb_path.name, v.base_T_cam) for v in data.train]
    features = tmp_path / "features.db"
    extract_features(features, data.undistorted_root / "rgb", data.full_camera or data.camera,
                     [n for n, _ in images], OPTS)
    n_pairs = len(nearest_camera_pairs(np.array([T[:3, 3] for _, T in images]), OPTS.neighbours))
    matches_digest = _colmap_threads_benchmark().matches_digest
    digests = set()
    for r in range(3):
        db = tmp_path / f"{r}.db"
        shutil.copy(features, db)
        assert match_pairs(db, images, tmp_path / "pairs.txt", OPTS) == n_pairs
        with sqlite3.connect(db) as con:
            verified = con.execute("SELECT SUM(rows) FROM two_view_geometries").fetchone()[0]
        assert verified > 1000  # real matches on the textured plane, not empty tables
        digests.add(matches_digest(db))
    assert len(digests) == 1
    listed = (tmp_path / "pairs.txt").read_text().split("\n")
    assert len([line for line in listed if line]) == n_pairs


@pytest.mark.slow
def test_colmap_threads_benchmark_prices_both_stages(plane_scene, tmp_path: Path) -> None:
    scene, _, _ = plane_scene
    out = tmp_path / "threads.json"
    assert _colmap_threads_benchmark().main([str(scene.root), "--repeats", "2", "--threads", "2",
                                             "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["pairs"] > 0 and result["extract_s"] > 0
    for stage in ("match", "triangulate"):
        for name in ("1 thread", "2 threads"):
            entry = result[stage][name]
            assert len(entry["seconds"]) == 2 and entry["median_s"] > 0
            assert entry["different_results"] == len(entry["results"]) >= 1
    assert result["match"]["1 thread"]["different_results"] == 1  # the default is repeatable
    assert result["triangulate"]["1 thread"]["different_results"] == 1

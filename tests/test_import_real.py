"""``brave6d import`` on a real capture: 65 photos of a skull (CC BY 4.0, tests/data/real/skull/README.md).

Expected values come from elsewhere: pycolmap's own reading of the model (cameras, registered
images, 2D observations of every 3D point) and OpenCV's projection (``cv2.projectPoints``). The
imported camera, poses and points must put every COLMAP observation back where COLMAP measured it
(COLMAP's pixel centres are at +0.5: the check moves them), whichever format it came through.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from brave6d.core.calibration_io import camera_poses, read_intrinsics
from brave6d.core.layout import SceneDir
from brave6d.training import (ImportOptions, PoseCheckError, ScaleChoice, UpChoice, get_preset, import_capture,
                              load_scene, train, train_scene)

SAMPLE = Path(__file__).parent / "data" / "real" / "skull"
MODEL = SAMPLE / "sparse" / "0"
#: The skull's real size is not published: the tests take 1 m between the centres of photos 01 and 30
#: (README.md), which puts the camera about 0.65 m from the skull.
SCALE = ("01.jpg", "30.jpg", 1.0)


def options(names: tuple[str, str] = ("01.jpg", "30.jpg"), **kw) -> ImportOptions:
    return ImportOptions(scale=ScaleChoice(distance=(*names, SCALE[2])), up=UpChoice(None), **kw)


@pytest.fixture(scope="module")
def rec() -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(MODEL))


@pytest.fixture(scope="module")
def colmap_scene(tmp_path_factory) -> SceneDir:
    out = tmp_path_factory.mktemp("real") / "colmap"
    import_capture(MODEL, out, options())
    return SceneDir(out)


@pytest.fixture(scope="module")
def transforms_scene(tmp_path_factory) -> SceneDir:
    out = tmp_path_factory.mktemp("real") / "ns"
    import_capture(SAMPLE / "transforms.json", out, options(("images/01.jpg", "images/30.jpg")))
    return SceneDir(out)


def source_name(record) -> str:  # type: ignore[no-untyped-def]
    return Path(record.model_extra["source_image"]).name


def reprojection_errors(scene: SceneDir, rec: pycolmap.Reconstruction, xyz_source: dict[int, np.ndarray]) -> np.ndarray:
    """Pixel distance between COLMAP's observations and the imported camera's projection of the
    observed points (``xyz_source``: point id -> position in the source's world)."""
    record = json.loads(scene.import_record_path.read_text())
    M = np.asarray(record["world"]["new_T_source"])
    cam = read_intrinsics(scene)
    pose_of = {source_name(r): T for r, T in camera_poses(scene)}
    errors = []
    for image_id in rec.reg_image_ids():
        image = rec.images[image_id]
        obs = [(p.xy, p.point3D_id) for p in image.points2D if p.has_point3D()]
        xy = np.array([o[0] for o in obs]) - 0.5  # COLMAP -> OpenCV pixel centres
        X = np.array([xyz_source[o[1]] for o in obs]) @ M[:3, :3].T + M[:3, 3]
        cam_T_world = np.linalg.inv(pose_of[image.name])
        rvec, _ = cv2.Rodrigues(cam_T_world[:3, :3])
        uv, _ = cv2.projectPoints(X, rvec, cam_T_world[:3, 3], cam.K, cam.dist_array)
        errors.append(np.linalg.norm(uv.reshape(-1, 2) - xy, axis=1))
    return np.concatenate(errors)


def test_colmap_import_matches_pycolmaps_reading(colmap_scene: SceneDir, rec: pycolmap.Reconstruction) -> None:
    (source_cam,) = rec.cameras.values()
    fx, fy, cx, cy, k1, k2, p1, p2 = source_cam.params
    cam = read_intrinsics(colmap_scene)
    assert (cam.width, cam.height) == (source_cam.width, source_cam.height)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [fx, fy, cx - 0.5, cy - 0.5], rtol=1e-12)
    np.testing.assert_allclose(cam.dist, [k1, k2, p1, p2], rtol=1e-12)
    frames = camera_poses(colmap_scene)
    assert sorted(source_name(r) for r, _ in frames) == sorted(rec.images[i].name for i in rec.reg_image_ids())
    errors = reprojection_errors(colmap_scene, rec, {i: p.xyz for i, p in rec.points3D.items()})
    assert len(errors) == rec.compute_num_observations()
    assert np.median(errors) < 0.3 and np.percentile(errors, 99) < 2.0, (np.median(errors), errors.max())
    centres = {source_name(r): T[:3, 3] for r, T in frames}
    assert np.linalg.norm(centres["01.jpg"] - centres["30.jpg"]) == pytest.approx(1.0, rel=1e-9)


def test_a_text_model_imports_like_the_binary_one(colmap_scene: SceneDir, rec: pycolmap.Reconstruction,
                                                  tmp_path: Path) -> None:
    text = tmp_path / "text"
    text.mkdir()
    rec.write_text(str(text))
    assert (text / "images.txt").is_file() and not (text / "images.bin").exists()
    import_capture(text, tmp_path / "scene", options(images=SAMPLE / "images"))
    got = {source_name(r): T for r, T in camera_poses(SceneDir(tmp_path / "scene"))}
    for r, T in camera_poses(colmap_scene):
        np.testing.assert_allclose(got[source_name(r)], T, atol=1e-6)


def test_transforms_json_import_agrees_with_colmap(transforms_scene: SceneDir, colmap_scene: SceneDir,
                                                   rec: pycolmap.Reconstruction) -> None:
    """nerfstudio's file of the same model: same camera, same poses up to a turn about +z (the
    heading is free), and COLMAP's observations land on its sparse_pc.ply points."""
    a, b = read_intrinsics(transforms_scene), read_intrinsics(colmap_scene)
    assert a == b
    ns = {source_name(r): T for r, T in camera_poses(transforms_scene)}
    cm = {source_name(r): T for r, T in camera_poses(colmap_scene)}
    assert ns.keys() == cm.keys()
    first = next(iter(cm))
    Rz = ns[first][:3, :3] @ cm[first][:3, :3].T
    assert Rz[2, 2] == pytest.approx(1.0, abs=1e-9)  # a rotation about z
    for name in cm:
        np.testing.assert_allclose(ns[name][:3, :3], Rz @ cm[name][:3, :3], atol=1e-7)
        np.testing.assert_allclose(ns[name][:3, 3], Rz @ cm[name][:3, 3], atol=1e-7)
    from plyfile import PlyData

    vertex = PlyData.read(str(SAMPLE / "sparse_pc.ply"))["vertex"]
    xyz = np.stack([np.asarray(vertex[c], np.float64) for c in "xyz"], axis=1)  # in point-id order (make_sample.py)
    errors = reprojection_errors(transforms_scene, rec, dict(zip(sorted(rec.point3D_ids()), xyz)))
    assert np.median(errors) < 0.3 and np.percentile(errors, 99) < 2.0, (np.median(errors), errors.max())


def test_missing_images_are_reported_by_name(tmp_path: Path) -> None:
    copy = tmp_path / "src"
    shutil.copytree(SAMPLE, copy, ignore=shutil.ignore_patterns("*.py", "README.md"))
    (copy / "images" / "07.jpg").unlink()
    (copy / "images" / "44.jpg").unlink()
    ns = import_capture(copy / "transforms.json", tmp_path / "ns", options(("images/01.jpg", "images/30.jpg")))
    assert ns.missing == ["images/07.jpg", "images/44.jpg"] and ns.frames == 63
    cm = import_capture(copy / "sparse" / "0", tmp_path / "cm", options())
    assert cm.missing == ["07.jpg", "44.jpg"] and cm.frames == 63


def test_opengl_axes_left_unflipped_are_named_at_import_and_at_train_start(tmp_path: Path) -> None:
    """The issue's bug: OpenCV camera-to-world matrices in a transforms.json (read as OpenGL's)."""
    data = json.loads((SAMPLE / "transforms.json").read_text())
    for frame in data["frames"]:
        frame["transform_matrix"] = (np.asarray(frame["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0])).tolist()
    copy = tmp_path / "src"
    shutil.copytree(SAMPLE / "images", copy / "images")
    shutil.copy(SAMPLE / "sparse_pc.ply", copy)
    (copy / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(PoseCheckError, match="OpenGL camera axes") as err:
        import_capture(copy / "transforms.json", tmp_path / "scene", options(("images/01.jpg", "images/30.jpg")))
    assert len(err.value.failing) == 65 and "images/01.jpg (0%)" in str(err.value)
    import_capture(copy / "transforms.json", tmp_path / "scene", options(("images/01.jpg", "images/30.jpg"),
                                                                        pose_check=False))
    scene = SceneDir(tmp_path / "scene")
    with pytest.raises(PoseCheckError, match="--skip-pose-check") as err:
        train(load_scene(scene, downscale=4), get_preset("fast"), "cpu", scene=scene)
    assert len(err.value.failing) == 65


@pytest.mark.slow
def test_a_small_training_of_the_imported_capture_exports_and_renders(tmp_path: Path) -> None:
    """The wiring: import (1/2 size), 60 training steps from the imported points, export, and the
    server's renderer draws the held-out views like the training's holdout evaluation did."""
    from brave6d.serve import SplatRenderer, load_bundle, export_bundle

    import_capture(MODEL, tmp_path / "scene", options(downscale=2))
    scene = SceneDir(tmp_path / "scene")
    preset = get_preset("fast").with_overrides(steps=60, coarse_steps=0, downscale=1, refine_start=10,
                                               refine_every=10, refine_stop=50, max_init_points=3000,
                                               checkpoint_every=60, curve_every=10, depth_lambda=0.0)
    metrics = train_scene(scene, preset, device="cpu", init_method="imported", show_progress=False)
    assert metrics["init"]["source"] == "imported" and metrics["steps"] == 60
    assert metrics["n_holdout_views"] == 7 and metrics["images"]["metrics_resolution"] == "240x160"
    assert 14.0 < metrics["holdout"]["psnr"] < 60.0
    bundle = load_bundle(export_bundle(scene.root).root)
    assert len(bundle.holdout) == 7 and not bundle.objects
    renderer = SplatRenderer(bundle.splat_path, device="cpu")
    psnrs = []
    for view in bundle.holdout:
        rendered = renderer.render(view.world_T_cam, bundle.camera).rgb.astype(np.float64)
        truth = cv2.cvtColor(cv2.imread(str(bundle.root / view.image)), cv2.COLOR_BGR2RGB).astype(np.float64)
        psnrs.append(10 * np.log10(255.0 ** 2 / np.mean((rendered - truth) ** 2)))
    assert np.mean(psnrs) == pytest.approx(metrics["holdout"]["psnr"], abs=1.5)

"""``brave6d import`` on instant-ngp's own sample, the fox (tests/data/real/fox/README.md).

The ``transforms.json`` is instant-ngp's file byte for byte: rotations rounded at the sixth digit
(max |R^T R - I| = 1.09e-6), 67 frames of which the repository ships 50 photos, intrinsics for the
1080x1920 originals. The photos are shipped at 1/4 size, so the sample also exercises resampled
copies (what nerfstudio's ``images_4`` folders are). Expected values come from the JSON itself.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.cli import main as cli_main
from brave6d.core.calibration_io import camera_poses, read_intrinsics
from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir
from brave6d.training import get_preset, train_scene
from brave6d.training.importing.colmap_source import read_colmap
from brave6d.training.importing.source import SourceCamera, downscale_factor

SAMPLE = Path(__file__).parent / "data" / "real" / "fox"
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def fox_json() -> dict:
    return json.loads((SAMPLE / "transforms.json").read_text())


@pytest.fixture(scope="module")
def fox_scene(tmp_path_factory) -> SceneDir:
    out = tmp_path_factory.mktemp("fox") / "scene"
    code = cli_main(["import", str(SAMPLE / "transforms.json"), str(out), "--scale", "0.1", "--up", "auto"])
    assert code == 0
    return SceneDir(out)


def test_the_unchanged_file_imports_with_its_rounding_recorded(fox_scene: SceneDir, fox_json: dict) -> None:
    record = json.loads(fox_scene.import_record_path.read_text())
    shipped = sorted(p.name for p in (SAMPLE / "images").glob("*.jpg"))
    listed = [f["file_path"] for f in fox_json["frames"]]
    assert len(shipped) == 50 and len(listed) == 67
    assert record["frames"] == 50 and len(record["missing"]) == 17
    assert sorted(Path(m).name for m in record["missing"]) == sorted(set(Path(n).name for n in listed) - set(shipped))
    rotations = record["rotations"]
    assert 1e-7 < rotations["largest_correction"] < 1e-5 and rotations["tolerance"] == 1e-3
    worst = next(f for f in fox_json["frames"] if f["file_path"] == rotations["largest_correction_frame"])
    R = np.asarray(worst["transform_matrix"])[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() > 1e-7  # the file's own rounding, not ours
    assert "50 of 50 cameras" in record["pose_check"]["summary"] and record["pose_check"]["least_share"] > 0.5
    assert "1/4" in record["source"]["images_downscaled"]


def test_intrinsics_are_the_files_scaled_to_the_shipped_photos(fox_scene: SceneDir, fox_json: dict) -> None:
    cam = read_intrinsics(fox_scene)
    assert (cam.width, cam.height) == (270, 480)
    s = 0.25  # 1080x1920 -> 270x480; COLMAP's corner-origin principal point scales exactly, then -0.5
    np.testing.assert_allclose([cam.fx, cam.fy], [fox_json["fl_x"] * s, fox_json["fl_y"] * s], rtol=1e-12)
    np.testing.assert_allclose([cam.cx, cam.cy], [fox_json["cx"] * s - 0.5, fox_json["cy"] * s - 0.5], rtol=1e-12)
    np.testing.assert_allclose(cam.dist, [fox_json[k] for k in ("k1", "k2", "p1", "p2")], rtol=1e-12)


def test_poses_are_the_files_up_to_the_recorded_world_change(fox_scene: SceneDir, fox_json: dict) -> None:
    """Every imported pose is new_T_source @ (the file's matrix, OpenGL -> OpenCV axes), scaled by 0.1."""
    record = json.loads(fox_scene.import_record_path.read_text())
    M = np.asarray(record["world"]["new_T_source"])
    np.testing.assert_allclose(np.linalg.norm(M[:3, :3], axis=0), [0.1] * 3, rtol=1e-9)
    by_name = {f["file_path"]: np.asarray(f["transform_matrix"]) for f in fox_json["frames"]}
    poses = camera_poses(fox_scene)
    assert len(poses) == 50
    for frame, T in poses:
        src = by_name[frame.model_extra["source_image"]] @ GL_TO_CV
        np.testing.assert_allclose(T[:3, 3], (M @ src)[:3, 3], atol=1e-9)
        np.testing.assert_allclose(T[:3, :3], M[:3, :3] @ src[:3, :3] / 0.1, atol=2e-6)  # the rounding
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    up = M[:3, :3].T @ np.array([0.0, 0.0, 10.0])  # the source's direction that became +z (M scales by 0.1)
    cam_up = np.array([by_name[f.model_extra["source_image"]][:3, 1] for f, _ in poses]).mean(axis=0)  # OpenGL y
    assert np.dot(up, cam_up / np.linalg.norm(cam_up)) > 0.9  # --up auto: the cameras' up vectors, on average


def kabsch_similarity(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale, rotation, translation with ``b ~ s R a + t`` (least squares, Umeyama)."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    U, S, Vt = np.linalg.svd((b - mb).T @ (a - ma))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / ((a - ma) ** 2).sum())
    return s, R, mb - s * R @ ma


@pytest.mark.parametrize("layout", ["binary", "text"])
def test_colmaps_own_model_of_the_photos_agrees_with_instant_ngps_poses(fox_scene: SceneDir, tmp_path: Path,
                                                                        layout: str) -> None:
    """Two real tools, one capture: COLMAP's model of the shipped photos (sparse/0, made by
    make_sample.py without instant-ngp's poses) imports and lands on instant-ngp's cameras up to a
    similarity: centres within 1 % of the ring's size, every camera's rotation within 1 degree."""
    import pycolmap

    model = SAMPLE / "sparse" / "0"
    if layout == "text":
        text = tmp_path / "text"
        text.mkdir()
        pycolmap.Reconstruction(str(model)).write_text(str(text))
        assert (text / "images.txt").is_file() and not (text / "images.bin").exists()
        model = text
    out = tmp_path / "colmap"
    code = cli_main(["import", str(model), str(out), "--images", str(SAMPLE / "images"),
                     "--scale-from-distance", "0001.jpg", "0110.jpg", "1.0", "--up", "auto"])
    assert code == 0
    ngp = {Path(f.model_extra["source_image"]).name: T for f, T in camera_poses(fox_scene)}
    cm = {Path(f.model_extra["source_image"]).name: T for f, T in camera_poses(SceneDir(out))}
    assert cm.keys() == ngp.keys() and len(cm) == 50
    names = sorted(cm)
    a = np.array([cm[n][:3, 3] for n in names])
    b = np.array([ngp[n][:3, 3] for n in names])
    s, R, t = kabsch_similarity(a, b)
    size = np.linalg.norm(b - b.mean(axis=0), axis=1).max()
    assert np.abs((s * a @ R.T + t) - b).max() < 0.01 * size
    worst = max(np.degrees(np.arccos(np.clip((np.trace(R @ cm[n][:3, :3] @ ngp[n][:3, :3].T) - 1) / 2, -1, 1)))
                for n in names)
    assert worst < 1.0, worst


@pytest.mark.slow
def test_the_fox_trains_in_miniature(fox_scene: SceneDir, tmp_path: Path) -> None:
    """The wiring on a real capture without sparse points: 60 steps at 1/2 of the shipped size."""
    preset = get_preset("fast").with_overrides(steps=60, coarse_steps=0, downscale=2, refine_start=10,
                                               refine_every=10, refine_stop=50, checkpoint_every=60,
                                               curve_every=10, depth_lambda=0.0)
    metrics = train_scene(fox_scene, preset, device="cpu", show_progress=False)
    assert metrics["steps"] == 60 and metrics["n_holdout_views"] >= 3
    assert np.isfinite(metrics["holdout"]["psnr"]) and 8.0 < metrics["holdout"]["psnr"] < 60.0
    assert fox_scene.splat_ply_path.is_file()
    assert metrics["pose_check"].startswith("pose check: 50 of 50 cameras see")  # printed by `brave6d train`


@pytest.mark.slow
def test_colmaps_model_of_the_fox_trains_in_miniature_from_its_points(tmp_path: Path) -> None:
    """The COLMAP format's wiring on this capture: the model's 5393 points start 60 steps at 1/2 size."""
    out = tmp_path / "colmap"
    assert cli_main(["import", str(SAMPLE / "sparse" / "0"), str(out), "--images", str(SAMPLE / "images"),
                     "--scale-from-distance", "0001.jpg", "0110.jpg", "1.0", "--up", "auto"]) == 0
    scene = SceneDir(out)
    preset = get_preset("fast").with_overrides(steps=60, coarse_steps=0, downscale=2, refine_start=10,
                                               refine_every=10, refine_stop=50, checkpoint_every=60,
                                               curve_every=10, depth_lambda=0.0)
    metrics = train_scene(scene, preset, device="cpu", init_method="imported", show_progress=False)
    assert metrics["init"]["source"] == "imported" and metrics["init"]["points"] > 5000
    assert metrics["steps"] == 60 and np.isfinite(metrics["holdout"]["psnr"]) and 8.0 < metrics["holdout"]["psnr"] < 60.0
    assert metrics["pose_check"].startswith("pose check: 50 of 50 cameras see")


def test_photos_of_another_size_are_refused_naming_the_frame(tmp_path: Path, fox_json: dict) -> None:
    import shutil

    import cv2

    copy = tmp_path / "src"
    shutil.copytree(SAMPLE / "images", copy / "images")
    (copy / "transforms.json").write_text(json.dumps(fox_json))
    odd = copy / "images" / "0001.jpg"
    cv2.imwrite(str(odd), cv2.resize(cv2.imread(str(odd)), (250, 480)))  # not a whole factor of 1080x1920
    code = cli_main(["import", str(copy / "transforms.json"), str(tmp_path / "scene"), "--scale", "0.1", "--up", "auto"])
    assert code != 0 and not (tmp_path / "scene").exists()


# ----------------------------------------------------------------------------- properties
@settings(max_examples=60, deadline=None)
@given(w=st.integers(16, 8000), h=st.integers(16, 8000), k=st.sampled_from([2, 3, 4, 8, 16]),
       f=st.floats(1.0, 1e5), u=st.floats(0.0, 1.0), v=st.floats(0.0, 1.0),
       x=st.floats(-2.0, 2.0), y=st.floats(-2.0, 2.0))
def test_a_scaled_camera_projects_where_the_resampled_image_shows_the_point(w, h, k, f, u, v, x, y) -> None:
    """Corner-origin pixels: a point's pixel in the copy is its pixel in the original divided by the
    size ratio; the factor is found again from the sizes; no NaN, no inf."""
    camera = SourceCamera("OPENCV", w, h, (f, f * 1.01, u * w, v * h, 0.01, -0.02, 0.001, 0.0))
    small = (max(1, w // k), max(1, h // k))
    found = downscale_factor(camera, small)
    assert found is not None and (found == k or (w // found, h // found) == small
                                  or (round(w / found), round(h / found)) == small)
    scaled = camera.scaled_to(*small)
    assert all(np.isfinite(scaled.params))
    p, q = camera.named, scaled.named
    px, py = p["fx"] * x + p["cx"], p["fy"] * y + p["cy"]
    qx, qy = q["fx"] * x + q["cx"], q["fy"] * y + q["cy"]
    assert qx == pytest.approx(px * small[0] / w, rel=1e-9, abs=1e-9)
    assert qy == pytest.approx(py * small[1] / h, rel=1e-9, abs=1e-9)


def test_a_size_that_is_no_whole_factor_is_not_taken_for_a_copy() -> None:
    camera = SourceCamera("PINHOLE", 1080, 1920, (1000.0, 1000.0, 540.0, 960.0))
    assert downscale_factor(camera, (1080, 1920)) == 1
    assert downscale_factor(camera, (270, 480)) == 4
    assert downscale_factor(camera, (250, 480)) is None and downscale_factor(camera, (1920, 1080)) is None
    with pytest.raises(DataError):
        camera.scaled_to(0, 480)


def test_a_model_without_images_names_each_place_looked_once(tmp_path: Path) -> None:
    import shutil

    shutil.copytree(SAMPLE / "sparse", tmp_path / "capture" / "sparse")
    with pytest.raises(DataError, match="no images folder found") as info:
        read_colmap(tmp_path / "capture")
    message = str(info.value)
    looked = message.split("(looked in ")[1].split(")")[0].split(", ")
    assert len(looked) == len(set(looked)) == 2, message

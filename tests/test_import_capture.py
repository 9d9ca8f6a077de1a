"""``brave6d import`` on synthetic captures whose truth is known: conventions, checks, hard cases.

The transforms.json files here are written the way nerfstudio / instant-ngp define them (OpenGL
camera axes built from the view direction: z backwards, y up), not with the importer's matrix, and
expected OpenCV poses come from ``brave6d.core.transforms.look_at``. The fisheye resampling is
checked against OpenCV's own fisheye model (``cv2.fisheye.distortPoints``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from brave6d.cli import main as cli_main
from brave6d.core.calibration_io import camera_poses, read_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import look_at
from brave6d.training import (ImportOptions, PoseCheckError, ScaleChoice, UpChoice, check_camera_poses,
                              import_capture, load_scene, read_source, train)
from brave6d.training.importing.image_io import source_pixel_maps
from brave6d.training.importing.source import SourceCamera
from brave6d.training.pose_check import axes_meeting_point

W, H = 48, 32


def ring(n: int, radius: float, elevation_deg: float = 30.0, target=(0.0, 0.0, 0.0)) -> list[np.ndarray]:
    """Eyes on a ring around ``target`` (z up) and their OpenCV ``world_T_cam`` looking at it."""
    el = math.radians(elevation_deg)
    out = []
    for i in range(n):
        az = 2 * math.pi * i / n
        eye = np.asarray(target) + radius * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        out.append(look_at(eye, target))
    return out


def gl_camera_to_world(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """An OpenGL camera-to-world matrix (x right, y up, z backwards) built from the view direction."""
    back = np.asarray(eye, float) - np.asarray(target, float)
    z = back / np.linalg.norm(back)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = x, y, z, eye
    return M


def sphere_points(radius: float, n: int = 200, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def write_ply(path: Path, xyz: np.ndarray) -> None:
    path.write_text("ply\nformat ascii 1.0\n" f"element vertex {len(xyz)}\n"
                    "property float x\nproperty float y\nproperty float z\nend_header\n"
                    + "".join(f"{p[0]} {p[1]} {p[2]}\n" for p in xyz))


def write_transforms(folder: Path, matrices: list[np.ndarray], camera: dict, *, points: np.ndarray | None = None,
                     missing: tuple[int, ...] = (), per_frame: dict[int, dict] | None = None,
                     size: tuple[int, int] = (W, H)) -> Path:
    """A transforms.json with one PNG per frame (a frame in ``missing`` is listed without its file)."""
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    rng = np.random.default_rng(1)
    for i, M in enumerate(matrices):
        name = f"images/f{i:03d}.png"
        if i not in missing:
            Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)).save(folder / name)
        frames.append({"file_path": name, "transform_matrix": np.asarray(M).tolist(), **(per_frame or {}).get(i, {})})
    data = {**camera, "frames": frames}
    if points is not None:
        write_ply(folder / "points.ply", points)
        data["ply_file_path"] = "points.ply"
    path = folder / "transforms.json"
    path.write_text(json.dumps(data))
    return path


CAMERA = {"w": W, "h": H, "fl_x": 40.0, "fl_y": 41.0, "cx": 24.5, "cy": 15.25, "camera_model": "OPENCV"}


def object_capture(folder: Path, radius: float = 0.5, n: int = 12, **kwargs) -> tuple[Path, list[np.ndarray]]:
    poses = ring(n, radius)
    gl = [gl_camera_to_world(T[:3, 3], np.zeros(3)) for T in poses]
    return write_transforms(folder, gl, kwargs.pop("camera", CAMERA), points=sphere_points(0.2 * radius), **kwargs), poses


def options(**kw) -> ImportOptions:
    return ImportOptions(scale=kw.pop("scale", ScaleChoice(factor=1.0)), up=kw.pop("up", UpChoice((0.0, 0.0, 1.0))), **kw)


# ----------------------------------------------------------------------------- conventions
def test_transforms_json_poses_become_opencv_poses_and_the_pixel_centre_moves(tmp_path: Path) -> None:
    source, truth = object_capture(tmp_path / "src")
    result = import_capture(source, tmp_path / "scene", options())
    scene = SceneDir(tmp_path / "scene")
    got = [T for _, T in camera_poses(scene)]
    assert result.frames == len(truth) == len(got)
    for T, want in zip(got, truth):  # scale 1, up +z, the axes meet at the origin: the world is unchanged
        np.testing.assert_allclose(T, want, atol=1e-9)
    cam = read_intrinsics(scene)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (40.0, 41.0, 24.0, 14.75)  # corner origin -> OpenCV: -0.5 px
    assert result.pose_check is not None and not result.pose_check.failing
    record = json.loads(scene.import_record_path.read_text())
    assert record["world"]["metres_per_source_unit"] == 1.0 and "--up 0,0,1" in record["world"]["up_from"]


def test_frames_listed_without_a_file_are_reported_by_name(tmp_path: Path) -> None:
    source, _ = object_capture(tmp_path / "src", missing=(2, 7))
    result = import_capture(source, tmp_path / "scene", options())
    assert result.missing == ["images/f002.png", "images/f007.png"]
    assert result.frames == 10
    assert json.loads(SceneDir(tmp_path / "scene").import_record_path.read_text())["missing"] == result.missing


def test_per_frame_intrinsics_win_and_different_cameras_are_resampled_to_one(tmp_path: Path) -> None:
    source, _ = object_capture(tmp_path / "src", per_frame={3: {"fl_x": 44.0}})
    result = import_capture(source, tmp_path / "scene", options())
    assert "resampled at import (2 different cameras)" in result.record["camera"]["images"]
    assert not read_intrinsics(SceneDir(tmp_path / "scene")).has_distortion


def test_the_cli_imports_and_says_where_scale_and_up_came_from(tmp_path: Path, capsys) -> None:
    source, _ = object_capture(tmp_path / "src")
    code = cli_main(["import", str(source), str(tmp_path / "scene"), "--scale-from-distance", "images/f000.png",
                     "f006", "2.0", "--up", "auto"])  # a frame by its source name, or its file name's stem
    out = capsys.readouterr().out
    assert code == 0, out
    assert "--scale-from-distance images/f000.png images/f006.png 2 m" in out and "--up auto" in out
    centres = {r.view_id: T[:3, 3] for r, T in camera_poses(SceneDir(tmp_path / "scene"))}
    assert np.linalg.norm(centres["f000"] - centres["f006"]) == pytest.approx(2.0, rel=1e-9)


def test_import_without_scale_or_up_takes_the_documented_defaults(tmp_path: Path, capsys) -> None:
    """No --scale / --scale-from-distance: the source's units are kept (1 m per unit), and the output and
    the record say so and what depends on it; no --up: auto (photos taken upright)."""
    source, _ = object_capture(tmp_path / "src")
    code = cli_main(["import", str(source), str(tmp_path / "scene")])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "scale: 1 m per source unit, from the default, 1 (no --scale or --scale-from-distance given" in out
    assert "--scale-from-distance FRAME_A FRAME_B METRES for a metric scene" in out and "up: --up auto" in out
    world = json.loads(SceneDir(tmp_path / "scene").import_record_path.read_text())["world"]
    assert world["metres_per_source_unit"] == 1.0 and world["scale_from"].startswith("the default, 1")
    given = import_capture(source, tmp_path / "given", options(scale=ScaleChoice(factor=1.0), up=UpChoice(None)))
    for (_, a), (_, b) in zip(camera_poses(SceneDir(tmp_path / "scene")), camera_poses(given.scene)):
        np.testing.assert_array_equal(a, b)  # the same world as --scale 1 --up auto


def test_up_auto_finds_a_tilted_up_and_makes_it_z(tmp_path: Path) -> None:
    tilt = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    eyes = [T[:3, 3] for T in ring(10, 1.0)]
    R = cv2.Rodrigues(np.cross([0, 0, 1.0], tilt) / np.linalg.norm(np.cross([0, 0, 1.0], tilt))
                      * math.acos(tilt[2]))[0]  # rotates +z onto the tilted up
    gl = [gl_camera_to_world(R @ e, np.zeros(3), up=tilt) for e in eyes]
    source = write_transforms(tmp_path / "src", gl, CAMERA, points=sphere_points(0.2))
    result = import_capture(source, tmp_path / "scene", options(up=UpChoice(None)))
    np.testing.assert_allclose(result.world.up_source, tilt, atol=1e-9)
    for _, T in camera_poses(SceneDir(tmp_path / "scene")):
        assert T[2, 3] == pytest.approx(math.sin(math.radians(30.0)), abs=1e-9)  # elevation kept, about the new +z


# ----------------------------------------------------------------------------- the pose check
def test_opengl_axes_read_as_opencv_are_refused_naming_the_frames(tmp_path: Path) -> None:
    poses = ring(12, 0.5)
    source = write_transforms(tmp_path / "src", poses, CAMERA, points=sphere_points(0.1))  # OpenCV matrices: the bug
    with pytest.raises(PoseCheckError, match="OpenGL") as err:
        import_capture(source, tmp_path / "scene", options())
    assert len(err.value.failing) == 12
    assert "images/f000.png (0%)" in str(err.value) and "and 4 more" in str(err.value)
    assert not (tmp_path / "scene").exists()


def test_only_the_cameras_that_look_away_are_named(tmp_path: Path) -> None:
    poses = ring(10, 0.5)
    gl = [gl_camera_to_world(T[:3, 3], np.zeros(3)) for T in poses]
    for i in (3, 8):  # these two look away from the object
        gl[i] = gl_camera_to_world(poses[i][:3, 3], 2 * poses[i][:3, 3])
    source = write_transforms(tmp_path / "src", gl, CAMERA, points=sphere_points(0.1))
    with pytest.raises(PoseCheckError) as err:
        import_capture(source, tmp_path / "scene", options())
    assert err.value.failing == ["images/f003.png", "images/f008.png"]
    ok = import_capture(source, tmp_path / "scene", options(pose_check=False))
    assert ok.pose_check is None and ok.record["pose_check"].startswith("skipped")


def test_axes_meeting_point_is_the_object_and_parallel_axes_give_none() -> None:
    np.testing.assert_allclose(axes_meeting_point(ring(8, 2.0, target=(1.0, 2.0, 3.0))), [1.0, 2.0, 3.0], atol=1e-9)
    parallel = [look_at([x, 0.0, 0.0], [x, 0.0, 5.0]) for x in (0.0, 0.1, 0.2)]
    assert axes_meeting_point(parallel) is None


def test_training_refuses_cameras_facing_away_before_it_starts(tmp_path: Path) -> None:
    from brave6d.training.toy_scenes import plane_views, write_scene

    cam = PinholeCamera(40, 30, 30.0, 30.0, 19.5, 14.5)
    views = plane_views(cam, [0.5], 6)
    for v in views:
        v.base_T_cam = v.base_T_cam @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL axes read as OpenCV
    scene = write_scene(tmp_path / "toy", cam, views)
    data = load_scene(scene)
    with pytest.raises(PoseCheckError, match="--skip-pose-check") as err:
        train(data, None, "cpu", scene=scene)  # type: ignore[arg-type]  # fails before the preset is read
    assert sorted(err.value.failing) == sorted(v.view_id for v in data.views)


# ----------------------------------------------------------------------------- cameras and images
def test_fisheye_maps_agree_with_opencvs_fisheye_model() -> None:
    k = (0.05, -0.01, 0.003, -0.001)
    source = SourceCamera("OPENCV_FISHEYE", 64, 48, (30.0, 31.0, 32.5, 24.0, *k))
    target = PinholeCamera(64, 48, 30.0, 31.0, 32.0, 23.5)
    map_x, map_y, valid = source_pixel_maps(source, target)
    assert valid == 1.0
    grid = target.pixel_grid()
    rays = np.stack([(grid[:, 0] - target.cx) / target.fx, (grid[:, 1] - target.cy) / target.fy], axis=1)
    K = np.array([[30.0, 0, 32.0], [0, 31.0, 23.5], [0, 0, 1]])  # OpenCV's pixel convention
    want = cv2.fisheye.distortPoints(rays.reshape(-1, 1, 2), K, np.array(k)).reshape(-1, 2)
    np.testing.assert_allclose(np.stack([map_x.ravel(), map_y.ravel()], axis=1), want, atol=1e-3)


def test_exif_rotated_photos_are_turned_when_only_the_turned_size_fits(tmp_path: Path) -> None:
    source, _ = object_capture(tmp_path / "src")
    rng = np.random.default_rng(5)
    stored = rng.integers(0, 255, (W, H, 3), dtype=np.uint8)  # stored portrait; EXIF 6 turns it to W x H
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(stored).save(tmp_path / "src" / "images" / "f001.jpg", exif=exif, quality=100)
    data = json.loads(source.read_text())
    data["frames"][1]["file_path"] = "images/f001.jpg"
    source.write_text(json.dumps(data))
    result = import_capture(source, tmp_path / "scene", options())
    assert result.record["exif_orientation_applied"] == ["images/f001.jpg"]
    written = np.asarray(Image.open(tmp_path / "scene" / "capture" / "rgb" / "000001.png"))
    with Image.open(tmp_path / "src" / "images" / "f001.jpg") as im:
        from PIL import ImageOps
        np.testing.assert_array_equal(written, np.asarray(ImageOps.exif_transpose(im).convert("RGB")))
    Image.fromarray(stored[:, :20]).save(tmp_path / "src" / "images" / "f001.jpg", exif=exif)
    with pytest.raises(DataError, match=r"frame images/f001.jpg: .* the image is 20x48 \(48x20 after its EXIF orientation 6\), its camera says 48x32"):
        import_capture(source, tmp_path / "scene2", options())


@pytest.mark.parametrize(("change", "message"), [
    ({"fl_x": 0.0}, "focal length fx must be positive"),
    ({"w": 0}, "fields 'w', 'h': whole numbers"),
    ({"w": 47.5}, "fields 'w', 'h': whole numbers"),
    ({"camera_model": "EQUIRECTANGULAR"}, "field 'camera_model': 'EQUIRECTANGULAR' is not supported"),
    ({"k4": 0.01}, "field 'k4'"),
    ({"fl_x": None, "camera_angle_x": 3.5}, "field 'camera_angle_x': a field of view in"),
])
def test_degenerate_intrinsics_are_refused_naming_the_field(tmp_path: Path, change: dict, message: str) -> None:
    camera = {k: v for k, v in {**CAMERA, **change}.items() if v is not None}
    source, _ = object_capture(tmp_path / "src", camera=camera)
    with pytest.raises(DataError, match=r"frames\[0\]'? \(images/f000.png\).*" + message.replace("(", r"\(")):
        read_source(source)


def test_a_pose_that_is_not_rigid_is_refused_naming_the_frame(tmp_path: Path) -> None:
    poses = [gl_camera_to_world(T[:3, 3], np.zeros(3)) for T in ring(4, 0.5)]
    poses[2][:3, :3] *= 2.0
    source = write_transforms(tmp_path / "src", poses, CAMERA)
    with pytest.raises(DataError, match=r"frames\[2\]' \(images/f002.png\)"):
        read_source(source)


def test_rotations_rounded_as_real_files_are_import_projected_and_the_correction_recorded(tmp_path: Path,
                                                                                         capsys) -> None:
    # instant-ngp's fox: six printed digits, column norms 1.000001 (max |R^T R - I| = 1.09e-6)
    truth = ring(6, 0.5)
    gl = [np.round(gl_camera_to_world(T[:3, 3], np.zeros(3)), 6) for T in truth]
    gl[3][:3, 0] *= 1.000001
    gl[3][:3, 2] *= 1.000001
    source = write_transforms(tmp_path / "src", gl, CAMERA, points=sphere_points(0.1))
    code = cli_main(["import", str(source), str(tmp_path / "scene"), "--scale", "1", "--up", "0,0,1"])
    assert code == 0, capsys.readouterr()
    scene = SceneDir(tmp_path / "scene")
    for (_, T), want in zip(camera_poses(scene), truth):
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        np.testing.assert_allclose(T, want, atol=1e-5)
    rotations = json.loads(scene.import_record_path.read_text())["rotations"]
    assert rotations["largest_correction_frame"] == "images/f003.png"
    assert 5e-7 < rotations["largest_correction"] < 1e-5 and rotations["tolerance"] == 1e-3


def test_a_sheared_rotation_is_refused_by_the_cli_in_one_line_naming_the_frame(tmp_path: Path, capsys) -> None:
    gl = [gl_camera_to_world(T[:3, 3], np.zeros(3)) for T in ring(4, 0.5)]
    gl[1][:3, 1] += 0.01 * gl[1][:3, 0]  # a shear of 1 %: |R^T R - I| = 1e-2, ten times the tolerance
    source = write_transforms(tmp_path / "src", gl, CAMERA, points=sphere_points(0.1))
    code = cli_main(["import", str(source), str(tmp_path / "scene"), "--scale", "1", "--up", "0,0,1"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "frames[1]' (images/f001.png).transform_matrix: rotation block is not orthonormal" in err
    assert "Traceback" not in err and not (tmp_path / "scene").exists()


# ----------------------------------------------------------------------------- properties
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(radius=st.floats(0.3, 10.0), unit=st.sampled_from([0.001, 1.0, 1000.0]), k1=st.floats(-0.3, 0.6),
       fisheye=st.booleans(), elevation=st.floats(5.0, 80.0))
def test_any_scene_size_and_strong_distortion_imports_finite_and_checked(tmp_path_factory, radius: float,
                                                                          unit: float, k1: float, fisheye: bool,
                                                                          elevation: float) -> None:
    """A 0.3 m object capture up to a 10 m room, in mm, m or km source units, fisheye-like k1:
    finite poses and intrinsics, the cameras at the right metric distance, the pose check passes."""
    folder = tmp_path_factory.mktemp("prop")
    poses = ring(8, radius / unit, elevation)
    gl = [gl_camera_to_world(T[:3, 3], np.zeros(3)) for T in poses]
    camera = {**CAMERA, "k1": k1, "camera_model": "OPENCV_FISHEYE" if fisheye else "OPENCV"}
    source = write_transforms(folder / "src", gl, camera, points=sphere_points(0.3 * radius / unit, 50))
    result = import_capture(source, folder / "scene", options(scale=ScaleChoice(factor=unit), up=UpChoice(None)))
    scene = SceneDir(folder / "scene")
    cam = read_intrinsics(scene)
    assert all(math.isfinite(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist))
    for record, T in camera_poses(scene):
        assert np.isfinite(T).all()
        assert record.distance_m == pytest.approx(radius, rel=1e-6)
    assert result.pose_check is not None and not result.pose_check.failing
    assert (cam.has_distortion is False) == (fisheye or k1 == 0.0)


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 6), flip=st.lists(st.booleans(), min_size=6, max_size=6), radius=st.floats(0.3, 10.0))
def test_the_check_names_exactly_the_flipped_cameras(n: int, flip: list[bool], radius: float) -> None:
    cam = PinholeCamera(W, H, 40.0, 40.0, 23.5, 15.5)
    poses = ring(n, radius)
    named = [(f"v{i}", T @ np.diag([1.0, -1.0, -1.0, 1.0]) if flip[i] else T) for i, T in enumerate(poses)]
    points = sphere_points(0.2 * radius)
    flipped = [name for (name, _), f in zip(named, flip) if f]
    if flipped:
        with pytest.raises(PoseCheckError) as err:
            check_camera_poses(cam, named, points, "points")
        assert err.value.failing == flipped
    else:
        assert not check_camera_poses(cam, named, points, "points").failing


@pytest.mark.parametrize("ngp", [True, False])
def test_without_points_the_ngp_cube_or_the_axes_meeting_point_is_the_reference(tmp_path: Path, ngp: bool) -> None:
    camera = {**CAMERA, **({"aabb_scale": 16, "scale": 0.5, "offset": [0.4, 0.55, 0.35]} if ngp else {})}
    # instant-ngp's cube centre in file coordinates: ((0.5 - offset) / scale) with the axes cycled (x <- z, y <- x, z <- y)
    target = np.array([(0.5 - 0.35) / 0.5, (0.5 - 0.4) / 0.5, (0.5 - 0.55) / 0.5]) if ngp else np.array([0.3, -0.2, 0.1])
    poses = ring(8, 2.0, target=tuple(target))
    good = [gl_camera_to_world(T[:3, 3], target) for T in poses]
    result = import_capture(write_transforms(tmp_path / "a", good, camera), tmp_path / "ok", options())
    assert result.pose_check is not None
    assert ("instant-ngp's unit cube" if ngp else "optical axes meet") in result.pose_check.reference
    with pytest.raises(PoseCheckError, match="OpenGL"):
        import_capture(write_transforms(tmp_path / "b", poses, camera), tmp_path / "bad", options())


def test_training_falls_back_to_the_imported_points_when_colmap_finds_too_few(tmp_path: Path) -> None:
    from brave6d.training.colmap_init import ColmapOptions, initial_points

    source, _ = object_capture(tmp_path / "src")  # noise images: nothing for COLMAP to triangulate
    import_capture(source, tmp_path / "scene", options())
    scene = SceneDir(tmp_path / "scene")
    data = load_scene(scene)
    init = initial_points(scene, data, ColmapOptions(max_features=256, neighbours=2), max_points=3000)
    assert init.source == "imported" and len(init) == 200
    assert "points (< 1000)" in init.details["colmap"]
    np.testing.assert_allclose(np.linalg.norm(init.points, axis=1), 0.1, rtol=1e-6)  # the sphere of radius 0.2 x 0.5
    explicit = initial_points(scene, data, method="imported", max_points=3000)
    assert explicit.source == "imported" and "colmap" not in explicit.details

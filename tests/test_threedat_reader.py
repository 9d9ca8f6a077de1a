"""3D-DAT reader and writer: the hand-made fixture, every malformed case, and round trips."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.annotation.threedat import (
    LibraryEntry,
    ThreeDatError,
    find_config,
    read_camera_poses,
    read_config,
    read_threedat,
)
from brave6d.annotation.threedat_writer import write_threedat_folder
from brave6d.core.camera import PinholeCamera
from brave6d.core.transforms import make_transform

FIXTURE = Path(__file__).parent / "fixtures" / "threedat"


@pytest.fixture()
def dat(tmp_path: Path) -> Path:
    """A writable copy of the fixture."""
    return Path(shutil.copytree(FIXTURE, tmp_path / "dat"))


def _edit_yaml(path: Path, edit) -> None:
    data = yaml.safe_load(path.read_text())
    edit(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


# ----------------------------------------------------------------------------- the fixture
def test_fixture_reads_with_the_expected_content() -> None:
    scene = read_threedat(FIXTURE)
    assert scene.scene_id == "scene1"
    assert [e.id for e in scene.library] == ["cube", "bar"]
    assert scene.library[0].scale == 0.001 and scene.library[0].mesh.name == "cube.ply"
    assert scene.library[0].class_name == "toys_office" and scene.library[0].color == (255, 0, 0)
    assert [o.object_id for o in scene.objects] == ["cube", "bar", "cube"]  # ids may repeat
    assert [o.entry for o in scene.objects] == [1, 2, 3]
    np.testing.assert_array_equal(scene.objects[0].world_T_model,
                                  [[0, -1, 0, 0.1], [1, 0, 0, 0.02], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert (scene.camera.width, scene.camera.height, scene.camera.fx, scene.camera.cy) == (64, 48, 60.0, 23.5)
    assert [p.frame_id for p in scene.camera_poses] == ["0", "1", "2"]


def test_camera_quaternions_are_scalar_last() -> None:
    poses = read_threedat(FIXTURE).camera_poses
    # frame 0: (qx qy qz qw) = (1 0 0 0) is 180 deg about x, NOT the identity
    np.testing.assert_array_equal(poses[0].world_T_cam[:3, :3], np.diag([1.0, -1.0, -1.0]))
    # frame 1 (comma separated): 120 deg about (-1, -1, 1): camera z = world -x, camera y = world -z
    np.testing.assert_allclose(poses[1].world_T_cam[:3, :3], [[0, 0, -1], [1, 0, 0], [0, -1, 0]], atol=1e-15)
    np.testing.assert_array_equal(poses[1].world_T_cam[:3, 3], [0.5, 0.0, 0.05])
    np.testing.assert_array_equal(poses[2].world_T_cam[:3, :3], np.eye(3))


def test_symmetries_from_the_library() -> None:
    cube, bar = read_threedat(FIXTURE).library
    assert len(cube.symmetries_discrete) == 1
    np.testing.assert_array_equal(cube.symmetries_discrete[0][:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert bar.symmetries_continuous[0].axis == (1.0, 0.0, 0.0)
    assert bar.symmetries_continuous[0].offset == (0.0, 0.005, 0.003)


def test_config_paths_are_relative_to_the_config_file(dat: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)  # somewhere else entirely
    cfg = read_config(dat / "dataset.yaml")
    assert cfg.scenes_dir == (dat / "scenes").resolve()
    assert cfg.object_library_file == (dat / "objects" / "object_library.yaml").resolve()
    assert find_config(dat) == dat / "dataset.yaml"


def test_pose_yaml_is_accepted_as_the_alternative_name(dat: Path) -> None:
    (dat / "annotations" / "scene1" / "poses.yaml").rename(dat / "annotations" / "scene1" / "pose.yaml")
    scene = read_threedat(dat)
    assert len(scene.objects) == 3 and scene.files["poses"].name == "pose.yaml"
    # and the other way round: the config names pose.yaml, the folder has poses.yaml
    (dat / "annotations" / "scene1" / "pose.yaml").rename(dat / "annotations" / "scene1" / "poses.yaml")
    _edit_yaml(dat / "dataset.yaml", lambda d: d["General"].update(object_pose_file="pose.yaml"))
    assert len(read_threedat(dat).objects) == 3


def test_shared_camera_yaml_in_scenes_dir(dat: Path) -> None:
    (dat / "scenes" / "scene1" / "camera.yaml").rename(dat / "scenes" / "camera.yaml")
    assert read_threedat(dat).camera.width == 64


@pytest.mark.parametrize("stored, atol", [
    (lambda m: m.astype(np.float32).astype(np.float64), 1e-6),  # what Blender stores
    (lambda m: np.round(m, 4), 1e-4),  # four printed decimals: |R^T R - I| ~1e-4, refused before the one rule
])
def test_float32_precision_poses_are_accepted_and_made_exactly_rigid(dat: Path, stored, atol: float) -> None:
    R = Rotation.from_euler("xyz", [12.3, -45.6, 78.9], degrees=True).as_matrix()
    pose = stored(make_transform(R, [0.1, 0.2, 0.3]))
    _edit_yaml(dat / "annotations" / "scene1" / "poses.yaml", lambda d: d[0].update(pose=pose.reshape(-1).tolist()))
    T = read_threedat(dat).objects[0].world_T_model
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-14)
    np.testing.assert_allclose(T, pose, atol=atol)


def test_integer_ids_and_comments(dat: Path) -> None:
    _edit_yaml(dat / "objects" / "object_library.yaml", lambda d: [e.update(id=i + 7) for i, e in enumerate(d)])
    _edit_yaml(dat / "annotations" / "scene1" / "poses.yaml",
               lambda d: [e.update(id=7 if e["id"] == "cube" else 8) for e in d])
    path = dat / "scenes" / "scene1" / "groundtruth_handeye.txt"
    path.write_text("# id tx ty tz qx qy qz qw\n\n" + path.read_text())
    scene = read_threedat(dat)
    assert [o.object_id for o in scene.objects] == [7, 8, 7]
    assert [p.line for p in scene.camera_poses] == [3, 4, 5]


# ----------------------------------------------------------------------------- malformed inputs
def _expect(dat: Path, *fragments: str) -> None:
    with pytest.raises(ThreeDatError) as info:
        read_threedat(dat)
    message = str(info.value)
    for fragment in fragments:
        assert fragment in message, message


def test_unknown_object_id_names_file_and_entry(dat: Path) -> None:
    _edit_yaml(dat / "annotations" / "scene1" / "poses.yaml", lambda d: d[2].update(id="mug"))
    _expect(dat, "annotations/scene1/poses.yaml", "entry 3", "'mug'", "unknown object id")


@pytest.mark.parametrize("kind, matrix, fragment", [
    ("scaled", np.diag([2.0, 2.0, 2.0, 1.0]), "not orthonormal"),
    ("sheared", np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "not orthonormal"),
    ("bottom row", np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1.0]]), "bottom row"),
    ("reflection", np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
    ("nan", np.array([[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "NaN"),
])
def test_non_rigid_pose_names_file_and_entry(dat: Path, kind: str, matrix: np.ndarray, fragment: str) -> None:
    path = dat / "annotations" / "scene1" / "poses.yaml"
    data = yaml.safe_load(path.read_text())
    data[1]["pose"] = matrix.reshape(-1).tolist()
    path.write_text(yaml.safe_dump(data))
    _expect(dat, "annotations/scene1/poses.yaml", "entry 2", "'bar'", "pose is not rigid", fragment)


def test_pose_with_wrong_length_or_missing(dat: Path) -> None:
    _edit_yaml(dat / "annotations" / "scene1" / "poses.yaml", lambda d: d[0].update(pose=[1.0] * 12))
    _expect(dat, "poses.yaml", "entry 1", "16 numbers")
    _edit_yaml(dat / "annotations" / "scene1" / "poses.yaml", lambda d: d[0].pop("pose"))
    _expect(dat, "poses.yaml", "entry 1", "'pose' is missing")


def test_missing_mesh_names_library_and_entry(dat: Path) -> None:
    (dat / "objects" / "bar" / "bar.ply").unlink()
    _expect(dat, "objects/object_library.yaml", "entry 2", "'bar'", "mesh not found", "bar/bar.ply")


@pytest.mark.parametrize("line, fragment", [
    ("3 0.1 0.2 0.3 0 0 0", "8 fields"),
    ("3 0.1 0.2 0.3 0 0 0 1 9", "8 fields"),
    ("3 0.1 zero 0.3 0 0 0 1", "non-numeric"),
    ("3 0.1 0.2 0.3 0 0 0 0", "zero quaternion"),
    ("3 0.1 0.2 0.3 0 0 0 2", "unit quaternion"),
    ("1 0.1 0.2 0.3 0 0 0 1", "appears twice"),
])
def test_malformed_handeye_line_names_file_and_line(dat: Path, line: str, fragment: str) -> None:
    path = dat / "scenes" / "scene1" / "groundtruth_handeye.txt"
    path.write_text(path.read_text() + line + "\n")
    _expect(dat, "scenes/scene1/groundtruth_handeye.txt:4", fragment)


@pytest.mark.parametrize("key", ["camera_intrinsics_file", "camera_pose_file"])
def test_missing_config_key_without_a_3ddat_default(dat: Path, key: str) -> None:
    _edit_yaml(dat / "dataset.yaml", lambda d: d["General"].pop(key))
    _expect(dat, "dataset.yaml", "General", f"missing key '{key}'")


def test_other_library_errors(dat: Path) -> None:
    lib = dat / "objects" / "object_library.yaml"
    original = lib.read_text()
    _edit_yaml(lib, lambda d: d[1].update(id="cube"))
    _expect(dat, "object_library.yaml", "entry 2", "duplicate id")
    lib.write_text(original)
    _edit_yaml(lib, lambda d: d[0].update(scale=-1))
    _expect(dat, "object_library.yaml", "entry 1", "'scale'")
    lib.write_text(original)
    _edit_yaml(lib, lambda d: d[0].update(symmetries_discrete=[[2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]))
    _expect(dat, "object_library.yaml", "entry 1", "symmetries_discrete")
    lib.write_text("- id: cube\n  mesh: [unclosed\n")
    _expect(dat, "object_library.yaml:", "invalid YAML")


def test_camera_yaml_errors(dat: Path) -> None:
    cam = dat / "scenes" / "scene1" / "camera.yaml"
    _edit_yaml(cam, lambda d: d.update(camera_matrix=[60.0, 0.0, 31.5]))
    _expect(dat, "scenes/scene1/camera.yaml", "camera_matrix", "9 numbers")
    _edit_yaml(cam, lambda d: d.pop("image_width"))
    _expect(dat, "scenes/scene1/camera.yaml", "image_width")


def test_several_scenes_need_a_choice(dat: Path) -> None:
    shutil.copytree(dat / "scenes" / "scene1", dat / "scenes" / "scene2")
    shutil.copytree(dat / "annotations" / "scene1", dat / "annotations" / "scene2")
    _expect(dat, "2 annotated scenes", "--scene")
    assert read_threedat(dat, "scene2").scene_id == "scene2"
    with pytest.raises(ThreeDatError, match="scene folder not found"):
        read_threedat(dat, "scene9")


# ----------------------------------------------------------------------------- writer round trips
def test_writer_then_reader_is_exact(tmp_path: Path) -> None:
    src = read_threedat(FIXTURE)
    poses = {int(p.frame_id): p.world_T_cam for p in src.camera_poses}
    objects = [(src.entry(o.object_id), o.world_T_model) for o in src.objects]
    cfg = write_threedat_folder(tmp_path / "out", "scene_a", objects, src.camera.pinhole(), poses,
                                camera_name="tiny")
    back = read_threedat(cfg.parent)
    assert back.scene_id == "scene_a" and back.camera == src.camera.__class__(64, 48, 60.0, 60.0, 31.5, 23.5, "tiny")
    assert [(e.id, e.name, e.scale, e.class_name, e.description, e.color) for e in back.library] == \
        [(e.id, e.name, e.scale, e.class_name, e.description, e.color) for e in src.library]
    for a, b in zip(back.library, src.library):
        assert a.mesh.read_bytes() == b.mesh.read_bytes()
        assert a.symmetries_continuous == b.symmetries_continuous
        np.testing.assert_array_equal(np.array(a.symmetries_discrete), np.array(b.symmetries_discrete))
    for a, b in zip(back.objects, src.objects):
        assert a.object_id == b.object_id
        np.testing.assert_array_equal(a.world_T_model, b.world_T_model)
    for a, b in zip(back.camera_poses, src.camera_poses):
        assert a.frame_id == b.frame_id
        np.testing.assert_allclose(a.world_T_cam, b.world_T_cam, atol=1e-15)
    text = (cfg.parent / "scenes" / "scene_a" / "groundtruth_handeye.txt").read_text()
    assert "," not in text and len(text.splitlines()[0].split()) == 8


@settings(max_examples=25)
@given(st.lists(st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1),
                          st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(0.1, 1)),
                min_size=1, max_size=6))
def test_round_trip_of_random_poses(tmp_path_factory, values) -> None:
    out = tmp_path_factory.mktemp("rt")
    cube = read_threedat(FIXTURE).library[0]
    poses, objects = {}, []
    for i, (a, b, c, x, y, z, w) in enumerate(values):
        R = Rotation.from_rotvec([a * math.pi, b, c]).as_matrix()
        poses[i * 5] = make_transform(R, [x, y, z])
        objects.append((cube, make_transform(R.T, [z, x, w])))
    cfg = write_threedat_folder(out / "dat", "s", objects, PinholeCamera(32, 24, 30.0, 31.0, 15.5, 11.5), poses)
    back = read_threedat(cfg)
    assert [int(p.frame_id) for p in back.camera_poses] == sorted(poses)
    for p in back.camera_poses:
        np.testing.assert_allclose(p.world_T_cam, poses[int(p.frame_id)], atol=1e-12)
    for o, (_, T) in zip(back.objects, objects):
        np.testing.assert_allclose(o.world_T_model, T, atol=1e-15)


def test_writer_refuses_to_replace_a_foreign_folder(tmp_path: Path) -> None:
    src = read_threedat(FIXTURE)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("precious")
    with pytest.raises(Exception, match="not a 3D-DAT folder"):
        write_threedat_folder(tmp_path / "mine", "s", [(src.library[0], np.eye(4))], src.camera.pinhole(),
                              {0: np.eye(4)})
    assert (tmp_path / "mine" / "thesis.tex").read_text() == "precious"


def test_writer_failure_writes_nothing(tmp_path: Path) -> None:
    src = read_threedat(FIXTURE)
    ghost = LibraryEntry("ghost", tmp_path / "missing.ply", 0.001)
    with pytest.raises(Exception, match="mesh of 'ghost' not found"):
        write_threedat_folder(tmp_path / "out", "s", [(src.library[0], np.eye(4)), (ghost, np.eye(4))],
                              src.camera.pinhole(), {0: np.eye(4)})
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_read_camera_poses_accepts_commas_and_spaces(tmp_path: Path) -> None:
    path = tmp_path / "gt.txt"
    path.write_text("a,1,2,3,0,0,0,1\nb 1 2 3 0 0 0 1\nc, 1, 2, 3, 0, 0, 0, 1\n")
    poses = read_camera_poses(path)
    assert [p.frame_id for p in poses] == ["a", "b", "c"]
    for p in poses:
        np.testing.assert_array_equal(p.world_T_cam[:3, 3], [1, 2, 3])


# ----------------------------------------------------------------------------- what 3D-DAT's reader accepts
def _write_like_3ddat(out: Path, **kwargs) -> Path:
    """The fixture's scene written the way 3D-DAT lays it out by default (config with only the two
    keys 3D-DAT has no default for, library at objects/objects.yaml, poses.yaml)."""
    src = read_threedat(FIXTURE)
    poses = {int(p.frame_id): p.world_T_cam for p in src.camera_poses}
    objects = [(src.entry(o.object_id), o.world_T_model) for o in src.objects]
    return write_threedat_folder(out, "001", objects, src.camera.pinhole(), poses, defaults_only=True, **kwargs)


def test_config_without_the_keys_3ddat_has_defaults_for(tmp_path: Path) -> None:
    cfg = _write_like_3ddat(tmp_path / "dat")
    assert set(yaml.safe_load(cfg.read_text())["General"]) == {"camera_intrinsics_file", "camera_pose_file"}
    scene = read_threedat(cfg.parent)
    root = cfg.parent.resolve()
    assert scene.config.scenes_dir == root / "scenes" and scene.config.annotation_dir == root / "annotations"
    assert scene.config.object_library_file == root / "objects" / "objects.yaml"
    assert scene.config.object_pose_file == "poses.yaml" and scene.config.rgb_dir == "rgb"
    assert scene.scene_id == "001" and [o.object_id for o in scene.objects] == ["cube", "bar", "cube"]
    assert scene.warnings == ()


@pytest.mark.parametrize("value", [None, ""])
def test_empty_annotation_dir_and_library_file_mean_3ddat_defaults(dat: Path, value) -> None:
    (dat / "objects" / "object_library.yaml").rename(dat / "objects" / "objects.yaml")
    _edit_yaml(dat / "dataset.yaml", lambda d: d["General"].update(annotation_dir=value, object_library_file=value))
    scene = read_threedat(dat)
    assert scene.files["library"] == dat.resolve() / "objects" / "objects.yaml"
    assert scene.files["poses"] == dat.resolve() / "annotations" / "scene1" / "poses.yaml"


def test_empty_scenes_dir_is_the_root_and_null_is_refused(tmp_path: Path) -> None:
    cfg = _write_like_3ddat(tmp_path / "dat")
    _edit_yaml(cfg, lambda d: d["General"].update(scenes_dir=None))
    _expect(cfg, "dataset.yaml", "General", "'scenes_dir'", "leave it out")
    (cfg.parent / "scenes" / "001").rename(cfg.parent / "001")
    _edit_yaml(cfg, lambda d: d["General"].update(scenes_dir=""))
    assert read_threedat(cfg).config.scenes_dir == cfg.parent.resolve()


def test_root_dir_in_the_config(dat: Path, tmp_path: Path, monkeypatch) -> None:
    elsewhere = tmp_path / "configs" / "dataset.yaml"
    elsewhere.parent.mkdir()
    (dat / "dataset.yaml").rename(elsewhere)
    _edit_yaml(elsewhere, lambda d: d["General"].update(root_dir=str(dat)))
    scene = read_threedat(elsewhere)
    assert scene.config.root == dat.resolve() and len(scene.objects) == 3
    # a relative root_dir is joined onto the working directory, as 3D-DAT joins it
    monkeypatch.chdir(tmp_path)
    _edit_yaml(elsewhere, lambda d: d["General"].update(root_dir="dat"))
    assert read_threedat(elsewhere).config.scenes_dir == dat.resolve() / "scenes"
    monkeypatch.chdir(elsewhere.parent)
    _expect(elsewhere, "dataset.yaml", "root_dir 'dat' is not a folder", "working directory")


@pytest.mark.parametrize("value, expected", [(None, 1.0), ("", 1.0), (0, 1.0), ("0.5", 0.5)])
def test_empty_scale_means_one(dat: Path, value, expected: float) -> None:
    _edit_yaml(dat / "objects" / "object_library.yaml", lambda d: d[1].update(scale=value))
    assert read_threedat(dat).library[1].scale == expected


def test_library_entries_without_mesh(dat: Path) -> None:
    lib = dat / "objects" / "object_library.yaml"
    _edit_yaml(lib, lambda d: d.extend([{"id": "idea", "name": "no mesh yet"}, {"id": "sketch", "mesh": ""}]))
    scene = read_threedat(dat)
    assert [(e.id, e.mesh) for e in scene.library[2:]] == [("idea", None), ("sketch", None)]
    assert len(scene.objects) == 3
    _edit_yaml(dat / "annotations" / "scene1" / "poses.yaml", lambda d: d[1].update(id="idea"))
    _expect(dat, "annotations/scene1/poses.yaml", "entry 2", "'idea' has no mesh", "entry 3")


def test_empty_pose_list_is_a_scene_without_objects(dat: Path) -> None:
    pose_file = dat / "annotations" / "scene1" / "poses.yaml"
    pose_file.write_text("[]\n")  # what 3D-DAT's save_pose writes for a scene without objects
    scene = read_threedat(dat)
    assert scene.objects == ()
    assert scene.warnings == ("annotations/scene1/poses.yaml: no annotated objects (an empty list)",)
    pose_file.write_text("")  # no YAML list at all: 3D-DAT fails on it too
    _expect(dat, "annotations/scene1/poses.yaml", "expected a YAML list")


def test_missing_configured_pose_file_says_which_file_was_read(dat: Path) -> None:
    (dat / "annotations" / "scene1" / "poses.yaml").rename(dat / "annotations" / "scene1" / "pose.yaml")
    scene = read_threedat(dat)
    assert scene.files["poses"].name == "pose.yaml" and len(scene.objects) == 3
    assert scene.warnings == ("annotations/scene1/poses.yaml (object_pose_file in dataset.yaml) not found; "
                              "read annotations/scene1/pose.yaml instead",)
    (dat / "annotations" / "scene1" / "pose.yaml").unlink()
    with pytest.raises(ThreeDatError, match=r"annotations/scene1/poses.yaml: object pose file not found"):
        read_threedat(dat, "scene1")


def test_rgb_files_in_3ddat_order(dat: Path) -> None:
    rgb = dat / "scenes" / "scene1" / "rgb"
    for name in ["b/000000.png", "000010.jpg", "000002.png", "000003.PNG", "000004.jpeg", "notes.txt", "a/000009.png"]:
        (rgb / name).parent.mkdir(parents=True, exist_ok=True)
        (rgb / name).write_bytes(b"")
    names = [p.relative_to(rgb).as_posix() for p in read_threedat(dat).rgb_files]
    assert names == ["000002.png", "000010.jpg", "a/000009.png", "b/000000.png"]

"""Import the hand-made 3D-DAT fixture into a captured scene and export BOP: hand-computed poses."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from brave6d.annotation.alignment import AlignmentError
from brave6d.annotation.bop import BopExportOptions, export_bop
from brave6d.annotation.bop_format import BopLayout, read_models_info, read_scene_camera, read_scene_gt
from brave6d.annotation.importer import assign_obj_ids, import_threedat
from brave6d.annotation.store import AnnotatedObject, load_annotation, write_annotation
from brave6d.annotation.toy_scene import make_synthetic_scene
from brave6d.annotation.threedat import read_threedat
from brave6d.annotation.threedat_writer import write_threedat_folder
from brave6d.cli import main as cli_main
from brave6d.core.errors import BraveError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import invert, look_at, make_transform

FIXTURE = Path(__file__).parent / "fixtures" / "threedat"

# Expected values worked out by hand (see tests/fixtures/threedat/README.md):
# cam_T_model = inv(world_T_cam) @ world_T_model, translation in mm. Views 0, 1, 2; instances
# cube (Rz 90 at (0.1, 0.02, 0)), bar (Rx 180 at (0.05, -0.03, 0.006)), cube (identity at 0).
EXPECTED = {
    0: [([[0, -1, 0], [-1, 0, 0], [0, 0, -1]], [100, -20, 500]),
        ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], [50, 30, 494]),
        ([[1, 0, 0], [0, -1, 0], [0, 0, -1]], [0, 0, 500])],
    1: [([[1, 0, 0], [0, 0, -1], [0, 1, 0]], [20, 50, 400]),
        ([[0, -1, 0], [0, 0, 1], [-1, 0, 0]], [-30, 44, 450]),
        ([[0, 1, 0], [0, 0, -1], [-1, 0, 0]], [0, 50, 500])],
    2: [([[0, -1, 0], [1, 0, 0], [0, 0, 1]], [90, 0, 400]),
        ([[1, 0, 0], [0, -1, 0], [0, 0, -1]], [40, -50, 406]),
        ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], [-10, -20, 400])],
}
# obj_ids: library ids sorted -> 'bar' = 1, 'cube' = 2
EXPECTED_OBJ_IDS = [2, 1, 2]
# A known hand-eye transform, so base_T_tcp differs from base_T_cam.
TCP_T_CAM = make_transform(Rotation.from_euler("xyz", [3, -2, 91], degrees=True).as_matrix(), [0.004, -0.063, 0.029])


def _scene(tmp_path: Path, base_T_dat: np.ndarray | None = None):
    """A captured scene whose calibrated camera poses are the fixture's, expressed via ``base_T_dat``."""
    dat = read_threedat(FIXTURE)
    B = np.eye(4) if base_T_dat is None else base_T_dat
    poses = {int(p.frame_id): B @ p.world_T_cam for p in dat.camera_poses}
    return make_synthetic_scene(tmp_path / "scene", dat.camera.pinhole(), poses, tcp_T_cam=TCP_T_CAM)


def _check_scene_gt(scene) -> None:
    layout = BopLayout.of_scene(scene)
    gt = read_scene_gt(layout.scene_gt_path)
    assert sorted(gt) == [0, 1, 2]
    for im_id, expected in EXPECTED.items():
        assert [g.obj_id for g in gt[im_id]] == EXPECTED_OBJ_IDS
        for g, (R, t) in zip(gt[im_id], expected):
            np.testing.assert_allclose(g.cam_R_m2c, R, rtol=0, atol=1e-9)
            np.testing.assert_allclose(g.cam_t_m2c, t, rtol=0, atol=1e-6)  # mm


def test_hand_computed_cam_poses_same_frame(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    result = import_threedat(FIXTURE, scene.root)
    assert not result.alignment.applied and result.matched_by == "frame index"
    export_bop(scene.root)
    _check_scene_gt(scene)
    # scene_camera: cam_T_world of view 0 (looking down from 0.5 m), K of the undistorted camera
    cams = read_scene_camera(BopLayout.of_scene(scene).scene_camera_path)
    np.testing.assert_allclose(cams[0].cam_R_w2c, np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(cams[0].cam_t_w2c, [0.0, 0.0, 500.0], atol=1e-9)
    np.testing.assert_array_equal(cams[0].cam_K, [[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]])
    assert cams[0].depth_scale == 1.0


def test_hand_computed_cam_poses_through_a_frame_offset(tmp_path: Path) -> None:
    """3D-DAT world != robot base: the alignment is estimated; camera-frame poses do not change."""
    base_T_dat = make_transform(Rotation.from_euler("xyz", [5, -10, 120], degrees=True).as_matrix(), [0.3, -0.25, 0.12])
    scene = _scene(tmp_path, base_T_dat)
    result = import_threedat(FIXTURE, scene.root)
    assert result.alignment.applied and result.alignment.rms_mm < 1e-6
    np.testing.assert_allclose(result.alignment.target_T_source, base_T_dat, atol=1e-12)
    annotation = load_annotation(scene)
    np.testing.assert_allclose(annotation.instances[0].world_T_model,
                               base_T_dat @ read_threedat(FIXTURE).objects[0].world_T_model, atol=1e-12)
    export_bop(scene.root)
    _check_scene_gt(scene)
    report = json.loads((scene.annotation_dir / "alignment.json").read_text())
    assert report["applied"] and len(report["residuals"]) == 3


def test_inconsistent_camera_poses_are_refused_and_nothing_written(tmp_path: Path) -> None:
    dat = read_threedat(FIXTURE)
    poses = {int(p.frame_id): p.world_T_cam.copy() for p in dat.camera_poses}
    poses[1][:3, 3] += [0.0, 0.02, 0.0]  # view 1 captured 2 cm elsewhere
    scene = make_synthetic_scene(tmp_path / "scene", dat.camera.pinhole(), poses, tcp_T_cam=TCP_T_CAM)
    with pytest.raises(AlignmentError, match="worst frames"):
        import_threedat(FIXTURE, scene.root)
    assert not scene.annotation_dir.exists()


def test_obj_ids_are_stable_across_reimports(tmp_path: Path) -> None:
    dat_dir = Path(shutil.copytree(FIXTURE, tmp_path / "dat"))
    scene = _scene(tmp_path)
    import_threedat(dat_dir, scene.root)
    assert load_annotation(scene).id_map == {"bar": 1, "cube": 2}
    # the lab adds an object whose id sorts first; existing ids must not move
    lib = dat_dir / "objects" / "object_library.yaml"
    data = yaml.safe_load(lib.read_text())
    data.append({"id": "anvil", "mesh": "cube/cube.ply", "scale": 0.001})
    lib.write_text(yaml.safe_dump(data))
    import_threedat(dat_dir, scene.root)
    annotation = load_annotation(scene)
    assert annotation.id_map == {"bar": 1, "cube": 2, "anvil": 3}
    assert [o.obj_id for o in annotation.objects] == [1, 2]  # anvil is not annotated yet: no object
    poses = dat_dir / "annotations" / "scene1" / "poses.yaml"
    poses.write_text(poses.read_text() + "- {id: anvil, pose: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}\n")
    import_threedat(dat_dir, scene.root)
    annotation = load_annotation(scene)
    assert annotation.id_map == {"bar": 1, "cube": 2, "anvil": 3}
    assert [o.obj_id for o in annotation.objects] == [1, 2, 3]
    # a fresh scene with the same library gets the sorted mapping
    assert assign_obj_ids(["cube", "bar", "anvil"], {}) == {"anvil": 1, "bar": 2, "cube": 3}
    assert assign_obj_ids([10, 2, "a"], {}) == {"2": 1, "10": 2, "a": 3}


@pytest.mark.parametrize("breakage", ["unknown id", "non-rigid pose", "missing mesh", "bad handeye line",
                                      "missing config key", "broken mesh"])
def test_malformed_input_leaves_the_previous_import_untouched(tmp_path: Path, breakage: str) -> None:
    dat_dir = Path(shutil.copytree(FIXTURE, tmp_path / "dat"))
    scene = _scene(tmp_path)
    import_threedat(dat_dir, scene.root)
    before = {p: p.read_bytes() for p in sorted(scene.annotation_dir.rglob("*")) if p.is_file()}
    poses = dat_dir / "annotations" / "scene1" / "poses.yaml"
    if breakage == "unknown id":
        poses.write_text(poses.read_text().replace("id: bar", "id: mug"))
    elif breakage == "non-rigid pose":
        poses.write_text(poses.read_text().replace("[0.0, -1.0, 0.0, 0.1, 1.0,", "[0.0, -2.0, 0.0, 0.1, 1.0,"))
    elif breakage == "missing mesh":
        (dat_dir / "objects" / "bar" / "bar.ply").unlink()
    elif breakage == "bad handeye line":
        p = dat_dir / "scenes" / "scene1" / "groundtruth_handeye.txt"
        p.write_text(p.read_text() + "3 0.1 0.2\n")
    elif breakage == "missing config key":
        cfg = dat_dir / "dataset.yaml"
        cfg.write_text(cfg.read_text().replace("camera_pose_file", "camera_poses_file"))
    elif breakage == "broken mesh":
        broken = "ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n"
        (dat_dir / "objects" / "bar" / "bar.ply").write_text(broken)
    with pytest.raises(BraveError) as info:
        import_threedat(dat_dir, scene.root)
    message = str(info.value)
    expected_file = {"unknown id": "poses.yaml", "non-rigid pose": "poses.yaml", "missing mesh": "object_library.yaml",
                     "bad handeye line": "groundtruth_handeye.txt:4", "missing config key": "dataset.yaml",
                     "broken mesh": "bar.ply"}[breakage]
    assert expected_file in message, message
    if breakage in ("unknown id", "non-rigid pose"):
        assert "entry" in message
    if breakage in ("missing mesh", "broken mesh"):
        assert "entry 2" in message and "'bar'" in message
    after = {p: p.read_bytes() for p in sorted(scene.annotation_dir.rglob("*")) if p.is_file()}
    assert after == before


def test_export_failure_keeps_the_previous_export(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    import_threedat(FIXTURE, scene.root)
    export_bop(scene.root)
    layout = BopLayout.of_scene(scene)
    before = {p: p.read_bytes() for p in sorted(scene.bop_dir.rglob("*")) if p.is_file()}
    (scene.capture_dir / "rgb" / "000001.png").unlink()  # the export fails at view 1
    with pytest.raises(BraveError, match="000001.png"):
        export_bop(scene.root, BopExportOptions(scene_id=3))
    after = {p: p.read_bytes() for p in sorted(scene.bop_dir.rglob("*")) if p.is_file()}
    assert after == before and BopLayout.of_scene(scene) == layout
    assert [p.name for p in scene.annotation_dir.iterdir() if p.name.startswith(".")] == []


def test_import_needs_a_captured_scene(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    scene.frames_path.write_text("")
    with pytest.raises(BraveError, match="no captured frames"):
        import_threedat(FIXTURE, scene.root)


def test_frames_matched_by_view_id_when_indices_differ(tmp_path: Path) -> None:
    dat_dir = Path(shutil.copytree(FIXTURE, tmp_path / "dat"))
    p = dat_dir / "scenes" / "scene1" / "groundtruth_handeye.txt"
    lines = p.read_text().splitlines()
    p.write_text("\n".join(f"view{i:04d} " + " ".join(line.replace(",", " ").split()[1:])
                           for i, line in enumerate(lines)) + "\n")
    scene = _scene(tmp_path)
    assert import_threedat(dat_dir, scene.root).matched_by == "view id"


def _cli(argv: list[str]) -> int:
    """``brave6d annotate ...``; drives brave6d.annotation.cli directly until the lead registers the command."""
    from brave6d.cli import COMMANDS

    if any(c.name == "annotate" for c in COMMANDS):
        return cli_main(["annotate", *argv])
    import argparse
    import sys

    from brave6d.annotation import cli

    parser = argparse.ArgumentParser()
    cli.configure(parser)
    try:
        return cli.run(parser.parse_args(argv))
    except BraveError as exc:
        print(f"brave6d annotate: error: {exc}", file=sys.stderr)
        return 2


def test_cli_import_and_export(tmp_path: Path, capsys) -> None:
    scene = _scene(tmp_path)
    assert _cli(["import-3ddat", str(FIXTURE), str(scene.root)]) == 0
    assert "imported 3 instances of 2 objects" in capsys.readouterr().out
    assert _cli(["export-bop", str(scene.root), "--scene-id", "7"]) == 0
    assert BopLayout.of_scene(scene).scene_id == 7
    assert (scene.bop_dir / "test" / "000007" / "scene_gt.json").is_file()
    bad = Path(shutil.copytree(FIXTURE, tmp_path / "bad"))
    (bad / "objects" / "cube" / "cube.ply").unlink()
    assert _cli(["import-3ddat", str(bad), str(scene.root)]) == 2
    err = capsys.readouterr().err
    assert "objects/object_library.yaml: entry 1 (id 'cube'): mesh not found" in err


def test_world_poses_are_metres_in_the_base_frame(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    import_threedat(FIXTURE, scene.root)
    annotation = load_annotation(scene)
    cube = annotation.object(2)
    assert cube.threedat_id == "cube" and cube.scale == 0.001 and cube.mesh.is_file()
    assert cube.mesh.is_relative_to(scene.annotation_dir.resolve())
    np.testing.assert_array_equal(annotation.instances[1].world_T_model[:3, 3], [0.05, -0.03, 0.006])
    # the camera pose the export used is base_T_tcp @ tcp_T_cam (calibrated), not base_T_tcp
    export_bop(scene.root)
    cams = read_scene_camera(BopLayout.of_scene(scene).scene_camera_path)
    world_T_cam = read_threedat(FIXTURE).camera_poses[2].world_T_cam
    np.testing.assert_allclose(cams[2].cam_T_world(), invert(world_T_cam), atol=1e-12)


# ----------------------------------------------------------------------------- folders 3D-DAT accepts
EYES = [(0.4, 0.0, 0.5), (0.0, 0.4, 0.5), (-0.4, 0.0, 0.5), (0.0, -0.4, 0.5), (0.3, 0.3, 0.4), (-0.3, 0.2, 0.6)]
BASE_T_DAT = make_transform(Rotation.from_euler("xyz", [4, -7, 100], degrees=True).as_matrix(), [0.2, -0.1, 0.05])
OBJ_POSE = make_transform(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [0.01, 0.02, 0.0])


def _six_views(tmp_path: Path):
    """A capture of six views (indices 0..5) whose poses are ``BASE_T_DAT @`` the 3D-DAT ones."""
    dat_poses = {i: look_at(eye, (0.0, 0.0, 0.0)) for i, eye in enumerate(EYES)}
    camera = read_threedat(FIXTURE).camera.pinhole()
    scene = make_synthetic_scene(tmp_path / "scene", camera, {i: BASE_T_DAT @ T for i, T in dat_poses.items()},
                                 tcp_T_cam=TCP_T_CAM)
    return scene, dat_poses, camera


def _subset_folder(tmp_path: Path, views: list[int], first_id: int | None, images: bool = True) -> Path:
    """A 3D-DAT folder of some captured views with their images, named as captured;
    ``first_id``: the lines renumbered from it, as a recorder numbers them (None: the capture indices)."""
    scene, dat_poses, camera = _six_views(tmp_path)
    cube = read_threedat(FIXTURE).library[0]
    cfg = write_threedat_folder(
        tmp_path / "dat", "001", [(cube, OBJ_POSE)], camera, {i: dat_poses[i] for i in views},
        images={i: (scene.rgb_dir / f"{i:06d}.png", None) for i in views} if images else None)
    if first_id is not None:
        gt = cfg.parent / "scenes" / "001" / "groundtruth_handeye.txt"
        lines = gt.read_text().splitlines()
        gt.write_text("".join(f"{first_id + n} {line.split(' ', 1)[1]}\n" for n, line in enumerate(lines)))
    return cfg


@pytest.mark.parametrize("first_id, disagreement", [(0, "line 1 with captured frame 0, the rgb images (as 3D-DAT) "
                                                        "with frame 1"),
                                                    (1, "line 2 with captured frame 2, the rgb images (as 3D-DAT) "
                                                        "with frame 3")])
def test_a_renumbered_subset_of_views_is_paired_by_its_images(tmp_path: Path, first_id: int, disagreement: str) -> None:
    cfg = _subset_folder(tmp_path, [1, 3, 4], first_id)
    scene = SceneDir(tmp_path / "scene")
    result = import_threedat(cfg.parent, scene.root)
    assert result.matched_by == "rgb files" and result.alignment.applied and result.alignment.rms_mm < 1e-6
    np.testing.assert_allclose(result.alignment.target_T_source, BASE_T_DAT, atol=1e-9)
    np.testing.assert_allclose(load_annotation(scene).instances[0].world_T_model, BASE_T_DAT @ OBJ_POSE, atol=1e-9)
    assert load_annotation(scene).source["paired_views"] == {str(first_id + n): i for n, i in enumerate([1, 3, 4])}
    # the ids, read as capture indices, are the cross-check: here they disagree, and the user is told
    assert (f"scenes/001/groundtruth_handeye.txt: the ids as captured frame indices pair {disagreement}; paired by "
            "the rgb images (as 3D-DAT)") in result.warnings


def test_images_and_ids_that_agree_cross_check(tmp_path: Path) -> None:
    cfg = _subset_folder(tmp_path, [0, 2, 5], None)
    result = import_threedat(cfg.parent, tmp_path / "scene")
    assert result.matched_by == "rgb files" and result.warnings == ()
    assert load_annotation(SceneDir(tmp_path / "scene")).source["cross_checked_by"] == ["frame index"]


def test_image_count_other_than_the_pose_count_is_reported(tmp_path: Path) -> None:
    cfg = _subset_folder(tmp_path, [0, 2, 5], None)
    rgb = cfg.parent / "scenes" / "001" / "rgb"
    shutil.copy(tmp_path / "scene" / "capture" / "rgb" / "000004.png", rgb / "000009.png")  # sorts last: unused
    result = import_threedat(cfg.parent, tmp_path / "scene")
    assert result.matched_by == "rgb files"
    assert result.warnings == ("scenes/001/rgb holds 4 images for 3 camera poses: the last 1 (sorted) have no "
                               "pose, as in 3D-DAT",)
    for name in ("000009.png", "000005.png"):
        (rgb / name).unlink()  # now too few images: 3D-DAT cannot open the scene, the ids still pair it
    result = import_threedat(cfg.parent, tmp_path / "scene")
    assert result.matched_by == "frame index"
    assert result.warnings == ("scenes/001/rgb holds 2 images for 3 camera poses (3D-DAT needs one per pose); "
                               "paired by the ids as captured frame indices",)


def test_a_wrong_pairing_is_named_when_nothing_aligns(tmp_path: Path) -> None:
    cfg = _subset_folder(tmp_path, [1, 3, 4], 0, images=False)
    scene = SceneDir(tmp_path / "scene")
    with pytest.raises(AlignmentError) as info:
        import_threedat(cfg.parent, scene.root)
    message = str(info.value)
    for fragment in ["scenes/001/groundtruth_handeye.txt", "paired by line id = captured frame index",
                     "worst frames", "scenes/001/rgb holds no .png/.jpg images", "A wrong pairing",
                     "3D-DAT pairs the lines with its sorted rgb images and ignores the ids"]:
        assert fragment in message, message
    assert not scene.annotation_dir.exists()


def test_images_that_do_not_align_fall_back_to_the_ids_with_a_warning(tmp_path: Path) -> None:
    """Images named from 1 as in the 3D-DAT README, ids = the capture indices 0..4."""
    cfg = _subset_folder(tmp_path, [0, 1, 2, 3, 4], None)
    rgb = cfg.parent / "scenes" / "001" / "rgb"
    for i in reversed(range(5)):
        (rgb / f"{i:06d}.png").rename(rgb / f"{i + 1:06d}.png")
    result = import_threedat(cfg.parent, tmp_path / "scene")
    assert result.matched_by == "frame index"
    assert any(w.startswith("scenes/001/groundtruth_handeye.txt: camera poses paired by line order with the "
                            "sorted images in scenes/001/rgb")
               and "do not align" in w for w in result.warnings), result.warnings


def test_an_empty_pose_list_imports_no_objects(tmp_path: Path) -> None:
    dat_dir = Path(shutil.copytree(FIXTURE, tmp_path / "dat"))
    (dat_dir / "annotations" / "scene1" / "poses.yaml").write_text("[]\n")
    scene = _scene(tmp_path)
    result = import_threedat(dat_dir, scene.root)
    assert (result.n_objects, result.n_instances) == (0, 0)
    assert "annotations/scene1/poses.yaml: no annotated objects (an empty list)" in result.warnings
    exported = export_bop(scene.root)
    layout = BopLayout.of_scene(scene)
    assert exported.instances == 0 and sorted(p.name for p in layout.models_dir.iterdir()) == ["models_info.json"]
    assert read_scene_gt(layout.scene_gt_path) == {0: [], 1: [], 2: []}


def test_library_objects_without_mesh_or_annotation_get_no_bop_model(tmp_path: Path) -> None:
    dat_dir = Path(shutil.copytree(FIXTURE, tmp_path / "dat"))
    (dat_dir / "objects" / "anvil").mkdir()
    (dat_dir / "objects" / "anvil" / "anvil.ply").write_text("ply\nbroken\n")  # never parsed: not annotated
    lib = dat_dir / "objects" / "object_library.yaml"
    lib.write_text(lib.read_text() + "- {id: idea, name: no mesh yet}\n- {id: anvil, mesh: anvil/anvil.ply}\n")
    scene = _scene(tmp_path)
    import_threedat(dat_dir, scene.root)
    annotation = load_annotation(scene)
    assert annotation.id_map == {"anvil": 1, "bar": 2, "cube": 3, "idea": 4}
    assert [o.threedat_id for o in annotation.objects] == ["bar", "cube"]
    export_bop(scene.root)
    layout = BopLayout.of_scene(scene)
    assert sorted(p.name for p in layout.models_dir.glob("*.ply")) == ["obj_000002.ply", "obj_000003.ply"]
    assert sorted(read_models_info(layout.models_info_path)) == [2, 3]


def test_bop_export_writes_models_of_annotated_objects_only(tmp_path: Path) -> None:
    """An objects.json that lists an object without instances (as imports before this rule wrote)."""
    scene = _scene(tmp_path)
    import_threedat(FIXTURE, scene.root)
    annotation = load_annotation(scene)
    cube = annotation.object(2)
    ghost = AnnotatedObject(obj_id=9, threedat_id="ghost", name="ghost", mesh=cube.mesh, scale=cube.scale)
    write_annotation(scene, dataclasses.replace(annotation, objects=(*annotation.objects, ghost)))
    assert [o.obj_id for o in load_annotation(scene).objects] == [1, 2, 9]
    export_bop(scene.root)
    layout = BopLayout.of_scene(scene)
    assert sorted(p.name for p in layout.models_dir.glob("*.ply")) == ["obj_000001.ply", "obj_000002.ply"]
    assert sorted(read_models_info(layout.models_info_path)) == [1, 2]
    assert json.loads(layout.info_path.read_text())["obj_ids"] == [1, 2]


def test_cli_says_which_pose_file_was_read(tmp_path: Path, capsys) -> None:
    dat_dir = Path(shutil.copytree(FIXTURE, tmp_path / "dat"))
    (dat_dir / "annotations" / "scene1" / "poses.yaml").rename(dat_dir / "annotations" / "scene1" / "pose.yaml")
    scene = _scene(tmp_path)
    assert _cli(["import-3ddat", str(dat_dir), str(scene.root)]) == 0
    assert ("warning: annotations/scene1/poses.yaml (object_pose_file in dataset.yaml) not found; "
            "read annotations/scene1/pose.yaml instead") in capsys.readouterr().out
    assert load_annotation(scene).source["files"]["poses"].endswith("pose.yaml")

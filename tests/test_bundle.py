"""Scene bundle: export, manifest verification (tamper -> refused), atomicity, BOP consistency."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from brave6d.core.errors import BraveError, DataError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import invert
from brave6d.serve.bundle import BundleError, export_bundle, load_bundle, verify_manifest
from brave6d.serve.toy_scene import CUBE_MM, make_synthetic_scene, world_T_cube


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SceneDir:
    return make_synthetic_scene(tmp_path_factory.mktemp("bundle_scene"), n_gaussians=5000, n_views=10)


@pytest.fixture()
def bundle_dir(scene: SceneDir, tmp_path: Path) -> Path:
    return export_bundle(scene.root, tmp_path / "bundle").root


def test_export_writes_a_self_contained_bundle(bundle_dir: Path, scene: SceneDir) -> None:
    names = {p.relative_to(bundle_dir).as_posix() for p in bundle_dir.rglob("*") if p.is_file()}
    assert {"manifest.json", "splat.ply", "scene.json", "objects.json", "holdout.json",
            "models/obj_000001.ply", "models/obj_000002.ply"} <= names
    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    assert set(manifest["files"]) == names - {"manifest.json"}
    for key in ("brave6d", "torch", "numpy", "python"):
        assert manifest["versions"][key]
    assert manifest["gaussians"] > 4000
    # the splat is copied byte for byte
    assert (bundle_dir / "splat.ply").read_bytes() == (scene.splat_dir / "point_cloud.ply").read_bytes()
    # no staging folders left behind
    assert not [p for p in bundle_dir.parent.iterdir() if p.name.startswith(".bundle")]


def test_loaded_bundle_content(bundle_dir: Path) -> None:
    b = load_bundle(bundle_dir)
    assert b.name == "synthetic_tabletop"
    assert (b.camera.width, b.camera.height) == (320, 240) and not b.camera.has_distortion
    assert [box.name for box in b.world.boxes] == ["table", "wall", "post"]
    assert b.world.workspace.min == (0.0, -0.6, 0.02)
    assert [(o.gt_id, o.obj_id, o.name) for o in b.objects] == [(0, 1, "cube_red"), (1, 2, "cube_blue")]
    np.testing.assert_array_equal(b.objects[1].world_T_obj, world_T_cube("cube_blue"))
    assert b.objects[0].diameter_mm == pytest.approx(CUBE_MM * np.sqrt(3), rel=1e-6)
    from brave6d.serve.bundle import load_model_m

    v, f = load_model_m(b.model_path(b.objects[0]))
    np.testing.assert_allclose(v.max(axis=0) - v.min(axis=0), [0.02, 0.02, 0.02], atol=1e-7)  # mm -> m
    assert len(f) == 12
    # holdout: the trainer's rule (10 % of the views), with the undistorted image
    assert len(b.holdout) == 1 and b.holdout[0].image is not None
    assert (bundle_dir / b.holdout[0].image).is_file()
    assert b.object_by("cube_blue").gt_id == 1 and b.object_by(0).name == "cube_red"
    with pytest.raises(KeyError):
        b.object_by("nope")


@pytest.mark.parametrize("victim", ["splat.ply", "objects.json", "scene.json", "models/obj_000002.ply"])
def test_tampered_bundle_is_refused(bundle_dir: Path, victim: str) -> None:
    path = bundle_dir / victim
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit
    path.write_bytes(bytes(data))
    with pytest.raises(BundleError, match="sha256") as info:
        load_bundle(bundle_dir)
    assert victim.split("/")[-1] in str(info.value)


def test_truncated_missing_and_escaping_files_are_refused(bundle_dir: Path) -> None:
    splat = bundle_dir / "splat.ply"
    splat.write_bytes(splat.read_bytes()[:-10])
    with pytest.raises(BundleError, match="size"):
        verify_manifest(bundle_dir)
    splat.unlink()
    with pytest.raises(BundleError, match="missing"):
        verify_manifest(bundle_dir)
    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    manifest["files"] = {"../outside.txt": {"sha256": "0" * 64, "bytes": 1}}
    (bundle_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match="outside"):
        verify_manifest(bundle_dir)
    manifest["format"] = "brave6d-bundle/99"
    (bundle_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match="unsupported bundle format"):
        verify_manifest(bundle_dir)
    (bundle_dir / "manifest.json").unlink()
    with pytest.raises(BundleError, match="no manifest"):
        verify_manifest(bundle_dir)


def test_server_refuses_a_tampered_bundle(bundle_dir: Path) -> None:
    from brave6d.serve.app import create_app

    objects = bundle_dir / "objects.json"
    data = json.loads(objects.read_text())
    data["objects"][0]["world_T_obj"][0][3] += 0.001  # move an object by 1 mm
    objects.write_text(json.dumps(data))
    with pytest.raises(BundleError, match="objects.json"):
        create_app(bundle_dir, device="cpu", warm_up=False)


def test_cli_serve_refuses_a_tampered_bundle(bundle_dir: Path) -> None:
    import argparse

    from brave6d.commands import serve as command

    (bundle_dir / "scene.json").write_text("{}")
    parser = argparse.ArgumentParser()
    command.configure(parser)
    with pytest.raises(BundleError, match="scene.json"):
        command.run(parser.parse_args([str(bundle_dir), "--port", "0"]))


def test_failed_export_keeps_the_previous_bundle(scene: SceneDir, tmp_path: Path) -> None:
    out = tmp_path / "bundle"
    export_bundle(scene.root, out)
    before = (out / "manifest.json").read_bytes()
    broken = tmp_path / "broken"
    shutil.copytree(scene.root, broken)
    (broken / "annotation" / "objects.json").unlink()
    with pytest.raises(BraveError, match="no imported annotation"):
        export_bundle(broken, out)
    assert (out / "manifest.json").read_bytes() == before
    verify_manifest(out)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".bundle")]


def test_export_cli(scene: SceneDir, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    from brave6d.serve import export_cli

    parser = argparse.ArgumentParser()
    export_cli.configure(parser)
    assert export_cli.run(parser.parse_args([str(scene.root), "--out", str(tmp_path / "b"), "--camera-radius",
                                             "0.03", "--no-holdout-images"])) == 0
    b = load_bundle(tmp_path / "b")
    assert b.world.camera_radius == 0.03 and b.holdout[0].image is None
    assert "brave6d serve" in capsys.readouterr().out


# ----------------------------------------------------------------------------- BOP consistency
@pytest.mark.slow
def test_ground_truth_equals_the_bop_export(tmp_path: Path) -> None:
    """For every exported BOP view, the server's cam_T_obj equals scene_gt's entry (same camera pose)."""
    pytest.importorskip("open3d")
    from fastapi.testclient import TestClient

    from brave6d.annotation.bop_format import (
        BopLayout,
        read_scene_camera,
        read_scene_gt,
        read_scene_gt_info,
    )
    from brave6d.core.calibration_io import camera_poses
    from brave6d.serve.app import create_app
    from brave6d.serve.toy_scene import make_synthetic_bundle

    bundle_dir = make_synthetic_bundle(tmp_path / "scene", n_gaussians=20_000, n_views=6, bop=True)
    scene = SceneDir(tmp_path / "scene")
    layout = BopLayout.of_scene(scene)
    gt = read_scene_gt(layout.scene_gt_path)
    info = read_scene_gt_info(layout.scene_gt_info_path)
    cams = read_scene_camera(layout.scene_camera_path)
    poses = {r.index: T for r, T in camera_poses(scene)}
    assert sorted(gt) == sorted(poses)
    b = load_bundle(bundle_dir)
    # the bundle took BOP's models (bit-identical files)
    assert (bundle_dir / "models/obj_000001.ply").read_bytes() == layout.model_path(1).read_bytes()

    with TestClient(create_app(b, device="cpu", mode="training"), base_url="http://localhost") as client:
        first = next(iter(sorted(poses)))
        eid = client.post("/episodes", json={"start": {"world_T_cam": poses[first].tolist()}, "depth": "none",
                                             "rgb": "none"}).json()["episode_id"]
        for im_id in sorted(poses):
            world_T_cam = poses[im_id]
            # the BOP camera pose is the same view
            np.testing.assert_allclose(cams[im_id].cam_T_world(), invert(world_T_cam), atol=1e-9)
            r = client.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": world_T_cam.tolist()},
                                                                "rgb": "none", "depth": "none"})
            assert r.status_code == 200 and r.json()["accepted"], r.text
            objects = r.json()["observation"]["objects"]
            assert [o["gt_id"] for o in objects] == list(range(len(gt[im_id])))
            for o, g, gi in zip(objects, gt[im_id], info[im_id]):
                assert o["obj_id"] == g.obj_id
                cam_T_obj = np.asarray(o["cam_T_obj"])
                np.testing.assert_allclose(cam_T_obj[:3, :3], g.cam_R_m2c, atol=1e-9)
                np.testing.assert_allclose(cam_T_obj[:3, 3] * 1000.0, g.cam_t_m2c, atol=1e-6)  # mm
                np.testing.assert_allclose(cam_T_obj, g.cam_T_model(), atol=1e-9)
                # same silhouette definition as BOP (pixel-centre rays, 3x canvas)
                assert o["px_count_all"] == gi.px_count_all
                assert abs(o["visib_fract"] - gi.visib_fract) < 0.1, (im_id, o["name"], o["visib_fract"], gi)


def test_holdout_views_follow_the_trainers_split(scene: SceneDir, tmp_path: Path) -> None:
    from brave6d.core.calibration_io import camera_poses
    from brave6d.serve.bundle import holdout_frames
    from brave6d.training import HeldOutView, write_holdout

    copy = SceneDir(tmp_path / "scene")
    shutil.copytree(scene.root, copy.root)
    # the split training recorded (the toy scene records the trainer's rule: 10 % per distance level)
    assert [r.index for r, _ in holdout_frames(copy)] == [5]
    # whatever training recorded is what the bundle holds; old guesses (metrics.json keys, COLMAP's
    # holdout.txt) are not read any more
    write_holdout(copy, [HeldOutView(1, "d0_v001"), HeldOutView(9, "d0_v009")])
    (copy.splat_dir / "metrics.json").write_text(json.dumps({"psnr": 30.0, "holdout": [{"index": 4}]}))
    copy.sparse_dir.mkdir(parents=True, exist_ok=True)
    (copy.sparse_dir / "holdout.txt").write_text("000003.png\n")
    assert [r.index for r, _ in holdout_frames(copy)] == [1, 9]
    b = load_bundle(export_bundle(copy.root, tmp_path / "b").root)
    assert [(h.index, h.view_id) for h in b.holdout] == [(1, "d0_v001"), (9, "d0_v009")]
    poses = {r.index: T for r, T in camera_poses(copy)}
    np.testing.assert_array_equal(b.holdout[1].world_T_cam, poses[9])


def test_a_scene_trained_before_the_split_file_still_exports(scene: SceneDir, tmp_path: Path) -> None:
    copy = SceneDir(tmp_path / "scene")
    shutil.copytree(scene.root, copy.root)
    copy.holdout_split_path.unlink()
    (copy.splat_dir / "metrics.json").write_text(json.dumps({"psnr": 30.0, "holdout": [{"index": 4}]}))
    b = load_bundle(export_bundle(copy.root, tmp_path / "b").root)
    assert [(h.index, h.view_id) for h in b.holdout] == [(5, "d0_v005")]  # the trainer's rule on the capture
    assert b.source.holdout_sha256 is None  # the manifest says the split was not recorded


def test_a_split_that_no_longer_matches_the_capture_is_refused(scene: SceneDir, tmp_path: Path) -> None:
    from brave6d.training import HeldOutView, write_holdout

    copy = SceneDir(tmp_path / "scene")
    shutil.copytree(scene.root, copy.root)
    write_holdout(copy, [HeldOutView(42, "d0_v042")])
    with pytest.raises(DataError, match=r"holdout\.json: held-out frame 42 \(d0_v042\) is not in the capture"):
        export_bundle(copy.root, tmp_path / "b")
    write_holdout(copy, [HeldOutView(5, "d9_v005")])
    with pytest.raises(DataError, match=r"held-out frame 5 \(d9_v005\) is view 'd0_v005' in the capture"):
        export_bundle(copy.root, tmp_path / "b")
    assert not (tmp_path / "b").exists()


# ----------------------------------------------------------------------------- where a bundle came from
def _strings(value: object) -> list[str]:
    if isinstance(value, dict):
        return [s for k, v in value.items() for s in (str(k), *_strings(v))]
    if isinstance(value, list):
        return [s for v in value for s in _strings(v)]
    return [value] if isinstance(value, str) else []


def test_the_manifest_names_its_source_without_the_builders_paths(scene: SceneDir, bundle_dir: Path) -> None:
    from brave6d.core.atomic import file_sha256

    text = (bundle_dir / "manifest.json").read_text()
    manifest = json.loads(text)
    for folder in {scene.root, scene.root.resolve(), bundle_dir.parent.resolve(), Path.home()}:
        assert str(folder) not in text, folder
    assert not [v for v in _strings(manifest) if v.startswith("/")]
    assert manifest["source"] == {
        "scene": "synthetic_tabletop", "splat": "splat/point_cloud.ply",
        "splat_sha256": manifest["files"]["splat.ply"]["sha256"], "metrics_sha256": None,
        "holdout_sha256": file_sha256(scene.holdout_split_path)}
    assert manifest["source"]["splat_sha256"] == file_sha256(scene.splat_ply_path)
    assert load_bundle(bundle_dir).source.splat == "splat/point_cloud.ply"


def test_a_bundle_made_before_still_loads_and_its_old_paths_are_ignored(bundle_dir: Path) -> None:
    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    manifest["source"] = {"scene": "/home/builder/scenes/tabletop", "splat": "/home/builder/scenes/tabletop/splat/x.ply"}
    (bundle_dir / "manifest.json").write_text(json.dumps(manifest))  # the manifest is not in its own file table
    b = load_bundle(bundle_dir)
    assert b.source.to_json() == {"scene": None, "splat": None, "splat_sha256": None, "metrics_sha256": None,
                                  "holdout_sha256": None}
    assert "/home/builder" not in json.dumps(b.summary())

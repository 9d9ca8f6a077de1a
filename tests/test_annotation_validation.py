"""The demo's 3D-DAT writer and the mask IoU check against simulated object-id buffers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from brave6d.annotation.bop import export_bop
from brave6d.annotation.bop_format import BopLayout, read_models_info
from brave6d.annotation.demo import write_demo_threedat
from brave6d.annotation.importer import import_threedat
from brave6d.annotation.toy_scene import make_synthetic_scene
from brave6d.annotation.threedat import read_threedat
from brave6d.annotation.validation import mask_iou_against_sim_truth
from brave6d.core.atomic import write_png
from brave6d.core.calibration_io import camera_poses
from brave6d.core.camera import PinholeCamera
from brave6d.core.transforms import look_at, make_transform, rpy_deg_to_matrix, transform_points

# A distorted raw camera (as captured); BOP works in its undistorted pinhole version.
RAW = PinholeCamera(96, 72, 90.0, 90.0, 47.5, 35.5, (0.08, -0.05, 0.0, 0.0, 0.0))
OBJECTS = [  # two boxes (mm) on a table-like plane, the second partly hidden behind the first in view 1
    {"name": "box_a", "category": "industry", "mesh": "assets/a.ply", "scale": 0.001,
     "pose": {"xyz": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 20.0]},
     "symmetry": {"discrete": [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]}},
    {"name": "box_b", "category": "household", "mesh": "assets/b.ply", "scale": 0.001,
     "pose": {"xyz": [0.06, 0.01, 0.0], "rpy_deg": [0.0, 0.0, -10.0]}},
]
VIEWS = {0: look_at([0.0, -0.05, 0.35], [0.03, 0.0, 0.0]),
         1: look_at([-0.25, 0.02, 0.12], [0.03, 0.0, 0.01]),
         2: look_at([0.2, 0.2, 0.2], [0.03, 0.0, 0.0])}


def _box(path: Path, size) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    box = trimesh.creation.box(extents=size)
    box.apply_translation([0, 0, size[2] / 2])
    box.export(path)


def _sim_ids(scene_root: Path, world_T_cam: np.ndarray) -> np.ndarray:
    """What the simulator writes: object ids through the DISTORTED camera (1 + spec index)."""
    rc = o3d.t.geometry.RaycastingScene()
    for obj in OBJECTS:
        m = trimesh.load(scene_root / obj["mesh"], process=False)
        T = make_transform(rpy_deg_to_matrix(obj["pose"]["rpy_deg"]), obj["pose"]["xyz"])
        rc.add_triangles(o3d.core.Tensor(transform_points(T, m.vertices * 0.001).astype(np.float32)),
                         o3d.core.Tensor(np.asarray(m.faces, dtype=np.uint32)))
    xy = RAW.normalized_rays(RAW.pixel_grid())
    d = np.c_[xy, np.ones(len(xy))] @ world_T_cam[:3, :3].T
    rays = np.c_[np.tile(world_T_cam[:3, 3], (len(d), 1)), d].astype(np.float32)
    out = rc.cast_rays(o3d.core.Tensor(rays))
    hit = np.isfinite(out["t_hit"].numpy())
    ids = np.where(hit, out["geometry_ids"].numpy().astype(np.int64) + 1, 0)
    return ids.reshape(RAW.height, RAW.width).astype(np.uint16)


@pytest.fixture(scope="module")
def sim_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim") / "scene"
    _box(root / "assets" / "a.ply", (30.0, 20.0, 25.0))
    _box(root / "assets" / "b.ply", (20.0, 20.0, 15.0))
    scene = make_synthetic_scene(root, RAW, VIEWS, objects=OBJECTS,
                                 tcp_T_cam=make_transform(rpy_deg_to_matrix([1, 2, 3]), [0.01, 0.02, 0.03]))
    for index, T in VIEWS.items():
        write_png(scene.capture.sim_truth_dir / "object_ids" / f"{index:06d}.png", _sim_ids(root, T))
    dat = write_demo_threedat(scene.root, root.parent / "threedat")
    import_threedat(dat.parent, scene.root)
    export_bop(scene.root)
    return scene, dat


def test_demo_writer_plays_the_annotator(sim_scene) -> None:
    scene, dat = sim_scene
    back = read_threedat(dat)
    assert back.scene_id == "synthetic" and [e.id for e in back.library] == ["box_a", "box_b"]
    assert [e.class_name for e in back.library] == ["industry", "household"]
    spec = scene.load_spec()
    for obj, pose in zip(spec.objects, back.objects):
        np.testing.assert_allclose(pose.world_T_model, obj.pose.matrix(), atol=1e-15)
    captured = {r.index: T for r, T in camera_poses(scene)}
    for p in back.camera_poses:
        np.testing.assert_allclose(p.world_T_cam, captured[int(p.frame_id)], atol=1e-12)
    assert back.camera.pinhole() == RAW.without_distortion()
    assert len(back.library[0].symmetries_discrete) == 1 and back.library[1].symmetries_discrete == ()
    info = read_models_info(BopLayout.of_scene(scene).models_info_path)
    assert info[1]["symmetries_discrete"] == [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]
    assert "symmetries_discrete" not in info[2]
    assert sorted(f.name for f in (dat.parent / "scenes" / "synthetic" / "rgb").iterdir()) == \
        ["000000.png", "000001.png", "000002.png"]


def test_masks_agree_with_the_simulated_id_buffers(sim_scene) -> None:
    scene, _ = sim_scene
    result = mask_iou_against_sim_truth(scene.root)
    assert result["count"] >= 5 and result["unmatched"] == []
    assert result["mean_iou"] >= 0.95, result["worst"]
    assert set(result["per_view"][0]) == {"box_a", "box_b"}


def test_iou_drops_when_the_buffer_is_wrong(sim_scene) -> None:
    scene, _ = sim_scene
    good = mask_iou_against_sim_truth(scene.root)["mean_iou"]
    path = scene.capture.sim_truth_dir / "object_ids" / "000000.png"
    original = path.read_bytes()
    try:
        ids = _sim_ids(scene.root, VIEWS[0])
        write_png(path, np.roll(ids, 4, axis=1))  # 4 px off
        shifted = mask_iou_against_sim_truth(scene.root)
        assert shifted["per_view"][0]["box_a"] < 0.9 < good
    finally:
        path.write_bytes(original)


def test_demo_stage_runs_on_a_captured_scene(sim_scene, tmp_path: Path) -> None:
    from brave6d.annotation.demo import stage_annotation
    from brave6d.core.run_context import RunContext

    scene, _ = sim_scene
    result = stage_annotation(RunContext(workdir=tmp_path, scene=scene, spec=scene.load_spec()))
    assert result.name == "annotation" and result.figures["views"] == 3 and result.figures["instances"] == 2
    assert (tmp_path / "threedat" / "dataset.yaml").is_file()

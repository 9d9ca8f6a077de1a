"""BOP results CSV (round trip, malformed lines) and BOP scene/model readers, end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.annotation import bop_cam_K, read_models_info, read_scene_camera
from brave6d.core.atomic import write_png
from brave6d.core.errors import DataError
from brave6d.evaluation.metrics.bop_results import (
    RESULTS_HEADER,
    check_times,
    format_results_csv,
    load_models,
    load_scene_gt_instances,
    load_split_gt_instances,
    read_bop_results,
    write_bop_results,
)
from brave6d.evaluation.metrics.recall import Estimate, evaluate_bop19
from brave6d.evaluation.metrics.depth_renderer import DepthRenderer

W, H = 320, 240
K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])


def _R(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


# ----------------------------------------------------------------------------- CSV
def test_csv_round_trip_is_exact(tmp_path):
    ests = [
        Estimate(1, 0, 5, 0.123456789012345, _R(1), [1.0 / 3.0, -250.5, 1234.56789], 0.5),
        Estimate(2, 17, 1, 1e-12, _R(2), [0.0, 0.0, 500.0], -1.0),
    ]
    path = write_bop_results(tmp_path / "m_brave-test.csv", ests)
    assert path.read_text().splitlines()[0] == RESULTS_HEADER
    back = read_bop_results(path)
    assert len(back) == 2
    for a, b in zip(ests, back):
        assert (a.scene_id, a.im_id, a.obj_id, a.score, a.time) == (b.scene_id, b.im_id, b.obj_id, b.score, b.time)
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)


@settings(max_examples=30)
@given(
    ids=st.tuples(st.integers(0, 10**6), st.integers(0, 10**6), st.integers(1, 10**4)),
    score=st.floats(-1e6, 1e6),
    t=st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3),
    seed=st.integers(0, 2**31),
)
def test_csv_round_trip_property(tmp_path_factory, ids, score, t, seed):
    e = Estimate(*ids, score, _R(seed), t, 1.5)
    path = tmp_path_factory.mktemp("csv") / "r.csv"
    write_bop_results(path, [e])
    (b,) = read_bop_results(path)
    assert (b.scene_id, b.im_id, b.obj_id, b.score) == (*ids, score)
    np.testing.assert_array_equal(b.R, e.R)
    np.testing.assert_array_equal(b.t, e.t)


def test_csv_without_header_and_with_blank_lines(tmp_path):
    text = format_results_csv([Estimate(1, 2, 3, 0.5, np.eye(3), [1, 2, 3], 0.1)])
    p = tmp_path / "r.csv"
    p.write_text(text.split("\n", 1)[1] + "\n\n")
    assert len(read_bop_results(p)) == 1
    p.write_text("scene_id,im_id,obj_id,score,R,t,time\r\n1,2,3,0.5,1 0 0 0 1 0 0 0 1,1 2 3,-1\r\n")
    (e,) = read_bop_results(p)
    assert e.time == -1.0 and e.t.tolist() == [1.0, 2.0, 3.0]


GOOD_R = "1 0 0 0 1 0 0 0 1"


@pytest.mark.parametrize(
    "line, message",
    [
        ("1,2,3,0.5,1 0 0 0 1 0 0 0 1,1 2 3", "7 comma-separated fields"),
        (f"1,2,3,0.5,{GOOD_R},1 2 3,0.1,extra", "7 comma-separated fields"),
        (f"a,2,3,0.5,{GOOD_R},1 2 3,0.1", "scene_id must be an integer"),
        (f"1,2,3,high,{GOOD_R},1 2 3,0.1", "score must be a number"),
        (f"1,2,3,nan,{GOOD_R},1 2 3,0.1", "score must be finite"),
        ("1,2,3,0.5,1 0 0 0 1 0 0 0,1 2 3,0.1", "R must have 9"),
        (f"1,2,3,0.5,{GOOD_R},1 2,0.1", "t must have 3"),
        (f"1,2,3,0.5,{GOOD_R},1 2 x,0.1", "t has a non-numeric"),
        (f"1,2,3,0.5,{GOOD_R},1 2 inf,0.1", "t contains NaN or inf"),
        ("1,2,3,0.5,2 0 0 0 1 0 0 0 1,1 2 3,0.1", "not a rotation"),
        ("1,2,3,0.5,-1 0 0 0 1 0 0 0 1,1 2 3,0.1", "not a rotation"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path, line, message):
    p = tmp_path / "bad.csv"
    p.write_text(f"{RESULTS_HEADER}\n1,2,3,0.5,{GOOD_R},1 2 3,0.1\n{line}\n")
    with pytest.raises(DataError, match=message) as err:
        read_bop_results(p)
    assert f"{p}:3:" in str(err.value)


def test_missing_results_file_and_unchecked_rotation(tmp_path):
    with pytest.raises(DataError, match="not found"):
        read_bop_results(tmp_path / "none.csv")
    p = tmp_path / "r.csv"
    p.write_text("1,2,3,0.5,2 0 0 0 1 0 0 0 1,1 2 3,0.1\n")
    assert read_bop_results(p, check_rotation=False)[0].R[0, 0] == 2.0


def test_write_refuses_nan(tmp_path):
    with pytest.raises(DataError, match="NaN"):
        write_bop_results(tmp_path / "r.csv", [Estimate(1, 2, 3, 0.5, np.eye(3), [np.nan, 0, 0])])


def test_check_times():
    e = [Estimate(1, 2, 3, 0.5, np.eye(3), [0, 0, 1], 0.2), Estimate(1, 2, 4, 0.5, np.eye(3), [0, 0, 1], 0.2)]
    check_times(e)
    with pytest.raises(DataError, match="run times"):
        check_times([*e, Estimate(1, 2, 5, 0.5, np.eye(3), [0, 0, 1], 0.3)])


# ----------------------------------------------------------------------------- BOP folders
@pytest.fixture(scope="module")
def bop_dataset(tmp_path_factory) -> dict:
    """A tiny BOP dataset: 2 objects (cube, hexagonal nut), 1 test scene with 2 images."""
    root = tmp_path_factory.mktemp("bop")
    models_dir = root / "models"
    models_dir.mkdir()
    cube = trimesh.creation.box(extents=(30.0, 30.0, 30.0))
    nut = trimesh.creation.cylinder(radius=12.0, height=10.0, sections=6)
    cube.export(models_dir / "obj_000001.ply")
    nut.export(models_dir / "obj_000002.ply")
    rz = [np.round(Rotation.from_euler("z", 60 * k, degrees=True).as_matrix(), 12) for k in range(1, 6)]
    sym = []
    for R in rz:
        T = np.eye(4)
        T[:3, :3] = R
        sym.append(T.reshape(-1).tolist())
    (models_dir / "models_info.json").write_text(json.dumps({
        "1": {"diameter": math.sqrt(3) * 30.0, "min_x": -15, "size_x": 30},
        "2": {"diameter": math.hypot(24.0, 10.0), "symmetries_discrete": sym},
    }))
    (root / "camera.json").write_text(json.dumps({"width": W, "height": H, "fx": 300.0, "fy": 300.0,
                                                   "cx": 160.0, "cy": 120.0, "depth_scale": 0.1}))
    scene = root / "test" / "000003"
    (scene / "depth").mkdir(parents=True)
    ren = DepthRenderer()
    ren.add_object(1, cube.vertices, cube.faces)
    ren.add_object(2, nut.vertices, nut.faces)
    poses = {
        0: [(1, _R(5), np.array([-40.0, 0.0, 400.0])), (2, _R(6), np.array([40.0, 10.0, 380.0]))],
        1: [(2, _R(7), np.array([0.0, 0.0, 350.0])), (1, _R(8), np.array([0.0, 60.0, 450.0]))],
    }
    scene_gt, scene_gt_info, scene_camera = {}, {}, {}
    for im_id, objs in poses.items():
        depth = np.full((H, W), np.inf)
        for obj_id, R, t in objs:
            d = ren.render(obj_id, R, t, K, W, H)
            depth = np.where((d > 0) & (d < depth), d, depth)
        depth = np.where(np.isfinite(depth), depth, 800.0)
        write_png(scene / "depth" / f"{im_id:06d}.png", np.round(depth / 0.1).astype(np.uint16))  # 0.1 mm units
        scene_gt[str(im_id)] = [{"cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": t.tolist(), "obj_id": o} for o, R, t in objs]
        scene_gt_info[str(im_id)] = [{"visib_fract": 0.9, "px_count_visib": 100} for _ in objs]
        scene_camera[str(im_id)] = {"cam_K": bop_cam_K(K).reshape(-1).tolist(), "depth_scale": 0.1}  # BOP's pixels
    scene_gt_info["1"][1]["visib_fract"] = 0.05  # the cube in image 1 is hardly visible: no target
    for name, data in (("scene_gt", scene_gt), ("scene_gt_info", scene_gt_info), ("scene_camera", scene_camera)):
        (scene / f"{name}.json").write_text(json.dumps(data))
    return {"root": root, "models": models_dir, "scene": scene, "poses": poses}


def test_load_scene_gt_instances(bop_dataset):
    gts = load_scene_gt_instances(bop_dataset["scene"])
    assert [(g.scene_id, g.im_id, g.obj_id) for g in gts] == [(3, 0, 1), (3, 0, 2), (3, 1, 2), (3, 1, 1)]
    assert gts[0].image_size == (W, H)
    np.testing.assert_allclose(gts[0].K, K)
    np.testing.assert_allclose(gts[1].t, bop_dataset["poses"][0][1][2])
    assert gts[3].visib_fract == 0.05
    depth = gts[0].depth()
    assert depth.shape == (H, W) and depth.max() == pytest.approx(800.0)  # uint16 * depth_scale -> mm
    assert load_split_gt_instances(bop_dataset["root"] / "test", with_depth=False)[0].depth is None


def test_load_models(bop_dataset):
    models = load_models(bop_dataset["models"])
    assert set(models) == {1, 2}
    assert models[1].faces is not None and len(models[1].points) == 8
    assert len(models[2].symmetries()) == 6
    assert read_models_info(bop_dataset["models"] / "models_info.json")[1]["size_x"] == 30


def test_bop_folder_end_to_end(bop_dataset, tmp_path):
    gts = load_scene_gt_instances(bop_dataset["scene"])
    models = load_models(bop_dataset["models"])
    ests = [Estimate(g.scene_id, g.im_id, g.obj_id, 1.0, g.R, g.t, 0.1) for g in gts]
    path = write_bop_results(tmp_path / "exact_brave-test.csv", ests)
    res = evaluate_bop19(gts, read_bop_results(path), models)
    assert res.n_targets == 3 and res.ar == 1.0
    # The nut of image 1 rotated by 180 deg about its axis (a declared symmetry) still scores 1;
    # estimating only the hardly visible cube of image 1 scores nothing for that image.
    g = gts[2]
    rz180 = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    sym_est = [e for e in ests if e.im_id == 0] + [Estimate(3, 1, 2, 1.0, g.R @ rz180, g.t, 0.1)]
    assert evaluate_bop19(gts, sym_est, models).ar == 1.0
    assert evaluate_bop19(gts, [e for e in ests if e.im_id == 0] + [ests[3]], models).ar == pytest.approx(2 / 3)
    assert evaluate_bop19(gts, [], models).ar == 0.0


def _rewrite(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def test_scene_reader_errors_name_the_file(bop_dataset, tmp_path):
    import shutil

    scene = tmp_path / "000001"
    shutil.copytree(bop_dataset["scene"], scene)
    (tmp_path / "camera.json").write_text("{}")  # no size here: it comes from the depth image
    assert load_scene_gt_instances(scene)[0].image_size == (W, H)

    _rewrite(scene / "scene_gt_info.json", lambda d: d["0"].pop())
    with pytest.raises(DataError, match=r"scene_gt_info\.json: image 0 has 1 entries"):
        load_scene_gt_instances(scene)
    _rewrite(scene / "scene_gt_info.json", lambda d: d["0"].append({"px_count_visib": 3}))
    with pytest.raises(DataError, match=r"scene_gt_info\.json: image 0 instance 1: missing 'visib_fract'"):
        load_scene_gt_instances(scene)
    _rewrite(scene / "scene_gt_info.json", lambda d: d["0"][1].update(visib_fract=1.0))
    _rewrite(scene / "scene_gt.json", lambda d: d["1"][0].update(cam_t_m2c=[1, 2]))
    with pytest.raises(DataError, match=r"scene_gt\.json: image 1 instance 0 cam_t_m2c"):
        load_scene_gt_instances(scene)
    (scene / "scene_camera.json").write_text("{not json")
    with pytest.raises(DataError, match=r"scene_camera\.json: not valid JSON"):
        load_scene_gt_instances(scene)
    with pytest.raises(DataError, match="scene id"):
        load_scene_gt_instances(tmp_path)
    with pytest.raises(DataError, match="not found"):
        load_scene_gt_instances(tmp_path / "missing")


def test_model_reader_errors(bop_dataset, tmp_path):
    import shutil

    models = tmp_path / "models"
    shutil.copytree(bop_dataset["models"], models)
    with pytest.raises(DataError, match="no entry for object 9"):
        load_models(models, obj_ids=[9])
    _rewrite(models / "models_info.json", lambda d: d["1"].update(diameter=0))
    with pytest.raises(DataError, match=r"models_info\.json: object 1: diameter must be positive"):
        load_models(models)
    _rewrite(models / "models_info.json", lambda d: d["1"].update(diameter=10, symmetries_discrete=[[1, 2]]))
    with pytest.raises(DataError, match=r"models_info\.json.*symmetries_discrete"):
        load_models(models)
    (models / "obj_000002.ply").unlink()
    with pytest.raises(DataError, match="obj_000002.ply: mesh file not found"):
        load_models(models, obj_ids=[2])


def test_renders_from_a_bop_cam_K_sample_the_pixels_bop_toolkit_does(tmp_path):
    """bop_toolkit's renderers (OpenGL; they make and score BOP's ground truth) put
    ``fx X / Z + cx`` of ``cam_K`` in window coordinates, where pixel (u, v) is sampled at
    (u + 0.5, v + 0.5). ``read_scene_camera`` converts cam_K to the project's K, so the depth
    renderer's OpenCV rays hit exactly bop_toolkit's pixels: same silhouette, edges at
    fractional positions. The old reader passed cam_K through (half a pixel off: this failed)."""
    cam_K = np.array([[300.0, 0.0, 160.2], [0.0, 310.0, 119.7], [0.0, 0.0, 1.0]])
    (tmp_path / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": cam_K.reshape(-1).tolist(),
                                                                   "depth_scale": 1.0}}))
    K = read_scene_camera(tmp_path / "scene_camera.json")[0].cam_K
    half = 23.3  # mm: a square facing the camera at 500 mm, edges off the pixel grid
    square = trimesh.Trimesh([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]],
                             [[0, 1, 2], [0, 2, 3]], process=False)
    t = np.array([7.1, -4.9, 500.0])
    depth = DepthRenderer()
    depth.add_object(1, square.vertices, square.faces)
    rendered = depth.render(1, np.eye(3), t, K, W, H) > 0
    corners = square.vertices + t
    uv = (corners @ cam_K.T)[:, :2] / corners[:, 2:]
    v, u = np.mgrid[0:H, 0:W] + 0.5  # OpenGL fragment centres
    gl = (u >= uv[:, 0].min()) & (u <= uv[:, 0].max()) & (v >= uv[:, 1].min()) & (v <= uv[:, 1].max())
    assert gl.sum() > 100
    np.testing.assert_array_equal(rendered, gl)

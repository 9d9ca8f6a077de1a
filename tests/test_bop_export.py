"""BOP export on a synthetic scene with a known occlusion configuration (pixel-exact expectations)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from brave6d.annotation.bop import export_bop
from brave6d.annotation.bop_format import BopLayout, read_models_info, read_scene_gt_info
from brave6d.annotation.importer import import_threedat
from brave6d.annotation.models import diameter, load_mesh, model_info_mm, write_ply
from brave6d.annotation.threedat import ContinuousSymmetry, LibraryEntry
from brave6d.annotation.threedat_writer import write_threedat_folder
from brave6d.annotation.toy_scene import make_synthetic_scene
from brave6d.annotation import bbox_xywh
from brave6d.core.atomic import read_png
from brave6d.core.camera import PinholeCamera
from brave6d.core.transforms import make_transform

REPO = Path(__file__).resolve().parent.parent
FIXTURE = Path(__file__).parent / "fixtures" / "threedat"

# 64 x 64 pinhole camera, f = 100 px; view 0 looks straight down from (0, 0, 1): u = 31.5 + 100 x / Z,
# v = 31.5 - 100 y / Z (camera y = world -y). Plate edges project onto half-integer pixel coordinates,
# so every pixel centre is far from an edge.
CAMERA = PinholeCamera(64, 64, 100.0, 100.0, 31.5, 31.5)
DOWN = make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 1.0])
UP = make_transform(np.eye(3), [0.0, 0.0, 1.0])  # view 1 looks away: nothing visible


def _box_ply(path: Path, lo, hi) -> Path:
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], dtype=float)
    f = np.array([(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6),
                  (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)])
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(v, f, process=False).export(path)
    return path


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[object, BopLayout]:
    """Plates A (z = 0, 20 x 20 px), B (z = 0.5, half over A), C (z = 0, truncated by the left image
    border) and a static occluder S (z = 0.5, over the lower half of C's visible part)."""
    tmp = tmp_path_factory.mktemp("bop")
    meshes = tmp / "meshes"
    a = LibraryEntry("plate_a", _box_ply(meshes / "a.ply", (-100, -100, -1), (100, 100, 0)), 0.001)
    b = LibraryEntry("plate_b", _box_ply(meshes / "b.ply", (0, -50, -1), (50, 50, 0)), 0.001,
                     symmetries_continuous=(ContinuousSymmetry((0.0, 0.0, 1.0), (0.025, 0.0, 0.0)),))
    c = LibraryEntry("strip_c", _box_ply(meshes / "c.ply", (-400, -50, -1), (-250, 50, 0)), 0.001)
    objects = [(a, np.eye(4)), (b, make_transform(np.eye(3), [0, 0, 0.5])), (c, np.eye(4))]
    dat = write_threedat_folder(tmp / "dat", "occlusion", objects, CAMERA, {0: DOWN, 1: UP})

    _box_ply(tmp / "scene" / "assets" / "s.ply", (-200, -50, 0), (-125, 0, 1))
    static = [{"name": "occluder", "mesh": "assets/s.ply", "scale": 0.001, "pose": {"xyz": [0.0, 0.0, 0.499]}}]

    def depth(index: int) -> np.ndarray:
        d = np.full((64, 64), 1000, dtype=np.uint16)
        d[:, :32] = 0  # no depth measured in the left half
        return d

    scene = make_synthetic_scene(tmp / "scene", CAMERA, {0: DOWN, 1: UP}, static_meshes=static, depth=depth)
    import_threedat(dat, scene.root)
    export_bop(scene.root)
    return scene, BopLayout.of_scene(scene)


def test_gt_info_of_the_occlusion_configuration(exported) -> None:
    _, layout = exported
    info = read_scene_gt_info(layout.scene_gt_info_path)
    a, b, c = info[0]
    assert (a.px_count_all, a.px_count_visib, a.px_count_valid) == (400, 200, 200)
    assert a.visib_fract == pytest.approx(0.5)
    assert a.bbox_obj == (22, 22, 19, 19) and a.bbox_visib == (22, 22, 9, 19)
    assert (b.px_count_all, b.px_count_visib, b.px_count_valid) == (200, 200, 200)
    assert b.visib_fract == 1.0 and b.bbox_obj == b.bbox_visib == (32, 22, 9, 19)
    # C: 15 x 10 px silhouette, 7 columns inside the image, 5 of its 10 rows there hidden by S
    assert (c.px_count_all, c.px_count_visib, c.px_count_valid) == (150, 35, 0)
    assert c.visib_fract == pytest.approx(35 / 150)
    assert c.bbox_obj == (-8, 27, 14, 9) and c.bbox_visib == (0, 27, 6, 4)


def test_nothing_visible_gives_bop_empty_values(exported) -> None:
    _, layout = exported
    for g in read_scene_gt_info(layout.scene_gt_info_path)[1]:
        assert (g.px_count_all, g.px_count_visib, g.px_count_valid, g.visib_fract) == (0, 0, 0, 0.0)
        assert g.bbox_obj == g.bbox_visib == (-1, -1, -1, -1)
    assert not read_png(layout.mask_path(1, 0)).any()


def test_masks_match_the_expected_rectangles(exported) -> None:
    _, layout = exported
    expect = np.zeros((64, 64), dtype=bool)
    expect[22:42, 22:42] = True
    mask = read_png(layout.mask_path(0, 0))
    assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
    np.testing.assert_array_equal(mask > 0, expect)
    expect_visib = expect.copy()
    expect_visib[:, 32:] = False
    np.testing.assert_array_equal(read_png(layout.mask_visib_path(0, 0)) > 0, expect_visib)
    c_mask = read_png(layout.mask_path(0, 2)) > 0
    c_visib = read_png(layout.mask_visib_path(0, 2)) > 0
    assert c_mask[27:37, 0:7].all() and c_mask.sum() == 70
    assert c_visib[27:32, 0:7].all() and c_visib.sum() == 35
    assert not (c_visib & ~c_mask).any()


def test_cam_K_makes_bop_toolkits_renderer_draw_our_masks(exported) -> None:
    """bop_toolkit's renderers (OpenGL) map ``fx X / Z + cx`` of ``cam_K`` to window coordinates
    and sample pixel (u, v) at (u + 0.5, v + 0.5): with the exported cam_K (the OpenCV K + 0.5 px)
    that coverage rule reproduces our mask of plate A exactly. The old export wrote the OpenCV K
    unchanged, which shifted bop_toolkit's silhouette one column and row (this test failed)."""
    _, layout = exported
    cam_K = np.array(json.loads(layout.scene_camera_path.read_text())["0"]["cam_K"]).reshape(3, 3)
    np.testing.assert_allclose(cam_K, CAMERA.K + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    # plate A's top face (world z = 0, +-0.1 m) seen from DOWN: camera frame x = X, y = -Y, z = 1 m
    corners = np.array([[x, -y, 1.0] for x in (-0.1, 0.1) for y in (-0.1, 0.1)])
    uv = (corners @ cam_K.T)[:, :2] / corners[:, 2:]
    v, u = np.mgrid[0:64, 0:64] + 0.5  # OpenGL fragment centres
    gl = (u >= uv[:, 0].min()) & (u <= uv[:, 0].max()) & (v >= uv[:, 1].min()) & (v <= uv[:, 1].max())
    np.testing.assert_array_equal(read_png(layout.mask_path(0, 0)) > 0, gl)


def test_layout_files_and_images(exported) -> None:
    scene, layout = exported
    assert layout.root == scene.bop_dir and layout.scene_dir == scene.bop_dir / "test" / "000001"
    cam = json.loads(layout.camera_path.read_text())
    # cx in BOP's pixel convention: CAMERA.cx + 0.5 (see test_cam_K_makes_bop_toolkits_renderer_draw_our_masks)
    assert (cam["width"], cam["height"], cam["fx"], cam["cx"], cam["depth_scale"]) == (64, 64, 100.0, 32.0, 1.0)
    assert read_png(layout.depth_path(0))[0, 40] == 1000
    assert layout.rgb_path(1).is_file()
    assert (layout.scene_dir / "mask_visib" / "000001_000002.png").is_file()
    info = read_models_info(layout.models_info_path)
    assert sorted(info) == [1, 2, 3]  # plate_a, plate_b, strip_c (sorted ids)
    assert info[2]["symmetries_continuous"] == [{"axis": [0.0, 0.0, 1.0], "offset": [25.0, 0.0, 0.0]}]
    assert info[1]["size_x"] == pytest.approx(200.0) and info[1]["min_z"] == pytest.approx(-1.0)


def test_models_in_millimetres_with_info(tmp_path: Path) -> None:
    cube = load_mesh(FIXTURE / "objects" / "cube" / "cube.ply").scaled(0.001)  # metres
    vertices_mm = cube.vertices * 1000.0
    write_ply(tmp_path / "obj_000001.ply", vertices_mm, cube.faces)
    back = trimesh.load(tmp_path / "obj_000001.ply", process=False)
    np.testing.assert_allclose(back.vertices, vertices_mm, atol=1e-5)
    np.testing.assert_array_equal(back.faces, cube.faces)
    rot90 = np.array([[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 2.0], [0, 0, 0, 1]])
    info = model_info_mm(vertices_mm, [rot90], [((0, 0, 1), (0, 0, 0))])
    assert info["diameter"] == pytest.approx(np.sqrt(300.0), abs=1e-9)
    assert (info["min_x"], info["min_y"], info["min_z"]) == (-5.0, -5.0, -5.0)
    assert (info["size_x"], info["size_y"], info["size_z"]) == (10.0, 10.0, 10.0)
    assert info["symmetries_discrete"] == [rot90.reshape(-1).tolist()]


def test_vertex_colours_are_kept(tmp_path: Path) -> None:
    nut = load_mesh(REPO / "data" / "demo" / "meshes" / "hex_nut.ply")
    assert nut.vertex_colors is not None
    write_ply(tmp_path / "nut.ply", nut.vertices, nut.faces, nut.vertex_colors)
    back = trimesh.load(tmp_path / "nut.ply", process=False)
    np.testing.assert_array_equal(np.asarray(back.visual.vertex_colors)[:, :3], nut.vertex_colors)


def test_diameter_on_hull_equals_brute_force() -> None:
    pts = np.random.default_rng(1).normal(size=(3000, 3)) * [3.0, 1.0, 0.5]
    brute = max(np.linalg.norm(pts[i] - pts, axis=1).max() for i in range(len(pts)))
    assert diameter(pts) == pytest.approx(brute, rel=1e-12)
    flat = np.c_[np.random.default_rng(2).normal(size=(50, 2)), np.zeros(50)]  # degenerate hull
    assert diameter(flat) == pytest.approx(max(np.linalg.norm(p - flat, axis=1).max() for p in flat))


def test_bbox_convention_matches_bop_toolkit() -> None:
    assert bbox_xywh(np.array([3, 7]), np.array([2, 2])) == (3, 2, 4, 0)
    assert bbox_xywh(np.array([], dtype=int), np.array([], dtype=int)) is None

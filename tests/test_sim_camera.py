"""SimCamera and SceneModel: analytic depth, object ids, textures, the ChArUco board, distortion."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import trimesh
from PIL import Image

from brave6d.core.board import chessboard_corners, make_charuco_board
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, DataError
from brave6d.core.spec import EffectsSpec, SceneSpec, load_scene_spec, parse_scene_spec
from brave6d.core.transforms import invert, look_at, make_transform, rotation_distance, rpy_deg_to_matrix
from brave6d.capture.protocols import Camera
from brave6d.capture.scene_model import BOARD_SEGMENT_ID, STATIC_ID_BASE, MeshPart, SceneModel, load_mesh_parts
from brave6d.capture.sim_camera import SimCamera, silhouette_mask

REPO = Path(__file__).resolve().parent.parent
SMALL = PinholeCamera.from_hfov(160, 100, 70.0)


def write_spec(tmp_path: Path, objects: list[dict[str, Any]], static: list[dict[str, Any]] = (),
               board: dict[str, Any] | None = None, effects: dict[str, Any] | None = None) -> SceneSpec:
    """A minimal scene spec file in ``tmp_path`` (meshes must already be there)."""
    data: dict[str, Any] = {
        "name": "tiny", "capture": {"target": [0, 0, 0]},
        "workspace": {"min": [-1, -1, -1], "max": [1, 1, 1]},
        "objects": [{"category": "industry", **o} for o in objects], "static_meshes": list(static),
        "simulation": {"true_tcp_T_camera": {}, "effects": effects or {}},
    }
    if board is not None:
        data["board"] = board
    path = tmp_path / "scene.yaml"
    path.write_text("# written by the test; parsed from the dict below\n")
    return parse_scene_spec(data, source=path)


def sim(model: SceneModel, camera: PinholeCamera = SMALL, pose: np.ndarray | None = None,
        effects: EffectsSpec | None = None, **kwargs: Any) -> SimCamera:
    T = np.eye(4) if pose is None else pose
    return SimCamera(model, camera, effects, lambda t: T, lambda: 0.0, **kwargs)


def ray_dirs(camera: PinholeCamera) -> np.ndarray:
    """Pinhole camera-frame ray directions (z = 1) of all pixel centres, computed independently."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    return np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], axis=-1)


# ----------------------------------------------------------------------------- depth
@pytest.mark.parametrize("rpy", [(0, 0, 0), (25, -15, 40), (-50, 10, 0)])
def test_plane_depth_matches_analytic(tmp_path: Path, rpy: tuple[float, float, float]) -> None:
    plane = trimesh.Trimesh([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    plane.export(tmp_path / "plane.ply")
    pose = {"xyz": [0.02, -0.03, 0.0], "rpy_deg": list(rpy)}
    spec = write_spec(tmp_path, [{"name": "plane", "mesh": "plane.ply", "pose": pose}])
    world_T_plane = spec.objects[0].pose.matrix()
    world_T_cam = look_at([0.15, 0.1, 0.45], [0.0, 0.0, 0.0])
    cam = sim(SceneModel.from_spec(spec), pose=world_T_cam, depth_range=(0.01, 10.0))
    result = cam.render(world_T_cam)

    cam_T_plane = invert(world_T_cam) @ world_T_plane
    n_c = cam_T_plane[:3, 2]
    d_c = float(n_c @ cam_T_plane[:3, 3])
    rays = ray_dirs(SMALL)
    z_true = d_c / (rays @ n_c)
    assert np.all(z_true > 0), "test set-up: the plane must fill the view"
    assert np.all(result.depth_m > 0)
    err = np.abs(result.depth_m.astype(np.float64) - z_true)
    assert err.max() < 1e-3
    assert err.max() < 1e-5  # float64 refinement: far below the 1 mm acceptance
    assert np.all(result.object_ids == 1)


def _ray_box(origin: np.ndarray, dirs: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Slab-method ray/box intersection (box frame); parameter of the entry point or inf."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - origin) / dirs
        t2 = (half - origin) / dirs
    t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)


def test_box_depth_and_ids_match_analytic(tmp_path: Path) -> None:
    size = np.array([0.08, 0.05, 0.03])
    trimesh.creation.box(size).export(tmp_path / "box.ply")
    trimesh.creation.box((2.0, 2.0, 0.02)).export(tmp_path / "table.ply")
    spec = write_spec(tmp_path, [{"name": "box", "mesh": "box.ply", "pose": {"xyz": [0.0, 0.0, 0.05], "rpy_deg": [10, -20, 35]}}],
                      static=[{"name": "table", "mesh": "table.ply", "pose": {"xyz": [0, 0, -0.01]}}])
    world_T_cam = look_at([0.12, -0.2, 0.3], [0.0, 0.0, 0.04])
    result = sim(SceneModel.from_spec(spec), pose=world_T_cam).render(world_T_cam)

    box_T_cam = invert(spec.objects[0].pose.matrix()) @ world_T_cam
    rays_cam = ray_dirs(SMALL).reshape(-1, 3)
    t_box = _ray_box(np.broadcast_to(box_T_cam[:3, 3], rays_cam.shape), rays_cam @ box_T_cam[:3, :3].T, size / 2)
    t_box = t_box.reshape(SMALL.height, SMALL.width)  # z = 1 directions: t is the z-depth
    on_box = np.isfinite(t_box)
    assert on_box.sum() > 500
    both = on_box & (result.object_ids == 1)
    assert np.abs(result.depth_m[both] - t_box[both]).max() < 1e-3
    mismatched = on_box != (result.object_ids == 1)
    assert mismatched.sum() <= 0.01 * on_box.sum()  # silhouette pixels only
    assert set(np.unique(result.segment_ids)) == {1, STATIC_ID_BASE}
    assert np.all(result.object_ids[~on_box & (result.segment_ids == STATIC_ID_BASE)] == 0)


def test_depth_range_and_background(tmp_path: Path) -> None:
    trimesh.creation.box((0.1, 0.1, 0.1)).export(tmp_path / "box.ply")
    spec = write_spec(tmp_path, [{"name": "near", "mesh": "box.ply", "pose": {"xyz": [0, 0, 0.3]}},
                                 {"name": "far", "mesh": "box.ply", "pose": {"xyz": [0.8, 0, 2.0]}}])
    cam = sim(SceneModel.from_spec(spec), depth_range=(0.1, 1.0), background_rgb=(10, 20, 30))
    result = cam.render(np.eye(4))
    far = result.object_ids == 2
    near = result.object_ids == 1
    assert far.any() and near.any()
    assert np.all(result.depth_m[far] == 0) and np.all(np.isfinite(result.z_m[far]))
    assert np.allclose(result.depth_m[near], 0.25, atol=1e-6)
    nothing = result.segment_ids == 0
    assert nothing.any()
    assert np.all(result.depth_m[nothing] == 0) and np.all(np.isinf(result.z_m[nothing]))
    assert np.all(result.rgb[nothing] == (10, 20, 30))


# ----------------------------------------------------------------------------- appearance
def test_checker_texture_maps_to_expected_pixels(tmp_path: Path) -> None:
    cells, cell_px, side = 4, 16, 0.2
    colours = np.array([[(40 + 60 * i, 20 + 70 * j, 200 - 40 * i) for j in range(cells)] for i in range(cells)], np.uint8)
    texture = np.repeat(np.repeat(colours, cell_px, axis=0), cell_px, axis=1)  # row i, column j
    quad = trimesh.Trimesh([[0, 0, 0], [side, 0, 0], [side, side, 0], [0, side, 0]], [[0, 1, 2], [0, 2, 3]],
                           visual=trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]],
                                                                 image=Image.fromarray(texture)), process=False)
    quad.export(tmp_path / "quad.obj")
    spec = write_spec(tmp_path, [{"name": "quad", "mesh": "quad.obj"}])
    # Head-on from +z, image up = world +y: the PNG should appear unmirrored and upright.
    world_T_cam = look_at([side / 2, side / 2, 0.3], [side / 2, side / 2, 0.0], up=(0, 1, 0))
    camera = PinholeCamera.from_hfov(200, 200, 50.0)
    cam = sim(SceneModel.from_spec(spec), camera, world_T_cam, light_direction=(0, 0, -1), ambient=0.2)
    rgb = cam.render(world_T_cam).rgb
    cam_T_world = invert(world_T_cam)
    for i in range(cells):
        for j in range(cells):
            # PNG row i is v from 1 - i/cells down; world y = side * (1 - (i + 0.5) / cells).
            centre = np.array([side * (j + 0.5) / cells, side * (1 - (i + 0.5) / cells), 0.0])
            uv = camera.project((cam_T_world[:3, :3] @ centre + cam_T_world[:3, 3])[None]).uv[0]
            u, v = int(round(uv[0])), int(round(uv[1]))
            patch = rgb[v - 3:v + 4, u - 3:u + 4].reshape(-1, 3).astype(int)
            assert np.abs(patch - colours[i, j]).max() <= 1, (i, j, patch[0], colours[i, j])


def test_several_textures_and_repeating_uvs() -> None:
    """Two quads with their own textures (odd sizes) share the atlas; UVs beyond 1 repeat."""
    rng = np.random.default_rng(5)
    cells_a = rng.integers(0, 256, (3, 5, 3), dtype=np.uint8)  # 3 rows x 5 columns of cells
    cells_b = rng.integers(0, 256, (2, 2, 3), dtype=np.uint8)
    tex_a = np.repeat(np.repeat(cells_a, 21, axis=0), 13, axis=1)  # 63 x 65 texels
    tex_b = np.repeat(np.repeat(cells_b, 40, axis=0), 40, axis=1)
    side = 0.1

    def quad(x0: float, name: str, tex: np.ndarray, repeat: float, segment: int) -> MeshPart:
        v = np.array([[x0, 0, 0], [x0 + side, 0, 0], [x0 + side, side, 0], [x0, side, 0]], float)
        uv = np.array([[0, 0], [repeat, 0], [repeat, repeat], [0, repeat]], float)
        return MeshPart(name, segment, v, np.array([[0, 1, 2], [0, 2, 3]]), uv=uv, texture=tex)

    model = SceneModel([quad(-0.11, "a", tex_a, 1.0, 1), quad(0.01, "b", tex_b, 2.0, 2)])
    assert len(model.textures) == 2
    world_T_cam = look_at([0.0, side / 2, 0.25], [0.0, side / 2, 0.0], up=(0, 1, 0))
    camera = PinholeCamera.from_hfov(400, 200, 60.0)
    rgb = sim(model, camera, world_T_cam, light_direction=(0, 0, -1)).render(world_T_cam).rgb
    cam_T_world = invert(world_T_cam)

    def colour_at(x: float, y: float) -> np.ndarray:
        uv = camera.project((cam_T_world[:3, :3] @ np.array([x, y, 0.0]) + cam_T_world[:3, 3])[None]).uv[0]
        return rgb[int(round(uv[1])), int(round(uv[0]))].astype(int)

    for i in range(3):
        for j in range(5):
            expected = cells_a[i, j].astype(int)
            assert np.abs(colour_at(-0.11 + side * (j + 0.5) / 5, side * (1 - (i + 0.5) / 3)) - expected).max() <= 1
    for i in range(4):  # 2x2 cells repeated twice in each direction
        for j in range(4):
            expected = cells_b[i % 2, j % 2].astype(int)
            assert np.abs(colour_at(0.01 + side * (j + 0.5) / 4, side * (1 - (i + 0.5) / 4)) - expected).max() <= 1


def test_vertex_colours_and_lambert(tmp_path: Path) -> None:
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    box.visual.vertex_colors = np.tile([180, 90, 30, 255], (len(box.vertices), 1))
    box.export(tmp_path / "box.ply")
    trimesh.creation.box((0.1, 0.1, 0.1)).export(tmp_path / "plain.stl")
    spec = write_spec(tmp_path, [{"name": "coloured", "mesh": "box.ply", "pose": {"xyz": [-0.06, 0, 0.4]}},
                                 {"name": "plain", "mesh": "plain.stl", "pose": {"xyz": [0.06, 0, 0.4]}}])
    # Light along the optical axis: the facing side is fully lit -> exactly the stored colour.
    lit = sim(SceneModel.from_spec(spec), light_direction=(0, 0, 1), ambient=0.3).render(np.eye(4))
    assert np.all(lit.rgb[lit.object_ids == 1] == (180, 90, 30))
    assert np.all(lit.rgb[lit.object_ids == 2] == (160, 160, 160))
    # Light from behind: ambient only, 0.3 of the linear radiance.
    dark = sim(SceneModel.from_spec(spec), light_direction=(0, 0, -1), ambient=0.3).render(np.eye(4))
    expected = 255 * (0.3 * (np.array([180, 90, 30]) / 255.0) ** 2.2) ** (1 / 2.2)  # ~ sRGB round trip
    assert np.all(np.abs(dark.rgb[dark.object_ids == 1].astype(float) - expected) < 8)


def test_mesh_loading_errors_name_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "broken.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    with pytest.raises(DataError, match="broken.ply"):
        load_mesh_parts(bad, 1.0, np.eye(4), 1, "broken")
    with pytest.raises(DataError, match="missing.obj"):
        load_mesh_parts(tmp_path / "missing.obj", 1.0, np.eye(4), 1, "missing")
    with pytest.raises(DataError, match="no triangles"):
        MeshPart("empty", 1, np.zeros((3, 3)), np.zeros((0, 3), int), source="empty.ply")


def test_scale_and_pose_are_applied(tmp_path: Path) -> None:
    trimesh.creation.box((100.0, 100.0, 100.0)).export(tmp_path / "mm_box.ply")  # millimetres
    spec = write_spec(tmp_path, [{"name": "box", "mesh": "mm_box.ply", "scale": 0.001,
                                  "pose": {"xyz": [0.0, 0.0, 0.5], "rpy_deg": [0, 0, 45]}}])
    model = SceneModel.from_spec(spec)
    result = sim(model).render(np.eye(4))
    centre = result.depth_m[SMALL.height // 2, SMALL.width // 2]
    assert centre == pytest.approx(0.45, abs=1e-6)


# ----------------------------------------------------------------------------- board
def _board_scene(tmp_path: Path) -> tuple[SceneSpec, SceneModel]:
    trimesh.creation.box((1.0, 1.0, 0.02)).export(tmp_path / "table.ply")
    board = {"squares_x": 7, "squares_y": 5, "square_length_m": 0.03, "marker_length_m": 0.022,
             "pose": {"xyz": [-0.1, 0.08, 0.0], "rpy_deg": [180, 0, 10]}}
    spec = write_spec(tmp_path, [], static=[{"name": "table", "mesh": "table.ply", "pose": {"xyz": [0, 0, -0.01]}}],
                      board=board)
    return spec, SceneModel.from_spec(spec, include_board=True)


def _detect(rgb: np.ndarray, spec: SceneSpec) -> tuple[np.ndarray, np.ndarray]:
    detector = cv2.aruco.CharucoDetector(make_charuco_board(spec.board))
    corners, ids, _, _ = detector.detectBoard(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    assert ids is not None and len(ids) >= 12, "board not detected"
    return corners.reshape(-1, 2).astype(np.float64), ids.ravel()


@pytest.mark.parametrize("eye", [(0.05, -0.15, 0.3), (-0.25, -0.05, 0.25)])
def test_rendered_board_is_detected_and_pnp_recovers_pose(tmp_path: Path, eye: tuple[float, float, float]) -> None:
    spec, model = _board_scene(tmp_path)
    world_T_board = spec.board.pose.matrix()
    centre = (world_T_board @ np.array([0.105, 0.075, 0.0, 1.0]))[:3]
    world_T_cam = look_at(eye, centre)
    camera = spec.camera.pinhole()
    rgb = sim(model, camera, world_T_cam).render(world_T_cam).rgb
    corners, ids = _detect(rgb, spec)
    ok, rvec, tvec = cv2.solvePnP(chessboard_corners(spec.board)[ids], corners, camera.K, None,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    assert ok
    cam_T_board_true = invert(world_T_cam) @ world_T_board
    estimate = make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
    assert np.linalg.norm(estimate[:3, 3] - cam_T_board_true[:3, 3]) < 1e-3
    assert math.degrees(rotation_distance(estimate, cam_T_board_true)) < 0.1


def test_board_wins_the_tie_with_a_coplanar_table(tmp_path: Path) -> None:
    spec, model = _board_scene(tmp_path)
    world_T_cam = look_at((0.0, -0.05, 0.4), (-0.0, 0.0, 0.0))
    result = sim(model, spec.camera.pinhole(), world_T_cam).render(world_T_cam)
    board_px = result.segment_ids == BOARD_SEGMENT_ID
    # The board covers a 0.24 x 0.18 m quad (with margin); a coplanar table must not punch holes into it.
    filled = cv2.morphologyEx(board_px.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)).astype(bool)
    assert board_px.sum() > 10000
    assert np.array_equal(filled & board_px, filled) or (filled & ~board_px).sum() < 5
    without = SceneModel.from_spec(spec, include_board=False)
    assert BOARD_SEGMENT_ID not in sim(without, spec.camera.pinhole(), world_T_cam).render(world_T_cam).segment_ids


def test_lens_distortion_puts_features_where_pinhole_camera_projects_them(tmp_path: Path) -> None:
    spec, model = _board_scene(tmp_path)
    dist = [0.12, -0.25, 0.002, -0.003, 0.05]
    effects = EffectsSpec.model_validate({"lens_distortion": {"dist": dist}})
    world_T_board = spec.board.pose.matrix()
    centre = (world_T_board @ np.array([0.105, 0.075, 0.0, 1.0]))[:3]
    # Look past the board so that it sits near the image corner, where distortion is strong.
    world_T_cam = look_at((0.0, -0.12, 0.3), centre + np.array([0.12, -0.06, 0.0]))
    cam = sim(model, spec.camera.pinhole(), world_T_cam, effects)
    assert cam.intrinsics.dist == tuple(dist)
    corners, ids = _detect(cam.render(world_T_cam).rgb, spec)
    cam_T_world = invert(world_T_cam)
    board_pts = chessboard_corners(spec.board)[ids]
    pts_cam = (cam_T_world @ world_T_board @ np.c_[board_pts, np.ones(len(ids))].T).T[:, :3]
    distorted = cam.intrinsics.project(pts_cam).uv
    pinhole = cam.intrinsics.without_distortion().project(pts_cam).uv
    assert np.abs(distorted - corners).max() < 0.5
    assert np.linalg.norm(pinhole - corners, axis=1).max() > 3.0  # the distortion is really there


# ----------------------------------------------------------------------------- protocol and options
def test_capture_returns_frame_with_ground_truth(tmp_path: Path) -> None:
    trimesh.creation.box((0.1, 0.1, 0.1)).export(tmp_path / "box.ply")
    spec = write_spec(tmp_path, [{"name": "box", "mesh": "box.ply", "pose": {"xyz": [0, 0, 0.3]}}])
    clock = iter([1.5, 2.5])
    poses = []

    def pose_at(t: float) -> np.ndarray:
        poses.append(t)
        return make_transform(rpy_deg_to_matrix((0, 0, 10 * t)), (0.0, 0.0, 0.0))

    cam = SimCamera.from_spec(spec, pose_at, lambda: next(clock))
    assert isinstance(cam, Camera)
    frame = cam.capture()
    assert frame.timestamp == 1.5 and poses == [1.5]
    assert frame.rgb.shape == (400, 640, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth_m is not None and frame.depth_m.dtype == np.float32
    assert frame.extras["object_ids"].dtype == np.uint16
    assert np.array_equal(frame.extras["world_T_cam_true"], pose_at(1.5))
    assert frame.extras["effects"] == [] and frame.extras["frame_index"] == 0
    assert cam.capture().extras["frame_index"] == 1
    cam.close()
    with pytest.raises(BraveError):
        cam.capture()


def test_supersampling_smooths_edges_and_keeps_depth(tmp_path: Path) -> None:
    trimesh.creation.box((0.1, 0.1, 0.1)).export(tmp_path / "box.ply")
    spec = write_spec(tmp_path, [{"name": "box", "mesh": "box.ply", "pose": {"xyz": [0, 0, 0.4], "rpy_deg": [0, 0, 30]}}])
    model = SceneModel.from_spec(spec)
    plain = sim(model, background_rgb=(0, 0, 0)).render(np.eye(4))
    for s in (2, 3):
        smooth = sim(model, background_rgb=(0, 0, 0), supersample=s).render(np.eye(4))
        assert np.array_equal(smooth.depth_m, plain.depth_m)
        assert np.array_equal(smooth.object_ids, plain.object_ids)
        grey_plain = np.unique(plain.rgb[..., 0]).size
        assert np.unique(smooth.rgb[..., 0]).size > grey_plain  # intermediate edge values appear
    with pytest.raises(BraveError):
        sim(model, supersample=0)


@pytest.mark.parametrize("dist", [(), (0.1, -0.05, 0.001, 0.0, 0.0)])
def test_edge_supersampling_matches_full_supersampling_on_silhouettes(tmp_path: Path, dist: tuple[float, ...]) -> None:
    trimesh.creation.box((0.1, 0.1, 0.1)).export(tmp_path / "box.ply")
    trimesh.creation.icosphere(2, radius=0.04).export(tmp_path / "ball.ply")
    spec = write_spec(tmp_path, [{"name": "box", "mesh": "box.ply", "pose": {"xyz": [-0.03, 0, 0.4], "rpy_deg": [20, 0, 30]}},
                                 {"name": "ball", "mesh": "ball.ply", "pose": {"xyz": [0.06, 0.02, 0.3]}}])
    model = SceneModel.from_spec(spec)
    effects = EffectsSpec.model_validate({"lens_distortion": {"dist": list(dist)}}) if dist else None
    plain = sim(model, effects=effects).render(np.eye(4))
    edges = sim(model, effects=effects, edge_supersample=3).render(np.eye(4))
    full = sim(model, effects=effects, supersample=3).render(np.eye(4))
    changed = np.any(edges.rgb != plain.rgb, axis=2)
    mask = edges.segment_ids != plain.segment_ids
    assert not mask.any() and np.array_equal(edges.depth_m, plain.depth_m)
    silhouette = silhouette_mask(plain.segment_ids, plain.z_m)
    assert changed.any() and not (changed & ~silhouette).any()  # only silhouette pixels are resampled
    assert 0 < silhouette.mean() < 0.1
    diff = np.abs(edges.rgb.astype(int) - full.rgb.astype(int))[silhouette]
    assert diff.max() <= 1  # same sub-pixel pattern as full 3x3 supersampling


def test_render_other_camera_model(tmp_path: Path) -> None:
    trimesh.creation.box((2.0, 2.0, 0.01)).export(tmp_path / "wall.ply")
    spec = write_spec(tmp_path, [{"name": "wall", "mesh": "wall.ply", "pose": {"xyz": [0, 0, 1.0]}}])
    cam = sim(SceneModel.from_spec(spec))
    other = PinholeCamera.from_hfov(32, 20, 40.0)
    result = cam.render(np.eye(4), camera=other)
    assert result.depth_m.shape == (20, 32)
    assert np.allclose(result.depth_m, 0.995, atol=1e-6)


@pytest.mark.slow
@pytest.mark.skipif(not (REPO / "data" / "demo" / "scene.yaml").is_file(), reason="demo scene not present")
def test_demo_scene_renders() -> None:
    spec = load_scene_spec(REPO / "data" / "demo" / "scene.yaml")
    model = SceneModel.from_spec(spec, include_board=True)
    target = np.asarray(spec.capture.target, dtype=float)
    world_T_cam = look_at(target + np.array([0.1, -0.25, 0.3]), target)
    cam = SimCamera.from_spec(spec, lambda t: world_T_cam, lambda: 0.0, scene_model=model)
    result = cam.render(world_T_cam)
    assert (result.depth_m > 0).mean() > 0.5
    assert len(np.unique(result.rgb.reshape(-1, 3), axis=0)) > 50

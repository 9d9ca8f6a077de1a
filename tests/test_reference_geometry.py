"""The reference geometry (brave6d.serve.reference): built from captured depth at calibrated poses,
shipped in the bundle with its checksum, and what scores are measured against, so that two
different splats of one scene give the same visible fractions and the same VSD test depth."""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brave6d.core.atomic import depth_m_to_mm_u16, file_sha256, read_json, read_png
from brave6d.core.camera import PinholeCamera
from brave6d.core.transforms import look_at
from brave6d.evaluation.metrics.episodes import models_from_bundle, read_episode, score_episodes
from brave6d.serve import (
    REFERENCE,
    Bundle,
    BundleError,
    ReferenceGeometry,
    ReferenceGeometryError,
    ReferenceSettings,
    SceneServer,
    ServerLimits,
    SplatRenderer,
    create_app,
    load_bundle,
    make_synthetic_bundle,
    read_episode_log,
    read_reference,
)
from brave6d.serve.reference import canonical_order, check_mesh, integrate_depth
from brave6d.serve.toy_scene import CUBE_POSES, TARGET, ring_poses, true_mesh
from brave6d.training import read_ply, write_ply

#: above the red cube, looking down at it
ABOVE_RED = look_at((0.40, -0.05, 0.22), (0.45, -0.03, 0.01))
VIEWS = [ABOVE_RED, look_at((0.52, 0.10, 0.25), (0.46, 0.0, 0.01)), look_at((0.30, 0.0, 0.30), (0.46, 0.0, 0.01))]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    """The synthetic scene with true captured depth, so its bundle has a reference geometry."""
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("ref_scene"), n_gaussians=8000, depth=True))


@pytest.fixture(scope="module")
def perturbed_splat(bundle: Bundle, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Another "training" of the scene: every Gaussian moved by a few mm, and an opaque floater
    between ABOVE_RED's camera and the red cube (as a badly trained splat may have)."""
    splat = read_ply(bundle.splat_path)
    rng = np.random.default_rng(3)
    eye, cube = ABOVE_RED[:3, 3], np.asarray(CUBE_POSES["cube_red"][0]) + [0.0, 0.0, 0.01]
    centre = eye + 0.5 * (cube - eye)
    n = 400
    floater = centre + rng.normal(0.0, 0.004, (n, 3))
    moved = dataclasses.replace(
        splat,
        means=np.concatenate([splat.means + rng.normal(0.0, 0.003, splat.means.shape), floater]).astype(np.float32),
        sh0=np.concatenate([splat.sh0, np.zeros((n, 1, 3))]).astype(np.float32),
        shN=np.concatenate([splat.shN, np.zeros((n, *splat.shN.shape[1:]))]).astype(np.float32),
        opacities=np.concatenate([splat.opacities, np.full(n, 6.0)]).astype(np.float32),
        scales=np.concatenate([splat.scales, np.full((n, 3), math.log(0.004))]).astype(np.float32),
        quats=np.concatenate([splat.quats, np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))]).astype(np.float32))
    return write_ply(tmp_path_factory.mktemp("perturbed") / "splat.ply", moved)


def without_reference(bundle: Bundle) -> Bundle:
    """The same bundle as an older export without the reference would load."""
    files = {k: v for k, v in bundle.manifest["files"].items() if k != REFERENCE}
    return dataclasses.replace(bundle, manifest={**bundle.manifest, "files": files})


def errors(measured: np.ndarray, truth: np.ndarray, world_T_cam: np.ndarray,
           camera: PinholeCamera) -> tuple[float, float, float]:
    """Median |error| (mm) and share within 5 mm on the truth's pixels with reference depth, and
    the share of the truth's pixels without reference depth; on the pixels whose true surface lies
    within 12 cm of the capture's target (what every captured frame saw)."""
    points = camera.unproject(camera.pixel_grid(), truth.reshape(-1)) @ world_T_cam[:3, :3].T + world_T_cam[:3, 3]
    near = (np.linalg.norm(points - np.asarray(TARGET), axis=1) < 0.12).reshape(truth.shape)
    has = (truth > 0) & near
    both = has & (measured > 0)
    e = np.abs(measured - truth)[both] * 1000.0
    return float(np.median(e)), float(np.mean(e <= 5.0)), float(np.mean(measured[has] == 0))


# ----------------------------------------------------------------------------- build
def test_reference_matches_the_true_geometry_of_a_synthetic_scene(bundle: Bundle) -> None:
    """Integrated from 10 true depth frames on a ring at 30 cm, seen from other poses (closer,
    farther, other elevations): the reference's depth is within 1 mm (median) of the truth."""
    assert bundle.reference_path is not None
    ref, truth = read_reference(bundle.reference_path), ReferenceGeometry(*true_mesh())
    poses = ring_poses(3, 0.22, 65.0) + ring_poses(3, 0.40, 40.0)
    for T in poses:
        median_mm, within_5, missing = errors(ref.depth(T, bundle.camera), truth.depth(T, bundle.camera), T,
                                               bundle.camera)
        assert median_mm <= 1.0 and within_5 >= 0.97 and missing <= 0.02, (median_mm, within_5, missing)
    record = read_json(bundle.root / "scene.json")["reference"]
    assert record["file"] == REFERENCE and record["units"] == "m"
    assert record["frames_used"] == 10 and record["frames_skipped"] == 0
    assert record["settings"] == dataclasses.asdict(ReferenceSettings())


def test_manifest_lists_the_reference_with_its_checksum(bundle: Bundle, tmp_path: Path) -> None:
    entry = bundle.manifest["files"][REFERENCE]
    path = bundle.root / REFERENCE
    assert entry == {"sha256": file_sha256(path), "bytes": path.stat().st_size}
    copy = Path(shutil.copytree(bundle.root, tmp_path / "bundle"))
    data = bytearray((copy / REFERENCE).read_bytes())
    data[-5] ^= 0xFF
    (copy / REFERENCE).write_bytes(bytes(data))
    with pytest.raises(BundleError, match=r"reference\.ply: sha256 .* does not match the manifest"):
        load_bundle(copy)


# ----------------------------------------------------------------------------- the key property
def test_scores_do_not_move_with_the_splat(bundle: Bundle, perturbed_splat: Path,
                                           caplog: pytest.LogCaptureFixture) -> None:
    """Two different splats of one scene: with the reference, identical visible fractions and test
    depths; without it (an older bundle), both move with the splat."""
    cam = bundle.camera.scaled(160, 100)

    def observe(b: Bundle, splat: Path | None) -> list:  # type: ignore[type-arg]
        renderer = SplatRenderer(splat, "cpu") if splat is not None else None
        server = SceneServer(b, device="cpu", renderer=renderer)
        return [server.observe(T, cam, 0) for T in VIEWS]

    a, b = observe(bundle, None), observe(bundle, perturbed_splat)
    assert any(not np.array_equal(x.depth, y.depth) for x, y in zip(a, b))  # the splats do differ
    for x, y in zip(a, b):
        assert x.geometry == y.geometry == "reference"
        assert [o.visib_fract for o in x.objects] == [o.visib_fract for o in y.objects]
        np.testing.assert_array_equal(x.test_depth, y.test_depth)
        assert np.all(np.isfinite(x.test_depth)) and np.count_nonzero(x.test_depth) > 0.9 * x.test_depth.size
    old = without_reference(bundle)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="brave6d.serve.reference"):
        a, b = observe(old, None), observe(old, perturbed_splat)
    assert len([r for r in caplog.records if "has no reference geometry" in r.getMessage()]) == 2  # one per server
    assert a[0].geometry == "splat"
    assert not np.array_equal(a[0].test_depth, b[0].test_depth)
    assert a[0].target().visib_fract > b[0].target().visib_fract  # the floater hides the cube from the splat


def test_a_submitted_episode_is_scored_on_the_reference(bundle: Bundle, perturbed_splat: Path,
                                                        tmp_path: Path) -> None:
    """The logged final depth is the reference at the final pose (not the splat the agent saw), the
    log and the score say so, and the exact pose scores 1."""
    server = SceneServer(bundle, device="cpu", renderer=SplatRenderer(perturbed_splat, "cpu"))
    app = create_app(bundle, scene=server, log_dir=tmp_path, limits=ServerLimits(max_episodes=10), warm_up=False,
                     mode="training")  # the oracle reads the truth
    with TestClient(app, base_url="http://localhost") as client:
        r = client.post("/episodes", json={"start": {"world_T_cam": ABOVE_RED.tolist()}, "target": "cube_red",
                                           "width": 160, "height": 100, "rgb": "none", "agent": "oracle"})
        assert r.status_code == 201, r.text
        obs = r.json()
        gt = np.asarray(next(o for o in obs["observation"]["objects"] if o["is_target"])["cam_T_obj"])
        eid = obs["episode_id"]
        r = client.post(f"/episodes/{eid}/estimates", json={"estimates": [
            {"obj_id": 1, "R": gt[:3, :3].reshape(-1).tolist(), "t_m": gt[:3, 3].tolist()}]})
        assert r.status_code == 200, r.text
    sub = next(r for r in read_episode_log(tmp_path / f"{eid}.jsonl") if r.event == "submit")
    assert sub.final_view.depth_source == "reference"
    logged = read_png(tmp_path / f"{eid}_final_depth.png", expect="depth")
    cam = bundle.camera.scaled(160, 100)
    np.testing.assert_array_equal(logged, depth_m_to_mm_u16(read_reference(bundle.reference_path).depth(ABOVE_RED, cam)))
    splat_depth = server.renderer.render(ABOVE_RED, cam, near=bundle.render.near, far=bundle.render.far).depth
    assert not np.array_equal(logged, depth_m_to_mm_u16(splat_depth))
    ep = read_episode(tmp_path / f"{eid}.jsonl")
    board = score_episodes([ep], models_from_bundle(bundle))
    assert ep.test_depth == "reference" and board.to_json()["test_depth"] == ["reference"]
    assert board.agents[0].ar == 1.0


# ----------------------------------------------------------------------------- hard cases
CAM = PinholeCamera.from_hfov(48, 36, 60.0)
COARSE = ReferenceSettings(voxel_m=0.01, trunc_m=0.04, depth_min_m=0.05, depth_max_m=1.0, min_weight=1.0)


def plane_frames(heights: list[float]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cameras looking straight down at the plane z = 0 from ``heights``: the true depth is the height."""
    out = []
    for k, h in enumerate(heights):
        T = look_at((0.01 * k, 0.005 * k, h), (0.01 * k, 0.005 * k, 0.0), up=(0.0, 1.0, 0.0))
        out.append((np.full((CAM.height, CAM.width), h, dtype=np.float32), T))
    return out


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(heights=st.lists(st.floats(0.2, 0.6), min_size=1, max_size=4),
       hole_share=st.floats(0.0, 0.95), junk=st.sampled_from([0.0, np.nan, np.inf, -1.0, 50.0, 1e30]),
       invalid=st.lists(st.booleans(), min_size=4, max_size=4), seed=st.integers(0, 2**16))
def test_holes_junk_and_invalid_frames(heights: list[float], hole_share: float, junk: float, invalid: list[bool],
                                       seed: int) -> None:
    """Depth with holes (filled with 0, NaN, inf, negative or far-out-of-range values), and frames
    with no valid depth at all (skipped and counted): the mesh is finite and on the plane, or,
    when nothing is left to integrate, a clear error names the scene."""
    rng = np.random.default_rng(seed)
    frames = []
    for (depth, T), bad in zip(plane_frames(heights), invalid):
        holes = rng.random(depth.shape) < (1.0 if bad else hole_share)
        frames.append((np.where(holes, np.float32(junk), depth), T))
    n_bad = sum(1 for (depth, _), bad in zip(frames, invalid) if bad)
    try:
        mesh = integrate_depth(iter(frames), CAM, COARSE, "scene toy")
    except ReferenceGeometryError as exc:
        assert "scene toy" in str(exc)
        return
    assert mesh.stats.frames_skipped == n_bad and mesh.stats.frames_used == len(frames) - n_bad
    assert np.all(np.isfinite(mesh.vertices)) and len(mesh.faces) > 0
    assert np.median(np.abs(mesh.vertices[:, 2])) <= COARSE.voxel_m


def test_all_frames_invalid_is_an_error_naming_the_scene() -> None:
    frames = [(np.where(True, np.float32(np.nan), d), T) for d, T in plane_frames([0.3, 0.4])]
    frames.append((None, np.eye(4)))  # a frame without a depth file
    with pytest.raises(ReferenceGeometryError, match=r"scene demo: no depth frame has valid depth .*3 frame\(s\) skipped"):
        integrate_depth(iter(frames), CAM, COARSE, "scene demo")


def test_depth_beyond_the_range_is_truncated() -> None:
    """A far wall (5 m) behind the plane is cut by depth_max: only the plane is in the mesh."""
    frames = plane_frames([0.3, 0.35, 0.4])
    for depth, _ in frames:
        depth[:, : CAM.width // 2] = 5.0
    mesh = integrate_depth(iter(frames), CAM, COARSE, "scene far")
    assert float(np.max(np.abs(mesh.vertices[:, 2]))) <= 2 * COARSE.voxel_m


@settings(max_examples=30, deadline=None)
@given(x=st.floats(-0.09, 0.09), y=st.floats(-0.09, 0.09), z=st.floats(-0.09, 0.09),
       yaw=st.floats(-math.pi, math.pi), pitch=st.floats(-1.5, 1.5))
def test_camera_inside_the_scene_sees_finite_depth(x: float, y: float, z: float, yaw: float, pitch: float) -> None:
    """Inside a closed box (20 cm), every ray hits a wall within the box's diagonal; no NaN/inf."""
    v, f = true_mesh()
    box_v = (v[:8] - v[:8].mean(0)) / (v[:8].max(0) - v[:8].min(0)) * 0.2  # the table box, rescaled to 20 cm
    ref = ReferenceGeometry(box_v, f[:12])
    direction = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    eye = np.array([x, y, z])
    T = look_at(eye, eye + direction, up=(0.0, 0.0, 1.0) if abs(direction[2]) < 0.99 else (1.0, 0.0, 0.0))
    depth = ref.depth(T, CAM)
    assert np.all(np.isfinite(depth)) and np.all(depth > 0) and float(depth.max()) <= 0.2 * math.sqrt(3) * 2


def test_empty_or_degenerate_meshes_are_clear_errors(tmp_path: Path) -> None:
    from brave6d.annotation import write_ply_mesh

    with pytest.raises(ReferenceGeometryError, match="has no triangles"):
        check_mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), "scene x")
    flat = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    with pytest.raises(ReferenceGeometryError, match="degenerate"):
        check_mesh(flat, np.array([[0, 1, 2]]), "scene x")
    with pytest.raises(ReferenceGeometryError, match="non-finite"):
        check_mesh(np.array([[0.0, 0.0, np.nan], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.array([[0, 1, 2]]), "scene x")
    path = write_ply_mesh(tmp_path / "reference.ply", flat, np.array([[0, 1, 2]]))
    with pytest.raises(ReferenceGeometryError, match=r"reference\.ply: the reference geometry is degenerate"):
        read_reference(path)
    with pytest.raises(ReferenceGeometryError, match=r"missing\.ply: cannot read"):
        read_reference(tmp_path / "missing.ply")


def test_settings_are_checked() -> None:
    with pytest.raises(ReferenceGeometryError, match="voxel_m must be a finite number > 0"):
        ReferenceSettings(voxel_m=float("nan"))
    with pytest.raises(ReferenceGeometryError, match="depth_min_m .* must be below depth_max_m"):
        ReferenceSettings(depth_min_m=2.0, depth_max_m=1.0)


def test_export_of_a_capture_without_valid_depth(tmp_path: Path) -> None:
    """Depth recorded but none valid: export refuses naming the scene and the way out
    (--no-reference), which then exports a bundle without a reference."""
    from brave6d.core.atomic import write_png
    from brave6d.serve import export_bundle, make_synthetic_scene

    scene = make_synthetic_scene(tmp_path / "scene", n_gaussians=2000, n_views=4, depth=True)
    for r in scene.frames():
        write_png(scene.capture.file(r.depth), np.zeros((240, 320), dtype=np.uint16))
    with pytest.raises(ReferenceGeometryError, match=r"scene .*scene: no depth frame has valid depth .*4 frame\(s\) "
                                                     r"skipped.*--no-reference"):
        export_bundle(scene.root)
    result = export_bundle(scene.root, reference=False)
    assert result.reference_triangles is None and load_bundle(result.root).reference_path is None


def _triangles(vertices: np.ndarray, faces: np.ndarray) -> set[tuple]:
    """Each triangle as its corner coordinates, started at the smallest corner (winding kept)."""
    out = set()
    for corners in vertices[faces].tolist():
        k = corners.index(min(corners))
        out.add(tuple(map(tuple, corners[k:] + corners[:k])))
    return out


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_canonical_order_is_the_same_for_any_vertex_and_face_order_and_keeps_the_surface(seed: int) -> None:
    """Open3D's threaded extraction emits one surface in varying orders; after canonical_order any
    permutation of vertices, of faces and of each face's starting corner gives the same arrays, and
    every triangle (with its winding) is the one it was."""
    rng = np.random.default_rng(seed)
    mesh = integrate_depth(iter(plane_frames([0.3, 0.4])), CAM, COARSE, "scene toy")
    v, f = mesh.vertices, mesh.faces
    perm = rng.permutation(len(v))
    inverse = np.argsort(perm)
    shuffled_v, shuffled_f = v[perm], np.roll(inverse[f][rng.permutation(len(f))], int(rng.integers(0, 3)), axis=1)
    v2, f2 = canonical_order(shuffled_v, shuffled_f)
    assert np.array_equal(v2, v) and np.array_equal(f2, f)  # integrate_depth returns the canonical order too
    assert _triangles(v2, f2) == _triangles(shuffled_v, shuffled_f)

"""The synthetic training split (``synth``): ground truth checked independently of the code that
wrote it, resting poses, determinism (same seed, any number of workers), resuming, and placement
properties (hypothesis)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.annotation import read_ply_mesh, read_scene_camera, read_scene_gt, read_scene_gt_info
from brave6d.core.atomic import read_png
from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.transforms import invert, make_transform, transform_points
from brave6d.synth import Randomization, SynthOptions, place_on_plane, resting_poses, synthesize

ROOT = Path(__file__).resolve().parent.parent
MESHES = ROOT / "data" / "demo" / "meshes"
OBJECTS = ("espresso_cup", "hex_nut", "sample_vial", "toy_brick", "block_green")


def _scene_yaml(folder: Path, width: int = 128, height: int = 96) -> Path:
    """A scene spec with five demo objects and no simulated effects (depth is exact)."""
    objects = "\n".join(f"  - {{name: {n}, category: mixed, mesh: {MESHES / (n + '.ply')}, scale: 0.001}}"
                        for n in OBJECTS)
    path = folder / "scene.yaml"
    path.write_text(f"""name: synth_test
capture: {{target: [0, 0, 0], distances_m: [0.2, 0.3, 0.4, 0.5]}}
workspace: {{min: [-1, -1, 0], max: [1, 1, 1]}}
camera: {{width: {width}, height: {height}, hfov_deg: 50}}
objects:
{objects}
""")
    return path


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("synth")
    spec = _scene_yaml(folder)
    out = folder / "out"
    synthesize(spec, out, SynthOptions(images=3, seed=0))
    return spec, out


# ----------------------------------------------------------------------------- an independent caster
def _cast_triangles(rays: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """z of the first hit of camera-frame rays (z = 1) from the origin on triangles (T, 3, 3),
    Moeller-Trumbore in float64 (inf = miss): a code path shared with nothing in the package."""
    best = np.full(len(rays), np.inf)
    p0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    for start in range(0, len(rays), 512):
        d = rays[start:start + 512, None, :]  # (R, 1, 3)
        h = np.cross(d, e2[None])
        a = np.einsum("rtk,tk->rt", h, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = 1.0 / a
            s = -p0[None]  # origin - p0
            u = f * np.einsum("rtk,rtk->rt", np.broadcast_to(s, h.shape), h)
            q = np.cross(np.broadcast_to(s, h.shape), e1[None])
            v = f * np.einsum("rtk,rtk->rt", np.broadcast_to(d, q.shape), q)
            t = f * np.einsum("rtk,tk->rt", q, e2)
        hit = (np.abs(a) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        best[start:start + 512] = np.where(hit, t, np.inf).min(axis=1)
    return best


def _object_depth(K: np.ndarray, width: int, height: int, vertices_m: np.ndarray, faces: np.ndarray,
                  cam_T_model: np.ndarray) -> np.ndarray:
    """(H, W) z-depth of one posed object alone (inf = not covered), at pixel centres."""
    tris = transform_points(cam_T_model, vertices_m)[faces]
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = np.stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1], np.ones(u.size)], axis=1)
    return _cast_triangles(rays, tris).reshape(height, width)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


# ----------------------------------------------------------------------------- acceptance
def test_ground_truth_matches_masks_rendered_again_from_the_written_poses(split: tuple[Path, Path]) -> None:
    _, out = split
    folder = out / "train_pbr" / "000000"
    cams, gts = read_scene_camera(folder / "scene_camera.json"), read_scene_gt(folder / "scene_gt.json")
    infos = read_scene_gt_info(folder / "scene_gt_info.json")
    assert sorted(gts) == [0, 1, 2]
    models = {i: read_ply_mesh(MESHES / f"{n}.ply", n) for i, n in enumerate(sorted(OBJECTS), start=1)}
    checked = occluded = 0
    for im_id, gt in gts.items():
        depth = read_png(folder / "depth" / f"{im_id:06d}.png", "depth").astype(np.float64) / 1000.0
        h, w = depth.shape
        for gt_id, g in enumerate(gt):
            model = models[g.obj_id]
            z = _object_depth(cams[im_id].cam_K, w, h, model.vertices * 0.001, model.faces, g.cam_T_model())
            ref_mask = np.isfinite(z)
            ref_visib = ref_mask & (depth > 0) & (np.abs(np.where(ref_mask, z, 0) - depth) <= 0.0015)
            mask = read_png(folder / "mask" / f"{im_id:06d}_{gt_id:06d}.png") > 0
            visib = read_png(folder / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png") > 0
            assert _iou(mask, ref_mask) >= 0.99, (im_id, gt_id, _iou(mask, ref_mask))
            assert _iou(visib, ref_visib) >= 0.99, (im_id, gt_id, _iou(visib, ref_visib))
            assert infos[im_id][gt_id].px_count_visib == int(visib.sum())
            checked += int(ref_mask.any())
            occluded += int(visib.sum() < mask.sum())
    assert checked >= 5 and occluded >= 2  # seed 0: objects in view, some of them partly hidden


def test_objects_rest_on_the_plane_with_rigid_poses(split: tuple[Path, Path]) -> None:
    _, out = split
    folder = out / "train_pbr" / "000000"
    cams, gts = read_scene_camera(folder / "scene_camera.json"), read_scene_gt(folder / "scene_gt.json")
    models = {i: read_ply_mesh(MESHES / f"{n}.ply", n) for i, n in enumerate(sorted(OBJECTS), start=1)}
    for im_id, gt in gts.items():
        world_T_cam = invert(cams[im_id].cam_T_world())
        for g in gt:
            R = g.cam_R_m2c
            assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
            lowest = transform_points(world_T_cam @ g.cam_T_model(), models[g.obj_id].vertices * 0.001)[:, 2].min()
            assert abs(lowest) <= 1e-4, (im_id, g.obj_id, lowest)  # on the plane, none below


def test_two_runs_with_one_seed_are_byte_identical_and_another_seed_differs(split: tuple[Path, Path],
                                                                            tmp_path: Path) -> None:
    spec, first = split
    again = tmp_path / "again"
    synthesize(spec, again, SynthOptions(images=3, seed=0))
    assert _tree(first) == _tree(again)
    other = tmp_path / "other"
    synthesize(spec, other, SynthOptions(images=3, seed=1))
    assert _tree(first)["train_pbr/000000/rgb/000000.png"] != _tree(other)["train_pbr/000000/rgb/000000.png"]


@pytest.mark.slow
def test_two_workers_write_the_same_bytes_as_one(split: tuple[Path, Path], tmp_path: Path) -> None:
    spec, first = split
    two = tmp_path / "two"
    synthesize(spec, two, SynthOptions(images=3, seed=0, workers=2))
    assert _tree(first) == _tree(two)


def test_a_resumed_run_skips_finished_images_and_ends_identical(split: tuple[Path, Path], tmp_path: Path) -> None:
    spec, first = split
    out = tmp_path / "resumed"
    assert synthesize(spec, out, SynthOptions(images=2, seed=0)).rendered == 2
    (out / "work" / "000001.json").unlink()  # image 1 interrupted before its record
    (out / "train_pbr" / "000000" / "rgb" / "000001.png").write_bytes(b"torn")
    result = synthesize(spec, out, SynthOptions(images=3, seed=0))
    assert (result.rendered, result.skipped) == (2, 1)
    assert _tree(first) == _tree(out)
    with pytest.raises(Exception, match="other settings"):
        synthesize(spec, out, SynthOptions(images=3, seed=9))


def test_cli_reports_images_per_second_and_errors_in_one_line(tmp_path: Path) -> None:
    spec = _scene_yaml(tmp_path, 32, 24)
    cmd = [sys.executable, "-m", "brave6d.cli", "synth", str(spec), str(tmp_path / "o"), "--images", "1"]
    ok = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "images/s" in ok.stdout
    bad = subprocess.run([*cmd[:4], str(tmp_path / "missing.yaml"), str(tmp_path / "p"), "--images", "1"],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert bad.returncode == 2 and "missing.yaml" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def _tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------- placement properties
def _convex_sets_intersect(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the convex hulls of point sets ``a`` and ``b`` share a point (an LP: no code shared
    with the footprint test it checks)."""
    from scipy.optimize import linprog

    na, nb = len(a), len(b)
    A_eq = np.zeros((5, na + nb))
    A_eq[:3, :na], A_eq[:3, na:] = a.T, -b.T
    A_eq[3, :na] = 1.0
    A_eq[4, na:] = 1.0
    res = linprog(np.zeros(na + nb), A_eq=A_eq, b_eq=[0, 0, 0, 1, 1], bounds=(0, None), method="highs")
    return res.status == 0


def _box(extents: tuple[float, float, float]) -> np.ndarray:
    e = np.asarray(extents) / 2
    return np.array([[x, y, z] for x in (-e[0], e[0]) for y in (-e[1], e[1]) for z in (-e[2], e[2])])


size = st.floats(min_value=0.0005, max_value=0.08)
thin = st.floats(min_value=0.0001, max_value=0.002)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(size, size, st.one_of(size, thin)), min_size=2, max_size=6),
       st.integers(min_value=0, max_value=2 ** 32 - 1))
def test_placed_boxes_and_thin_plates_never_interpenetrate_or_sink(extents: list[tuple[float, float, float]],
                                                                   seed: int) -> None:
    rng = np.random.default_rng(seed)
    shapes = []
    for e in extents:
        tilt = make_transform(np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1], np.zeros(3))
        if np.linalg.det(tilt[:3, :3]) < 0:
            tilt[:3, 0] *= -1
        v = transform_points(tilt, _box(e))
        shapes.append((v, resting_poses(v)))
    placement = place_on_plane(shapes, rng, radius_m=0.05, clearance_m=0.0)
    assert placement.placed and placement.placed[0] == 0  # the first always fits
    posed = {}
    for i in placement.placed:
        T = placement.poses[i]
        assert T is not None and np.all(np.isfinite(T))
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9) and np.linalg.det(T[:3, :3]) > 0
        posed[i] = transform_points(T, shapes[i][0])
        assert abs(posed[i][:, 2].min()) <= 1e-9  # on the plane, not below
    keys = sorted(posed)
    for n, i in enumerate(keys):
        for j in keys[n + 1:]:
            shrink_i = posed[i].mean(axis=0) + (posed[i] - posed[i].mean(axis=0)) * (1 - 1e-6)
            assert not _convex_sets_intersect(shrink_i, posed[j]), (i, j)


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(["flat", "needle", "point", "random"]), st.integers(3, 30),
       st.integers(min_value=0, max_value=2 ** 32 - 1))
def test_degenerate_meshes_give_a_clear_error_or_a_valid_pose(kind: str, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.05, 0.05, size=(n, 3))
    if kind == "flat":
        pts[:, 2] = 0.01
        pts = pts @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    elif kind == "needle":
        pts = rng.uniform(-0.05, 0.05, size=(n, 1)) * rng.normal(size=(1, 3)) + rng.normal(size=3)
    elif kind == "point":
        pts = np.repeat(rng.normal(size=(1, 3)), n, axis=0)
    try:
        rest = resting_poses(pts)
    except DegenerateGeometryError as exc:
        assert kind in ("point", "needle") and "extent" in str(exc)
        return
    assert np.all(np.isfinite(rest.transforms)) and np.isclose(rest.probabilities.sum(), 1.0)
    for T in rest.transforms:
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-9)
        assert abs(transform_points(T, pts)[:, 2].min()) <= 1e-9


def test_randomization_settings_are_checked() -> None:
    with pytest.raises(Exception, match="objects per image"):
        Randomization(min_objects=3, max_objects=2)

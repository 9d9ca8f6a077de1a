"""The weight-free baseline agent (brave6d.evaluation.agents): perception, registration and multi-view fusion
on ray-cast views with a known answer, then both policies end to end against a live server on
127.0.0.1 (the demo's evaluation stage on the synthetic bundle), the client and Gym-style submission.

Slow (minutes): the end-to-end part renders every episode on the CPU; the ray-cast scenes and the
evaluation stage are built once per module and shared."""

from __future__ import annotations

import json
from dataclasses import replace
from functools import cache
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from brave6d.annotation import write_ply_mesh
from brave6d.core.transforms import invert, look_at, make_transform
from brave6d.evaluation.agents import (
    ACTIVE_AGENT,
    STATIC_AGENT,
    Cluster,
    RegistrationOptions,
    View,
    make_agent,
    multiview_icp,
    one_thread,
    perceive,
    read_model_ply,
    register_model,
    register_views,
    run_episode,
    sample_model,
    view_scene,
    view_weights,
    voxel_size,
)
from brave6d.evaluation.metrics.bop_metrics import identity_symmetries, mssd
from brave6d.evaluation.metrics.episodes import read_episodes
from brave6d.evaluation.metrics.depth_renderer import render_depth
from brave6d.serve.app import create_app
from brave6d.serve.bundle import Bundle, load_bundle
from brave6d.serve.client import BraveClient, PoseEstimate
from brave6d.serve.gym_env import BraveEnv
from brave6d.serve.runner import ServerThread
from brave6d.serve.toy_scene import cube_mesh_mm, make_synthetic_bundle

pytestmark = pytest.mark.slow

K = np.array([[277.0, 0.0, 159.5], [0.0, 277.0, 119.5], [0.0, 0.0, 1.0]])  # 320 x 240, 60 deg
W, H = 320, 240


def l_shape_mm(scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """An L-shaped block (no rotational symmetry) resting on z = 0, millimetres."""
    bar = trimesh.creation.box((40, 12, 12), make_transform(np.eye(3), (0, 0, 6)))
    post = trimesh.creation.box((12, 12, 24), make_transform(np.eye(3), (14, 0, 24)))
    mesh = trimesh.util.concatenate([bar, post])
    return np.asarray(mesh.vertices) * scale, np.asarray(mesh.faces)


def diameter_mm(vertices: np.ndarray) -> float:
    from brave6d.serve.bundle import model_diameter

    return model_diameter(vertices)


def view(vertices: np.ndarray, faces: np.ndarray, world_T_obj: np.ndarray, world_T_cam: np.ndarray,
         noise_m: float = 0.0005, seed: int = 0) -> np.ndarray:
    """Depth (m) of the object on a table top (z = 0, 0.6 m square), ray cast, with noise."""
    table = trimesh.creation.box((600, 600, 10), make_transform(np.eye(3), (0, 0, -5)))
    cam_T_world = invert(world_T_cam)
    depths = []
    for v, f, T in ((vertices, faces, world_T_obj), (np.asarray(table.vertices), np.asarray(table.faces), np.eye(4))):
        P = cam_T_world @ T
        depths.append(render_depth(v, f, P[:3, :3], P[:3, 3] * 1000.0, K, W, H))
    d = np.where(depths[0] > 0, depths[0], np.inf)
    d = np.minimum(d, np.where(depths[1] > 0, depths[1], np.inf))
    d = np.where(np.isfinite(d), d / 1000.0, 0.0)
    rng = np.random.default_rng(seed)
    return np.where(d > 0, d + rng.normal(0.0, noise_m, d.shape), 0.0).astype(np.float32)


@cache
def scene_case(scale: float, distance: float, elevation_deg: float = 55.0,  # type: ignore[no-untyped-def]
               yaw_deg: float = 30.0):
    """(vertices, faces, model cloud, world_T_obj, world_T_cam, depth) of an L on a table
    (cached: every test reads it, none changes it)."""
    v, f = l_shape_mm(scale)
    model = sample_model(7, v, f, diameter_mm(v), 1500, seed=0)
    world_T_obj = make_transform(Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix(), (0.02, -0.01, 0.0))
    centre = world_T_obj[:3, 3] + np.array([0.0, 0.0, 0.012 * scale])
    el, az = np.radians(elevation_deg), np.radians(200.0)
    eye = centre + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    world_T_cam = look_at(eye, centre)
    return v, f, model, world_T_obj, world_T_cam, view(v, f, world_T_obj, world_T_cam)


def elsewhere_T_obj() -> np.ndarray:
    """Where a misleading view shows the L: 6 cm off and turned by 70 degrees."""
    world_T_obj = scene_case(1.0, 0.25)[3]
    return world_T_obj @ make_transform(Rotation.from_euler("z", 70, degrees=True).as_matrix(), (0.06, 0.0, 0.0))


@cache
def l_view(azimuth_deg: float, noise_m: float = 0.0005, misleading: bool = False) -> View:
    """One view of the L from ``azimuth_deg`` (0.25 m, 55 deg up) and the agent's perception of it;
    ``misleading``: the depth image shows the L elsewhere (a neighbour or a splat artefact)."""
    v, f, model, world_T_obj, _, _ = scene_case(1.0, 0.25)
    return observe_shape(v, f, model, world_T_obj, azimuth_deg, elsewhere_T_obj() if misleading else world_T_obj,
                         noise_m)


def observe_shape(v: np.ndarray, f: np.ndarray, model, world_T_obj: np.ndarray,  # type: ignore[no-untyped-def]
                  azimuth_deg: float, shown_T_obj: np.ndarray, noise_m: float) -> View:
    """A view looking at the L's place from ``azimuth_deg`` whose depth shows the mesh (v, f) at ``shown_T_obj``."""
    centre = world_T_obj[:3, 3] + np.array([0.0, 0.0, 0.012])
    el, az = np.radians(55.0), np.radians(azimuth_deg)
    world_T_cam = look_at(centre + 0.25 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]),
                          centre)
    depth = view(v, f, shown_T_obj, world_T_cam, noise_m)
    obs = SimpleNamespace(world_T_cam=world_T_cam, depth=depth, K=K)
    return View(obs, perceive(depth, K, world_T_cam, model, None))


def centre_error(world_T_est: np.ndarray, world_T_obj: np.ndarray) -> float:
    """Distance (m) between the L's centre under two poses."""
    centre = scene_case(1.0, 0.25)[0].mean(axis=0) / 1000.0
    return float(np.linalg.norm((world_T_est[:3, :3] @ centre + world_T_est[:3, 3])
                                - (world_T_obj[:3, :3] @ centre + world_T_obj[:3, 3])))


# ----------------------------------------------------------------------------- units
def test_model_sample_is_on_the_surface_with_outward_normals(tmp_path: Path) -> None:
    v, f = cube_mesh_mm()
    m = sample_model(1, v, f, 34.64, 1000, seed=3)
    assert m.points.shape == (1000, 3) and m.diameter_m == pytest.approx(0.03464)
    p = m.points * 1000.0
    on_face = np.isclose(np.abs(p[:, 0]), 10) | np.isclose(np.abs(p[:, 1]), 10) | np.isclose(p[:, 2], 0) | \
        np.isclose(p[:, 2], 20)
    assert on_face.all()
    centre = np.array([0.0, 0.0, 0.01])
    assert np.all(np.einsum("ij,ij->i", m.normals, m.points - centre) > 0)
    flipped = sample_model(1, v, f[:, ::-1], 34.64, 1000, seed=3)  # inward winding is repaired
    np.testing.assert_array_equal(flipped.normals, m.normals)
    np.testing.assert_array_equal(sample_model(1, v, f, 34.64, 1000, seed=3).points, m.points)
    write_ply_mesh(tmp_path / "cube.ply", v, f)
    verts, faces, colors = read_model_ply((tmp_path / "cube.ply").read_bytes())
    np.testing.assert_allclose(verts, v)
    np.testing.assert_array_equal(faces, f)
    assert colors is None and m.colors is None, "a model without vertex colours samples none"


def test_perception_finds_the_object_above_the_table() -> None:
    v, f, model, world_T_obj, world_T_cam, depth = scene_case(1.0, 0.25)
    seen = perceive(depth, K, world_T_cam, model, None)
    assert seen.plane is not None and seen.cluster is not None
    up = world_T_cam[2, :3]
    assert float(seen.plane.n @ up) > 0.99  # the table, not the object's faces
    truth = invert(world_T_cam) @ world_T_obj
    centre = truth[:3, :3] @ (v.mean(axis=0) / 1000.0) + truth[:3, 3]
    assert np.linalg.norm(seen.cluster.centroid - centre) < 0.5 * model.diameter_m
    assert 0.5 * model.extents[0] < seen.cluster.extents[0] < 1.3 * model.extents[0]


@pytest.mark.parametrize("scale, distance", [(1.0, 0.25), (0.3, 0.09)], ids=["45mm", "tiny-14mm"])
def test_registration_recovers_the_pose(scale: float, distance: float) -> None:
    v, f, model, world_T_obj, world_T_cam, depth = scene_case(scale, distance)
    seen = perceive(depth, K, world_T_cam, model, None)
    assert seen.cluster is not None
    reg = register_model(model, seen.cluster, seen.plane, depth, K, min_height=seen.min_height)
    truth = invert(world_T_cam) @ world_T_obj
    err = mssd(reg.cam_T_obj[:3, :3], reg.cam_T_obj[:3, 3] * 1000, truth[:3, :3], truth[:3, 3] * 1000, v,
               identity_symmetries())
    assert err < 0.1 * model.diameter_m * 1000, (err, reg)
    again = register_model(model, seen.cluster, seen.plane, depth, K, min_height=seen.min_height)
    np.testing.assert_array_equal(again.cam_T_obj, reg.cam_T_obj)  # deterministic


AZIMUTHS = (200.0, 235.0, 165.0)


def views_with_a_misleading_one(misleading_at: int) -> list[View]:
    """Three views of the L; one (``misleading_at``) shows it 6 cm from where the other two see it,
    and most clearly (no depth noise, so its own registration scores best in its own view)."""
    return [l_view(az, 0.0, True) if i == misleading_at else l_view(az, 0.002) for i, az in enumerate(AZIMUTHS)]


@pytest.mark.parametrize("misleading_at", [0, 1])
def test_fusion_gives_the_final_views_fit_refined_on_all_views(misleading_at: int) -> None:
    """The final (last) view and one other agree; the submitted pose, in the final view's frame,
    is where they see the object, however clearly the third view shows something else."""
    model, world_T_obj = scene_case(1.0, 0.25)[2], scene_case(1.0, 0.25)[3]
    views = views_with_a_misleading_one(misleading_at)
    assert all(p.cluster is not None for _, p in views)
    reg = register_views(model, views)
    assert reg is not None and np.all(np.isfinite(reg.cam_T_obj))
    world_T_est = views[-1].observation.world_T_cam @ reg.cam_T_obj
    assert centre_error(world_T_est, world_T_obj) < 0.5 * model.diameter_m < \
        centre_error(world_T_est, elsewhere_T_obj())
    assert reg.score > 0.3  # it explains the consistent views (scores are at most 1)


def test_fusion_keeps_the_final_views_own_fit() -> None:
    """The final view is where the estimate is scored: its own fit stands even when the other
    views see the object elsewhere."""
    model = scene_case(1.0, 0.25)[2]
    views = views_with_a_misleading_one(2)
    reg = register_views(model, views)
    world_T_est = views[-1].observation.world_T_cam @ reg.cam_T_obj
    assert centre_error(world_T_est, elsewhere_T_obj()) < 0.5 * model.diameter_m


def turned_in_place_T_obj(degrees: float) -> np.ndarray:
    """The L at its place, turned by ``degrees`` about the vertical through its centroid."""
    v, world_T_obj = scene_case(1.0, 0.25)[0], scene_case(1.0, 0.25)[3]
    centre = v.mean(axis=0) / 1000.0
    turn = make_transform(Rotation.from_euler("z", degrees, degrees=True).as_matrix(), (0.0, 0.0, 0.0))
    return world_T_obj @ make_transform(np.eye(3), centre) @ turn @ make_transform(np.eye(3), -centre)


def rotation_error_deg(world_T_est: np.ndarray, world_T_obj: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(world_T_obj[:3, :3].T @ world_T_est[:3, :3]).magnitude()))


def test_fusion_takes_how_the_object_is_turned_from_the_views_that_explain_all_views() -> None:
    """The views agree where the object is but the final one shows it turned (the demo's cup, whose
    handle the far start view cannot resolve and two nearer views can): the orientation that
    explains every view best is submitted, in the final view's frame. Before, the final view's own
    fit stood (90 deg off)."""
    v, f, model, world_T_obj, _, _ = scene_case(1.0, 0.25)
    turned = turned_in_place_T_obj(90.0)
    # (from 235 deg the L's half turn explains those two views as well as the truth: not used here)
    views = [l_view(200.0), l_view(150.0), observe_shape(v, f, model, world_T_obj, 250.0, turned, 0.0005)]
    assert all(p.cluster is not None for _, p in views)
    own = register_model(model, views[2].perception.cluster, views[2].perception.plane, views[2].observation.depth, K,
                         min_height=views[2].perception.min_height)
    assert rotation_error_deg(views[2].observation.world_T_cam @ own.cam_T_obj, turned) < 10.0  # it sees the turn
    reg = register_views(model, views)
    world_T_est = views[-1].observation.world_T_cam @ reg.cam_T_obj
    assert rotation_error_deg(world_T_est, world_T_obj) < 10.0 < 80.0 < rotation_error_deg(world_T_est, turned)
    assert centre_error(world_T_est, world_T_obj) < 0.1 * model.diameter_m


@pytest.mark.parametrize("misleading_at", [0, 1, 2])
def test_without_the_target_in_the_final_view_the_views_outvote_a_misleading_one(misleading_at: int) -> None:
    """The final view shows no cluster: the registration that explains all views best is
    submitted, in the final view's frame, and the misleading view is outvoted."""
    model, world_T_obj = scene_case(1.0, 0.25)[2], scene_case(1.0, 0.25)[3]
    views = views_with_a_misleading_one(misleading_at)
    final = l_view(200.0)
    reg = register_views(model, views, final=View(final.observation, replace(final.perception, cluster=None)))
    world_T_est = final.observation.world_T_cam @ reg.cam_T_obj
    assert centre_error(world_T_est, world_T_obj) < 0.5 * model.diameter_m < \
        centre_error(world_T_est, elsewhere_T_obj())


def test_fusion_reports_in_the_final_view() -> None:
    """``final``: the chosen pose is expressed in that view's frame (the agent went back to its
    start view to submit), whatever the order of the views it registered."""
    model, world_T_obj = scene_case(1.0, 0.25)[2], scene_case(1.0, 0.25)[3]
    views = [l_view(az) for az in AZIMUTHS]
    reg = register_views(model, views, final=views[0])
    assert reg is not None and np.all(np.isfinite(reg.cam_T_obj))
    world_T_est = views[0].observation.world_T_cam @ reg.cam_T_obj
    assert centre_error(world_T_est, world_T_obj) < 0.1 * model.diameter_m
    in_last = register_views(model, views)  # default: the last view
    world_T_last = views[-1].observation.world_T_cam @ in_last.cam_T_obj
    assert np.linalg.norm(world_T_last[:3, 3] - world_T_est[:3, 3]) < 0.1 * model.diameter_m


def test_refinement_on_all_views_pins_the_pose_down() -> None:
    """Starting 5 mm and 6 degrees off, ICP on the clusters of three noisy views at once (in the
    first view's frame) lands clearly nearer the truth (MSSD) than ICP on that view alone."""
    v, _, model, world_T_obj, _, _ = scene_case(1.0, 0.25)
    views = [l_view(az, 0.002) for az in (200.0, 250.0, 150.0)]
    assert all(p.cluster is not None for _, p in views)
    voxel = voxel_size(model, RegistrationOptions())
    scenes = [view_scene(p.cluster, p.plane, p.min_height, o.depth, o.K, voxel) for o, p in views]
    ref_T_world = invert(views[0].observation.world_T_cam)
    refs_T_cam = [ref_T_world @ o.world_T_cam for o, _ in views]
    truth = ref_T_world @ world_T_obj
    start = truth @ make_transform(Rotation.from_euler("xz", [6.0, -6.0], degrees=True).as_matrix(),
                                   (0.004, -0.003, 0.0))

    def error(T: np.ndarray) -> float:
        return float(mssd(T[:3, :3], T[:3, 3] * 1000, truth[:3, :3], truth[:3, 3] * 1000, v, identity_symmetries()))

    with one_thread():  # as the agent runs it: Open3D's parallel sums vary otherwise
        both = multiview_icp(model, start, scenes, refs_T_cam, voxel)
        again = multiview_icp(model, start, scenes, refs_T_cam, voxel)
        alone = multiview_icp(model, start, scenes[:1], refs_T_cam[:1], voxel)
    assert np.all(np.isfinite(both))
    # measured: start 9.8 mm, the first view alone 2.2 mm, all three views 1.5 mm (two: 1.3 mm)
    assert error(both) < 0.7 * error(alone) < error(start), (error(both), error(alone), error(start))
    assert error(both) < 0.05 * model.diameter_m * 1000
    np.testing.assert_array_equal(again, both)


def test_a_view_no_pose_explains_well_votes_less() -> None:
    """A view whose cluster is not the object (a ball the L-shaped model fits only in part) gets
    a clearly smaller weight than the views that see the object."""
    model, world_T_obj = scene_case(1.0, 0.25)[2], scene_case(1.0, 0.25)[3]
    views = [l_view(az) for az in (200.0, 235.0)]
    ball = trimesh.creation.icosphere(2, 30.0)
    ball_T = make_transform(np.eye(3), world_T_obj[:3, 3] + np.array([0.0, 0.0, 0.03]))
    views.append(observe_shape(np.asarray(ball.vertices), np.asarray(ball.faces), model, world_T_obj, 165.0, ball_T,
                               0.0005))
    own = [register_model(model, p.cluster, p.plane, o.depth, o.K, min_height=p.min_height).score for o, p in views]
    w = view_weights(own)
    assert w[2] < 0.75 * min(w[0], w[1]), (own, w)


def test_fusion_needs_a_cluster() -> None:
    model = scene_case(1.0, 0.25)[2]
    obs, seen = l_view(200.0)
    assert register_views(model, [View(obs, replace(seen, cluster=None))]) is None


def test_registration_falls_back_cleanly_on_a_few_points() -> None:
    v, f = cube_mesh_mm()
    model = sample_model(1, v, f, 34.64, 500)
    cluster = Cluster(np.array([[0.0, 0.0, 0.3], [0.001, 0.0, 0.3], [0.0, 0.001, 0.301]]),
                      np.array([[10, 10], [11, 10], [10, 11]]))
    reg = register_model(model, cluster, None, np.zeros((H, W), np.float32), K)
    assert np.all(np.isfinite(reg.cam_T_obj)) and reg.method in ("resting", "centroid")
    assert np.linalg.norm(reg.cam_T_obj[:3, 3] - [0.0, 0.0, 0.3]) < 2 * model.diameter_m


def test_nothing_to_see_gives_no_cluster() -> None:
    v, f = cube_mesh_mm()
    model = sample_model(1, v, f, 34.64, 500)
    assert perceive(np.zeros((H, W), np.float32), K, np.eye(4), model, None).cluster is None


# ----------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("baseline_scene"), n_gaussians=8000))


@pytest.fixture(scope="module")
def stage(bundle: Bundle, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    from brave6d.evaluation.demo import stage_evaluate

    work = tmp_path_factory.mktemp("evaluate_stage")
    ctx = SimpleNamespace(scene=SimpleNamespace(bundle_dir=bundle.root), workdir=work, device="cpu", quick=True)
    return stage_evaluate(ctx), work / "evaluation"


def test_evaluation_stage_runs_both_baselines_on_every_object(stage,  # type: ignore[no-untyped-def]
                                                              bundle: Bundle) -> None:
    from brave6d.evaluation.agents import runnable_agents

    result, out = stage
    n_agents = len(runnable_agents())  # no learned model in this work directory: the weight-free agents
    assert result.figures["episodes"] == n_agents * len(bundle.objects)
    for key in ("AR active", "AR static", "mean adjustments"):
        assert isinstance(result.figures[key], float) and np.isfinite(result.figures[key])
    for name in ("leaderboard.csv", "leaderboard.json", "episodes.csv", "per_object.csv", "baseline.json"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "baseline.json").read_text())
    assert summary["format"] == "brave6d-baseline/2" and summary["image_size"] == [320, 240]
    assert summary["mode"] == "scored" and {a["mode"] for a in summary["agents"]} == {"scored"}
    assert result.figures["mode"] == "scored"  # the baselines play the default, scored server
    assert {a["agent"] for a in summary["agents"]} == set(runnable_agents()) == {"baseline-active", "baseline-static"}
    assert {"agent", "ar", "ar_vsd", "ar_mssd", "ar_mspd", "mean_adjustments", "mean_wall_time_s", "episodes"} <= \
        set(summary["agents"][0])
    rows = summary["episodes"]
    assert len(rows) == n_agents * len(bundle.objects)
    for row in rows:
        assert 0.0 <= row["ar"] <= 1.0 and row["found"] is True
    active = [row["adjustments"] for row in rows if row["agent"] == ACTIVE_AGENT]
    assert [row["adjustments"] for row in rows if row["agent"] == STATIC_AGENT] == [0] * len(bundle.objects)
    # the active agent found every cube: at least one side view and the way back to its start
    assert len(active) == len(bundle.objects) and min(active) >= 2
    assert result.figures["mean adjustments"] == pytest.approx(float(np.mean(active)))
    objects = (out / "per_object.csv").read_text().splitlines()
    assert len(objects) == 1 + n_agents * len(bundle.objects) and "cube_red" in objects[1] + objects[2]


def test_baselines_find_the_cube_and_start_alike(stage, bundle: Bundle) -> None:  # type: ignore[no-untyped-def]
    _, out = stage
    episodes = read_episodes([out / "episodes"])
    starts: dict[str, list] = {}
    for e in episodes:
        reset = json.loads(e.path.read_text().splitlines()[0])
        starts.setdefault(e.target.name, []).append(np.asarray(reset["world_T_cam"]))
        assert e.submitted and len(e.estimates) == 1
        est, truth = e.estimates[0], e.target.cam_T_obj
        centre = np.array([0.0, 0.0, 0.01])  # the cube's centre in its model frame
        error = np.linalg.norm((est.R @ centre + est.t_m) - (truth[:3, :3] @ centre + truth[:3, 3]))
        assert error < 0.012, (e.agent, e.target.name, error)  # a reasonably placed 20 mm cube
    for name, poses in starts.items():
        np.testing.assert_array_equal(poses[0], poses[1], err_msg=name)


def test_active_baseline_submits_from_its_start_view(stage) -> None:  # type: ignore[no-untyped-def]
    """The active variant explores, then goes back to the pose it started from (inside the
    capture rings, where the splat was trained) and submits there; the move back counts."""
    _, out = stage
    checked = 0
    for e in read_episodes([out / "episodes"]):
        if e.agent != "baseline-active":
            continue
        records = [json.loads(line) for line in e.path.read_text().splitlines()]
        moves = [r for r in records if r["event"] in ("set_pose", "move") and r["accepted"]]
        if len(moves) < 2:
            continue
        start = np.asarray(records[0]["world_T_cam"])
        np.testing.assert_allclose(moves[-1]["world_T_cam"], start, atol=1e-12)
        assert moves[-1]["adjustments"] == len(moves)
        checked += 1
    assert checked >= 1


def test_client_and_gym_env_submit(bundle: Bundle, tmp_path: Path) -> None:
    app = create_app(bundle, device="cpu", log_dir=tmp_path, warm_up=False, mode="training")  # the gym agent cheats
    with ServerThread(app) as server, BraveClient(server.url) as client:
        assert server.host == "127.0.0.1"
        agent = make_agent(STATIC_AGENT, client)
        first = run_episode(client, agent, "cube_blue", seed=5, width=160, height=120)
        again = run_episode(client, agent, "cube_blue", seed=5, width=160, height=120)
        np.testing.assert_array_equal(first.estimates[0].cam_T_obj, again.estimates[0].cam_T_obj)
        assert first.submission["submitted"] and first.adjustments == 0
        env = BraveEnv(client=client, target="cube_red", width=64, height=48, agent="gym-agent", mode="training")
        obs, info = env.reset(seed=1)
        truth = next(o for o in info["objects"] if o.is_target)
        obs, reward, terminated, truncated, info = env.submit([PoseEstimate(truth.obj_id, truth.cam_T_obj)])
        assert terminated and not truncated and info["submission"]["estimates"] == 1
        with pytest.raises(RuntimeError):
            env.step(np.zeros(6))
    agents = {e.agent for e in read_episodes([tmp_path])}
    assert agents == {"baseline-static", "gym-agent"}

"""Episode scoring (brave6d.evaluation.metrics.episodes, brave6d evaluate) on hand-made logs written by the
server's own record writer, and the estimates endpoint (POST /episodes/{id}/estimates)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.core.atomic import depth_m_to_mm_u16, read_png, write_png
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.transforms import look_at, make_transform
from brave6d.evaluation.metrics.episodes import (
    episode_to_bop,
    models_from_bundle,
    read_episode,
    read_episodes,
    score_episodes,
    write_leaderboard,
)
from brave6d.evaluation.metrics.recall import ObjectModel, evaluate_bop19
from brave6d.evaluation.metrics.depth_renderer import render_depth
from brave6d.serve import (
    Bundle,
    EpisodeLog,
    FinalView,
    LoggedEstimate,
    ObjectState,
    ResetRecord,
    SceneServer,
    ServerLimits,
    SubmitRecord,
    TargetRef,
    create_app,
    load_bundle,
    make_synthetic_bundle,
    read_episode_log,
)
from brave6d.serve.toy_scene import cube_mesh_mm

CAMERA = PinholeCamera.from_hfov(96, 72, 60.0)
#: cube_red (obj_id 1) 0.25 m in front of the camera, turned about its vertical axis
GT = make_transform(Rotation.from_euler("xyz", [110, 5, 30], degrees=True).as_matrix(), [0.01, -0.005, 0.25])
FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
#: above the red cube, looking down at it: splat depth is right there (seen obliquely, a splat
#: table looks centimetres higher than it is and VSD can then miss even the exact pose)
ABOVE_RED = look_at((0.40, -0.05, 0.22), (0.45, -0.03, 0.01))


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("scoring_scene"), n_gaussians=8000))


@pytest.fixture(scope="module")
def models(bundle: Bundle) -> dict[int, ObjectModel]:
    return models_from_bundle(bundle)


def depth_of(cam_T_obj: np.ndarray) -> np.ndarray:
    """What the server would log: the cube seen alone (metres, 0 = no data)."""
    v, f = cube_mesh_mm()
    return render_depth(v, f, cam_T_obj[:3, :3], cam_T_obj[:3, 3] * 1000.0, CAMERA.K, CAMERA.width,
                        CAMERA.height).astype(np.float32) / 1000.0


def write_episode(folder: Path, eid: str, agent: str | None, estimates: list[np.ndarray] | None,
                  gt: np.ndarray = GT, adjustments: int = 0, bundle_name: str = "synthetic_tabletop",
                  started: str = "2026-01-01T00:00:00.000+00:00", scene: str | None = None, seed: int = 7) -> Path:
    """A reset (+ submit with ``estimates``, cam_T_obj 4x4 of obj 1; None: no submission) log,
    written through the server's log schema (:mod:`brave6d.serve.episode_log`)."""
    folder.mkdir(parents=True, exist_ok=True)
    target = TargetRef(gt_id=0, obj_id=1, name="cube_red")
    depth = depth_of(gt)
    px = int(np.count_nonzero(depth))
    objects = [ObjectState(gt_id=0, obj_id=1, name="cube_red", is_target=True, cam_T_obj=gt, px_count_all=px,
                           px_count_visib=px, visib_fract=1.0),
               ObjectState(gt_id=1, obj_id=2, name="cube_blue", is_target=False,
                           cam_T_obj=make_transform(np.eye(3), [0.2, 0.0, 0.5]), px_count_all=10, px_count_visib=0,
                           visib_fract=0.0)]
    reset = ResetRecord(time=started, episode_id=eid, bundle=bundle_name, agent=agent, target=target, scene=scene,
                        width=CAMERA.width, height=CAMERA.height, K=CAMERA.K, seed=seed, start="random",
                        world_T_cam=np.eye(4), timings_ms={}, target_cam_T_obj=gt, target_visib_fract=1.0)
    lines = [EpisodeLog.format(reset)]
    if estimates is not None:
        depth_file = f"{eid}_final_depth.png"
        write_png(folder / depth_file, depth_m_to_mm_u16(depth))
        submit = SubmitRecord(
            time=started, episode_id=eid, agent=agent, bundle=bundle_name, bundle_root=str(folder.resolve()),
            target=target, estimates=[LoggedEstimate(obj_id=1, R=T[:3, :3], t_m=T[:3, 3], score=0.9) for T in estimates],
            final_view=FinalView(world_T_cam=np.eye(4), K=CAMERA.K, width=CAMERA.width, height=CAMERA.height,
                                 depth_file=depth_file),
            objects=objects, adjustments=adjustments, steps=adjustments, refusals=0, collisions=0, elapsed_s=1.5)
        lines.append(EpisodeLog.format(submit))
    path = folder / f"{eid}.jsonl"
    path.write_text("".join(lines))
    return path


def score_one(path: Path, models: dict[int, ObjectModel]) -> dict[str, float]:
    board = score_episodes([read_episode(path)], models)
    a = board.agents[0]
    return {"ar": a.ar, **a.ar_per_metric}


# ----------------------------------------------------------------------------- scoring
def test_exact_pose_scores_one(tmp_path: Path, models: dict[int, ObjectModel]) -> None:
    scores = score_one(write_episode(tmp_path, "exact", "oracle", [GT]), models)
    assert scores == {"ar": 1.0, "vsd": 1.0, "mssd": 1.0, "mspd": 1.0}


def test_empty_and_missing_submissions_score_zero(tmp_path: Path, models: dict[int, ObjectModel]) -> None:
    assert score_one(write_episode(tmp_path, "empty", "lazy", []), models)["ar"] == 0.0
    path = write_episode(tmp_path / "nosub", "nosub", "lazy", None)
    ep = read_episode(path)
    assert not ep.submitted and ep.target.is_target and ep.estimates == ()
    assert score_one(path, models)["ar"] == 0.0


def test_symmetric_object_rotated_by_its_symmetry(tmp_path: Path, models: dict[int, ObjectModel]) -> None:
    cube = models[1]
    rz90 = make_transform(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [0.0, 0.0, 0.0])
    sym = {1: ObjectModel(1, cube.points, cube.diameter, cube.faces, (tuple(rz90.reshape(-1)),))}
    est = GT @ rz90  # the same cube surface, another model frame
    path = write_episode(tmp_path, "sym", "symm", [est])
    scores = score_one(path, sym)
    assert scores["mssd"] == 1.0 and scores["mspd"] == 1.0 and scores["vsd"] == 1.0
    assert score_one(path, models)["mssd"] == 0.0  # without the symmetry it is 90 degrees off


def test_target_always_counts_and_other_objects_only_on_request(tmp_path: Path) -> None:
    ep = read_episode(write_episode(tmp_path, "t", "a", [GT]))
    gts, ests = episode_to_bop(ep, 3, 4)
    assert [(g.scene_id, g.im_id, g.obj_id) for g in gts] == [(3, 4, 1)] and len(ests) == 1
    np.testing.assert_allclose(ests[0].t, GT[:3, 3] * 1000.0)
    gts, _ = episode_to_bop(ep, 3, 4, all_objects=True)
    assert [g.obj_id for g in gts] == [1, 2] and gts[1].visib_fract == 0.0  # cube_blue: not visible
    np.testing.assert_array_equal(gts[0].depth(), read_png(ep.depth_path).astype(np.float64))


def test_agents_ranked_and_aggregated_exactly(tmp_path: Path, models: dict[int, ObjectModel]) -> None:
    shifted = GT.copy()
    shifted[:3, 3] += [0.004, 0.0, 0.0]
    far = GT.copy()
    far[:3, 3] += [0.0, 0.0, 0.012]
    paths = [write_episode(tmp_path, f"a{i}", "alpha", [T], adjustments=i, started=f"2026-01-01T00:00:0{i}.000+00:00")
             for i, T in enumerate([GT, shifted, far])]
    paths.append(write_episode(tmp_path, "b0", "beta", [far], adjustments=5))
    paths.append(write_episode(tmp_path, "b1", "beta", None, adjustments=1))
    episodes = read_episodes([tmp_path])
    board = score_episodes(episodes, models)
    assert [a.agent for a in board.agents] == ["alpha", "beta"]
    alpha, beta = board.agents
    assert alpha.episodes == 3 and alpha.mean_adjustments == 1.0 and beta.submitted == 1
    # per-episode counts add up to the AR of one BOP evaluation over all of alpha's episodes
    ids = {s.episode.episode_id: (s.scene_id, s.im_id) for s in board.episodes}
    gts, ests = [], []
    for e in episodes:
        if e.agent == "alpha":
            g, est = episode_to_bop(e, *ids[e.episode_id])
            gts += g
            ests += est
    direct = evaluate_bop19(gts, ests, models)
    assert alpha.ar == pytest.approx(direct.ar, abs=1e-12)
    for m in ("vsd", "mssd", "mspd"):
        assert alpha.ar_per_metric[m] == pytest.approx(direct.metrics[m].ar, abs=1e-12)
    assert [s.im_id for s in board.episodes if s.episode.agent == "alpha"] == [0, 1, 2]  # by start time
    written = write_leaderboard(board, tmp_path / "out")
    assert {p.name for p in written} == {"leaderboard.csv", "leaderboard.json", "episodes.csv", "per_object.csv",
                                         "per_scene.csv", "per_category.csv", "not_ranked.csv", "paired.csv"}
    assert (tmp_path / "out" / "leaderboard.csv").read_text().splitlines()[0].startswith("agent,mode,episodes,submitted")
    assert {a.mode for a in board.agents} == {"training"}  # hand-made logs name no mode: older than the modes
    data = json.loads((tmp_path / "out" / "leaderboard.json").read_text())
    assert data["agents"][0]["agent"] == "alpha" and len(data["episodes"]) == 5


def test_the_leaderboard_gives_active_minus_static_paired_by_start(tmp_path: Path,
                                                                  models: dict[int, ObjectModel]) -> None:
    off = GT @ make_transform(np.eye(3), [0.3, 0.0, 0.0])
    for seed in range(4):  # the active agent right from every start, the static one from half of them
        write_episode(tmp_path, f"act{seed}", "mine-active", [GT], seed=seed, started=f"2026-01-01T00:00:0{seed}.000+00:00")
        write_episode(tmp_path, f"sta{seed}", "mine-static", [GT if seed % 2 else off], seed=seed,
                      started=f"2026-01-01T00:01:0{seed}.000+00:00")
    write_episode(tmp_path, "lone", "mine-active", [GT], seed=9)  # a start the static agent never played
    board = score_episodes(read_episodes([tmp_path]), models)
    [d] = board.paired
    assert (d.active, d.static, d.pairs) == ("mine-active", "mine-static", 4)
    assert d.mean == pytest.approx(0.5) and d.se == pytest.approx(0.5 / math.sqrt(4) * math.sqrt(4 / 3))
    assert "not resolved: about 6 paired starts would resolve 0.500" in board.paired_table()  # 1.7 SE
    write_leaderboard(board, tmp_path / "out")
    assert (tmp_path / "out" / "paired.csv").read_text().splitlines()[1].startswith("mine-active,mine-static,4,0.5")
    assert json.loads((tmp_path / "out" / "leaderboard.json").read_text())["paired"][0]["pairs"] == 4


def test_scores_per_scene_and_category_are_exact(tmp_path: Path, models: dict[int, ObjectModel]) -> None:
    """Scenes and categories group the same exact true-positive sums as the agent's AR."""
    miss = GT @ make_transform(np.eye(3), [0.3, 0.0, 0.0])
    write_episode(tmp_path, "s0", "alpha", [GT], scene="bench")
    write_episode(tmp_path, "s1", "alpha", [GT], scene="bench", started="2026-01-01T00:00:01.000+00:00")
    write_episode(tmp_path, "s2", "alpha", [miss], scene="shelf", started="2026-01-01T00:00:02.000+00:00")
    write_episode(tmp_path, "s3", "alpha", [miss], bundle_name="old_bundle")  # a version-1 style log: no scene
    board = score_episodes(read_episodes([tmp_path]), models, categories={1: "toys_office"})
    by_scene = {g.group: g for g in board.scenes}
    assert set(by_scene) == {"bench", "shelf", "old_bundle"}
    assert by_scene["bench"].ar == pytest.approx(1.0) and by_scene["bench"].episodes == 2
    assert by_scene["shelf"].ar == pytest.approx(0.0) and by_scene["old_bundle"].ar == pytest.approx(0.0)
    overall = board.agents[0]
    assert overall.ar == pytest.approx(sum(g.n_targets * g.ar for g in board.scenes) / overall.n_targets)
    [category] = board.categories
    assert category.group == "toys_office" and category.n_targets == 4
    assert category.ar == pytest.approx(overall.ar) and category.ar_per_metric == pytest.approx(overall.ar_per_metric)
    uncategorised = score_episodes(read_episodes([tmp_path]), models).categories
    assert [g.group for g in uncategorised] == ["uncategorised"]
    assert "| bench" in board.group_table("scene") and "toys_office" in board.group_table("category")


def test_cli_prints_leaderboard_and_writes_files(tmp_path: Path, bundle: Bundle,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.evaluation import cli

    logs = tmp_path / "logs"
    write_episode(logs, "c0", "oracle", [GT])
    write_episode(logs, "c1", None, [])
    parser = argparse.ArgumentParser()
    cli.configure(parser)
    args = parser.parse_args([str(logs), "--bundle", str(bundle.root), "--out", str(tmp_path / "lb"),
                              "--mode", "training"])  # hand-made logs name no mode: they read as training
    assert cli.run(args) == 0
    out = capsys.readouterr().out
    assert "| agent" in out and "oracle" in out and "unknown" in out and "AR_MSPD" in out
    assert (tmp_path / "lb" / "leaderboard.csv").is_file()
    write_episode(logs, "c2", "x", [GT], bundle_name="another_scene")
    with pytest.raises(DataError, match="another_scene"):
        cli.run(args)


def test_bundle_found_from_the_logs(tmp_path: Path, bundle: Bundle) -> None:
    from brave6d.evaluation.cli import resolve_bundles

    write_episode(tmp_path, "r0", "a", [GT])
    eps = read_episodes([tmp_path])
    assert resolve_bundles(eps, [tmp_path], bundle.root) == [bundle.root]
    with pytest.raises(DataError, match="--bundle"):
        resolve_bundles(eps, [tmp_path], None)  # the recorded root (tmp_path) holds no bundle


@pytest.mark.parametrize("text, match", [
    ('{"event": "move"}\n', "first record must be a 'reset'"),
    ('{"event": "reset", "episode_id": "x"}\n', r":1: 'reset' record does not match .* field 'bundle'"),
    ('{"event": "reset", "format_version": 5}\n', r":1: episode log format version 5 is not supported"),
    ('{"event": "reset", "format_version": "1"}\n', r":1: episode log format version '1' is not supported"),
    ('{"event": "reset"}\nnot json\n{"event": "close"}\n', r":2: not valid JSON"),
])
def test_malformed_logs_name_file_and_field(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.jsonl"
    path.write_text(text)
    with pytest.raises(DataError, match=match) as info:
        read_episode(path)
    assert "bad.jsonl" in str(info.value)


def test_no_logs_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="no episode logs"):
        read_episodes([tmp_path])
    with pytest.raises(DataError, match="not found"):
        read_episodes([tmp_path / "missing"])


@settings(max_examples=25)
@given(quat=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: sum(x * x for x in q) > 1e-3),
       t=st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.2, 1.0)),
       score=st.floats(-1e6, 1e6))
def test_scores_are_finite_for_any_rigid_estimate(tmp_path_factory: pytest.TempPathFactory,
                                                  models: dict[int, ObjectModel], quat: list[float],
                                                  t: tuple[float, float, float], score: float) -> None:
    folder = tmp_path_factory.mktemp("prop")
    est = make_transform(Rotation.from_quat(quat).as_matrix(), t)
    path = write_episode(folder, "p", "prop", [est])
    rec = json.loads(path.read_text().splitlines()[1])
    rec["estimates"][0]["score"] = score
    path.write_text(path.read_text().splitlines()[0] + "\n" + json.dumps(rec) + "\n")
    board = score_episodes(read_episodes([path]), models)
    values = [board.agents[0].ar, *board.agents[0].ar_per_metric.values()]
    assert all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values)


# ----------------------------------------------------------------------------- the endpoint
@pytest.fixture(scope="module")
def served(bundle: Bundle, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    log_dir = tmp_path_factory.mktemp("estimates_logs")
    app = create_app(bundle, scene=SceneServer(bundle, device="cpu"), log_dir=log_dir,
                     limits=ServerLimits(max_episodes=100), warm_up=False, mode="training")  # the oracle reads the truth
    with TestClient(app, base_url="http://localhost") as client:
        yield client, log_dir


def new_episode(client: TestClient, start: np.ndarray = FREE, width: int = 64, height: int = 48,
                **extra: object) -> dict:
    r = client.post("/episodes", json={"start": {"world_T_cam": start.tolist()}, "target": "cube_red",
                                       "width": width, "height": height, "rgb": "none", **extra})
    assert r.status_code == 201, r.text
    return r.json()


def test_submission_is_logged_with_the_final_view(served, bundle: Bundle) -> None:  # type: ignore[no-untyped-def]
    client, log_dir = served
    first = new_episode(client, ABOVE_RED, 160, 120, agent="oracle-1")
    eid = first["episode_id"]
    step = client.post(f"/episodes/{eid}/move", json={"linear": [0, 0, 0.04], "duration": 0.5, "rgb": "none"}).json()
    assert step["accepted"]
    obs = step["observation"]
    gt = np.asarray(next(o for o in obs["objects"] if o["is_target"])["cam_T_obj"])
    r = client.post(f"/episodes/{eid}/estimates", json={"estimates": [
        {"obj_id": 1, "R": gt[:3, :3].reshape(-1).tolist(), "t_m": gt[:3, 3].tolist(), "score": 0.7}]})
    assert r.status_code == 200, r.text
    reply = r.json()
    assert reply["submitted"] and reply["closed"] and reply["estimates"] == 1 and reply["adjustments"] == 1
    assert reply["depth_file"] == f"{eid}_final_depth.png" and reply["agent"] == "oracle-1"
    records = read_episode_log(log_dir / f"{eid}.jsonl")
    assert [r.event for r in records] == ["reset", "move", "submit", "close", "digest"]
    sub = records[2]
    assert sub.final_view.width == 160 and sub.final_view.height == 120
    np.testing.assert_allclose(sub.final_view.K, obs["K"])
    np.testing.assert_allclose(sub.final_view.world_T_cam, obs["world_T_cam"])
    assert [o.gt_id for o in sub.objects] == [o.gt_id for o in bundle.objects]
    assert all(o.visib_fract is not None for o in sub.objects)
    depth = read_png(log_dir / reply["depth_file"], expect="depth")
    d_obs = np.frombuffer(__import__("base64").b64decode(obs["depth"]["data"]), "<f4").reshape(120, 160)
    np.testing.assert_array_equal(depth, depth_m_to_mm_u16(d_obs))
    ep = read_episode(log_dir / f"{eid}.jsonl")
    assert ep.agent == "oracle-1" and ep.adjustments == 1 and ep.submitted
    # a bundle without a reference geometry: scored on the splat's depth, and the score says so
    assert sub.final_view.depth_source == "splat" and ep.test_depth == "splat"
    board = score_episodes([ep], models_from_bundle(bundle))
    assert board.agents[0].ar == 1.0 and board.to_json()["test_depth"] == ["splat"]
    assert board.episodes[0].to_json()["test_depth"] == "splat"
    # the episode is over
    assert client.post(f"/episodes/{eid}/estimates", json={"estimates": []}).status_code == 409
    assert client.post(f"/episodes/{eid}/move", json={"linear": [0, 0, 0.01], "duration": 0.5}).status_code == 409
    assert client.get(f"/episodes/{eid}").json()["submitted"] is True


I3 = [1, 0, 0, 0, 1, 0, 0, 0, 1]
BAD_SUBMISSIONS = [
    ('{"estimates": [{"obj_id": 1, "R": [NaN,0,0,0,1,0,0,0,1], "t_m": [0,0,0.3]}]}', 422, "finite", "estimates.0.R"),
    ('{"estimates": [{"obj_id": 1, "R": %s, "t_m": [0,Infinity,0.3]}]}' % I3, 422, "finite", "estimates.0.t_m"),
    ('{"estimates": [{"obj_id": 1, "R": %s, "t_m": [0,0,0.3], "score": NaN}]}' % I3, 422, "finite", None),
    ('{"estimates": [{"obj_id": 1, "R": [2,0,0,0,1,0,0,0,1], "t_m": [0,0,0.3]}]}', 422, "not a rotation",
     "estimates.0.R"),
    ('{"estimates": [{"obj_id": 1, "R": [1,0.1,0,0,1,0,0,0,1], "t_m": [0,0,0.3]}]}', 422, "orthonormal", None),
    ('{"estimates": [{"obj_id": 1, "R": [-1,0,0,0,1,0,0,0,1], "t_m": [0,0,0.3]}]}', 422, "det = -1", None),
    ('{"estimates": [{"obj_id": 1, "R": [1,0,0,0,1,0,0,0], "t_m": [0,0,0.3]}]}', 422, "at least 9", None),
    ('{"estimates": [{"obj_id": 99, "R": %s, "t_m": [0,0,0.3]}]}' % I3, 422, "unknown object id 99",
     "estimates.0.obj_id"),
    ('{"estimates": [{"obj_id": 1, "R": %s, "t_m": [0,0,0.3], "extra": 1}]}' % I3, 422, "Extra inputs", None),
    ('{"estimates": [{"R": %s, "t_m": [0,0,0.3]}]}' % I3, 422, "obj_id", None),
    ('{"estimates": []%s}' % ', "agent": "bad/name"', 422, "agent", "agent"),
    ('{"estimates": %s}' % json.dumps([{"obj_id": 1, "R": I3, "t_m": [0, 0, 0.3]}] * 101), 422, "at most 100", None),
    ('{"estimates": [', 400, "malformed JSON", None),
    ('{}', 422, "estimates", None),
]


@pytest.mark.parametrize("text, status, match, field", BAD_SUBMISSIONS)
def test_bad_submissions_are_refused(served, text: str, status: int, match: str,  # type: ignore[no-untyped-def]
                                     field: str | None) -> None:
    client, log_dir = served
    eid = new_episode(client, depth="none")["episode_id"]
    r = client.post(f"/episodes/{eid}/estimates", content=text.encode(), headers={"content-type": "application/json"})
    assert r.status_code == status, r.text
    body = r.json()
    assert match in body["error"], body
    if field is not None:
        assert field in body["field"]  # pydantic errors say body.estimates.0.R.0
    assert client.get(f"/episodes/{eid}").json()["submitted"] is False  # nothing happened
    assert not (log_dir / f"{eid}_final_depth.png").exists()
    assert client.post(f"/episodes/{eid}/close").status_code == 200


def test_submit_to_unknown_episode_is_404(served) -> None:  # type: ignore[no-untyped-def]
    client, _ = served
    r = client.post("/episodes/nope/estimates", json={"estimates": []})
    assert r.status_code == 404 and r.json()["field"] == "episode_id"

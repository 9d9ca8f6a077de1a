"""Scored and training modes over HTTP, the WebSocket and the gymnasium envs, and the logs' keyed
digest as ``brave6d evaluate`` checks it.

Each interface is played by an agent that keeps every reply it gets (bodies, ``GET /bundle``, the
episode's state, the ``.npz``, the submission's answer; the envs' observations and infos) and
searches them for the target's true pose (:mod:`truth_search`: any pose within 1 mm and 1 degree of
its world_T_obj or of its cam_T_obj in any view of the episode). In scored mode it finds nothing;
in training mode it finds it (so the search can fail)."""

from __future__ import annotations

import argparse
import io
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from truth_search import target_truths, truth_found

from brave6d.core.errors import BraveError, DataError
from brave6d.core.transforms import look_at
from brave6d.evaluation.metrics import models_from_bundle, read_episode, read_episodes, score_episodes
from brave6d.serve import (
    BraveEnv,
    BraveVectorEnv,
    Bundle,
    EpisodeManager,
    LogKey,
    SceneServer,
    ServerLimits,
    ServerThread,
    create_app,
    load_bundle,
    make_synthetic_bundle,
)

TARGET = "cube_red"
SEED = 3
FREE2 = look_at((0.30, 0.10, 0.35), (0.46, 0.0, 0.01))
#: A shared 2-core machine can take long over one render: no test waits on the server's 30 s default.
LIMITS = ServerLimits(request_timeout_s=600)
TRUTH_FIELDS = ("cam_T_obj", "world_T_obj", "visib_fract", "bbox_visib", "bbox_obj", "px_count_visib", "px_count_all")


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("scored_scene"), n_gaussians=3000))


@pytest.fixture(scope="module")
def scene(bundle: Bundle) -> SceneServer:
    from brave6d.serve.catalog import warm_scene

    return warm_scene(SceneServer(bundle, device="cpu"))  # the kernels compiled before any request's timeout runs


def world_T_target(bundle: Bundle) -> np.ndarray:
    return next(o.world_T_obj for o in bundle.objects if o.name == TARGET)


def cameras_in(replies: list[Any]) -> list[np.ndarray]:
    """Every world_T_cam the agent was told (4x4 under a ``world_T_cam`` key, anywhere)."""
    out: list[np.ndarray] = []

    def walk(v: Any) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                if k == "world_T_cam" and np.asarray(x).shape == (4, 4):
                    out.append(np.asarray(x, dtype=np.float64))
                else:
                    walk(x)
        elif isinstance(v, (list, tuple)):
            for x in v:
                walk(x)

    for r in replies:
        walk(r)
    return out


def truth_keys(value: Any) -> set[str]:
    """The ground-truth fields (:data:`TRUTH_FIELDS`) that hold a value anywhere in ``value``."""
    found: set[str] = set()
    if isinstance(value, dict):
        for k, v in value.items():
            if k in TRUTH_FIELDS and v is not None and np.size(v) > 0:
                found.add(k)
            found |= truth_keys(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            found |= truth_keys(v)
    return found


def check(mode: str, replies: list[Any], bundle: Bundle, cameras: list[np.ndarray] | None = None) -> None:
    truths = target_truths(world_T_target(bundle), cameras if cameras is not None else cameras_in(replies))
    assert len(truths) > 2  # the target's world pose and at least two views of it
    found = truth_found(replies, truths)
    if mode == "scored":
        assert found == [], f"scored mode: the target's true pose is in {found}"
        assert not any(truth_keys(r) for r in replies), [truth_keys(r) for r in replies]
    else:
        assert found, "training mode: the search found no true pose (it cannot fail?)"


# ----------------------------------------------------------------------------- HTTP and WebSocket
@pytest.mark.parametrize("mode", ["scored", "training"])
def test_http_agent_finds_the_truth_only_in_training_mode(mode: str, bundle: Bundle, scene: SceneServer,
                                                          tmp_path: Path) -> None:
    app = create_app(bundle, scene=scene, log_dir=tmp_path / "logs", mode=mode, warm_up=False, limits=LIMITS)
    replies: list[Any] = []
    with TestClient(app, base_url="http://localhost") as client:
        def get(method: str, path: str, **kw: Any) -> Any:
            r = client.request(method, path, **kw)
            assert r.status_code < 300, r.text
            replies.append(r.json())
            return r.json()

        for path in ("/health", "/bundle", "/scenes"):
            assert get("GET", path)["mode" if path != "/scenes" else "scenes"]
        first = get("POST", "/episodes", json={"target": TARGET, "seed": SEED, "width": 96, "height": 72,
                                               "rgb": "none"})
        eid = first["episode_id"]
        assert first["mode"] == mode and first["target"]["name"] == TARGET  # the target's identity in both
        get("POST", f"/episodes/{eid}/move", json={"linear": [0, 0, 0.02], "duration": 0.5, "rgb": "none"})
        get("POST", f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": FREE2.tolist()}, "rgb": "none"})
        get("GET", f"/episodes/{eid}")
        get("GET", "/episodes")
        npz = client.get(f"/episodes/{eid}/observation.npz")
        with np.load(io.BytesIO(npz.content)) as data:
            replies.append({k: data[k] for k in data.files if k not in ("rgb", "depth")})
        get("POST", f"/episodes/{eid}/estimates", json={"estimates": [
            {"obj_id": 1, "R": np.eye(3).reshape(-1).tolist(), "t_m": [0.0, 0.0, 0.3]}]})
    assert (replies[1]["objects"][0].get("world_T_obj") is None) == (mode == "scored")
    check(mode, replies, bundle)


@pytest.mark.parametrize("mode", ["scored", "training"])
def test_websocket_agent_finds_the_truth_only_in_training_mode(mode: str, bundle: Bundle, scene: SceneServer,
                                                               tmp_path: Path) -> None:
    app = create_app(bundle, scene=scene, log_dir=tmp_path / "logs", mode=mode, warm_up=False, limits=LIMITS)
    with TestClient(app, base_url="http://localhost") as client:
        first = client.post("/episodes", json={"target": TARGET, "seed": SEED, "width": 96, "height": 72,
                                               "rgb": "none"}).json()
        replies: list[Any] = [first]
        with client.websocket_connect(f"ws://localhost/episodes/{first['episode_id']}/ws") as ws:
            for msg in ({"op": "move", "linear": [0, 0, 0.02], "duration": 0.5, "rgb": "none"},
                        {"op": "set_pose", "pose": {"world_T_cam": FREE2.tolist()}, "rgb": "none"},
                        {"op": "get"}, {"op": "close"}):
                ws.send_text(json.dumps(msg))
                replies.append(json.loads(ws.receive_text()))
    assert all("error" not in r for r in replies), replies
    assert all(r["mode"] == mode for r in replies)
    check(mode, replies, bundle)


# ----------------------------------------------------------------------------- gymnasium
@pytest.mark.parametrize("mode", ["scored", "training"])
def test_gym_agent_finds_the_truth_only_in_training_mode(mode: str, bundle: Bundle, scene: SceneServer,
                                                         tmp_path: Path) -> None:
    from brave6d.serve import PoseEstimate

    app = create_app(bundle, scene=scene, log_dir=tmp_path / "logs", mode=mode, warm_up=False, limits=LIMITS)
    with ServerThread(app) as server:
        env = BraveEnv(server.url, target=TARGET, width=96, height=72, max_steps=10, mode=mode)
        try:
            obs, info = env.reset(seed=SEED)
            replies: list[Any] = [obs, info, env._last.message]  # and the reply the env kept from the server
            cameras = [obs["world_T_cam"]]
            rewards = []
            for action in ([0, 0, 0.5, 0, 0, 0], [0.2, 0, 0, 0, 0.3, 0]):
                obs, reward, _, _, info = env.step(np.array(action, dtype=np.float32))
                replies += [obs, info, env._last.message]
                cameras.append(obs["world_T_cam"])
                rewards.append(reward)
            obs, reward, terminated, _, info = env.submit([PoseEstimate(1, np.eye(4))])
            replies += [obs, info]
            assert terminated and info["submission"]["mode"] == mode
        finally:
            env.close()
    assert all(r["mode"] == mode for r in replies if isinstance(r, dict) and "episode_id" in r)
    assert ("objects" in replies[1]) == (mode == "training")
    if mode == "scored":
        assert rewards == [0.0, 0.0]  # the visible area is ground truth
    check(mode, replies, bundle, cameras)


def test_gym_env_refuses_a_server_of_the_other_mode(bundle: Bundle, scene: SceneServer, tmp_path: Path) -> None:
    for served, asked, says in (("training", "scored", "without --training"), ("scored", "training", "--training")):
        app = create_app(bundle, scene=scene, log_dir=tmp_path / served, mode=served, warm_up=False, limits=LIMITS)
        with ServerThread(app) as server:
            env = BraveEnv(server.url, target=TARGET, width=64, height=48, mode=asked)
            with pytest.raises(BraveError, match=f"runs in {served} mode.*{says}"):
                env.reset(seed=0)
            assert env.client.episode_id is None  # the refused episode was closed
            env.close()
    with pytest.raises(BraveError, match="mode"):
        BraveEnv("http://127.0.0.1:1", mode="evaluation")


@pytest.mark.parametrize("mode", ["scored", "training"])
def test_vector_agent_finds_the_truth_only_in_training_mode(mode: str, bundle: Bundle, scene: SceneServer) -> None:
    envs = BraveVectorEnv(scene, 2, target=TARGET, width=64, height=48, mode=mode)
    try:
        obs, info = envs.reset(seed=SEED)
        replies: list[Any] = [obs, info]
        cameras = list(obs["world_T_cam"])
        for _ in range(2):
            obs, rewards, _, _, info = envs.step(np.tile([0, 0, 0.5, 0, 0.2, 0], (2, 1)))
            replies += [obs, info, rewards]
            cameras += list(obs["world_T_cam"])
        # the sub-environments' views, as the envs hold them (what a subclass could read)
        replies += [list(v.objects) for v in envs._views if v is not None]
    finally:
        envs.close()
    if mode == "scored":
        assert not np.any(rewards)
    check(mode, replies, bundle, cameras)
    with pytest.raises(BraveError, match="runs in training mode"):
        BraveVectorEnv(EpisodeManager(scene, mode="training"), 1, mode="scored")


# ----------------------------------------------------------------------------- the digest
def scored_episode(bundle: Bundle, scene: SceneServer, logs: Path, key: LogKey, estimate: np.ndarray) -> Path:
    """One scored episode on ``bundle`` signed with ``key``; the log's path."""
    app = create_app(bundle, scene=scene, log_dir=logs, mode="scored", log_key=key, warm_up=False, limits=LIMITS)
    with TestClient(app, base_url="http://localhost") as client:
        eid = client.post("/episodes", json={"target": TARGET, "seed": SEED, "width": 96, "height": 72,
                                             "rgb": "none", "agent": "honest"}).json()["episode_id"]
        r = client.post(f"/episodes/{eid}/estimates", json={"estimates": [
            {"obj_id": 1, "R": estimate[:3, :3].reshape(-1).tolist(), "t_m": estimate[:3, 3].tolist()}]})
        assert r.status_code == 200, r.text
    return logs / f"{eid}.jsonl"


def evaluate(logs: Path, bundle: Bundle, key_file: Path, out: Path, *extra: str) -> int:
    from brave6d.evaluation import cli

    parser = argparse.ArgumentParser()
    cli.configure(parser)
    return cli.run(parser.parse_args([str(logs), "--bundle", str(bundle.root), "--out", str(out),
                                      "--log-key", str(key_file), *extra]))


def test_an_edited_log_is_refused_and_a_copy_rescores_alike(bundle: Bundle, scene: SceneServer, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    key_file = tmp_path / "server.key"
    from brave6d.serve import server_log_key

    key = server_log_key(key_file)
    assert key_file.stat().st_mode & 0o777 == 0o600 and server_log_key(key_file).key_id == key.key_id
    # an estimate near the truth (so that an edit can move the score), in the final view's frame
    logs = tmp_path / "logs"
    probe = read_episode(scored_episode(bundle, scene, tmp_path / "probe", key, np.eye(4)), key)
    truth = probe.target.cam_T_obj.copy()
    truth[:3, 3] += 0.02
    log = scored_episode(bundle, scene, logs, key, truth)
    assert evaluate(logs, bundle, key_file, tmp_path / "first") == 0
    first = json.loads((tmp_path / "first" / "leaderboard.json").read_text())
    assert first["mode"] == "scored" and first["agents"][0]["mode"] == "scored"
    assert first["episodes"][0]["digest"] == "verified" and first["not_ranked"] == []
    # an unedited copy elsewhere scores the same
    copy = tmp_path / "copy"
    copy.mkdir()
    for f in logs.iterdir():
        shutil.copy2(f, copy / f.name)
    assert evaluate(copy, bundle, key_file, tmp_path / "second") == 0
    second = json.loads((tmp_path / "second" / "leaderboard.json").read_text())
    assert second["agents"][0]["ar"] == first["agents"][0]["ar"]
    eid = log.stem
    # one estimate edited (moved onto the truth): refused, naming the episode
    lines = (copy / log.name).read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if '"event": "submit"' in line)
    record = json.loads(lines[k])
    record["estimates"][0]["t_m"] = probe.target.cam_T_obj[:3, 3].tolist()
    lines[k] = json.dumps(record)
    (copy / log.name).write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=f"episode {eid}: the log does not match the digest"):
        evaluate(copy, bundle, key_file, tmp_path / "third")
    # an adjustment count edited, the depth image replaced, a line added after the digest: refused too
    for edit, match in (
        (lambda text: text.replace('"adjustments": 0', '"adjustments": 1', 1), "does not match the digest"),
        (lambda text: text + lines[0] + "\n", "after the log's 'digest' record"),
    ):
        shutil.copy2(log, copy / log.name)
        (copy / log.name).write_text(edit(log.read_text()))
        with pytest.raises(DataError, match=match):
            evaluate(copy, bundle, key_file, tmp_path / "fourth")
    shutil.copy2(log, copy / log.name)
    depth = next(copy.glob("*_final_depth.png"))
    depth.write_bytes(depth.read_bytes()[:-12] + b"\0" * 12)
    with pytest.raises(DataError, match=f"episode {eid}: the final depth image is not the one"):
        evaluate(copy, bundle, key_file, tmp_path / "fifth")


def test_evaluate_ranks_scored_episodes_and_lists_the_others_apart(bundle: Bundle, scene: SceneServer,
                                                                   tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.serve import server_log_key

    key_file = tmp_path / "server.key"
    key = server_log_key(key_file)
    logs = tmp_path / "logs"
    scored = scored_episode(bundle, scene, logs, key, np.eye(4))
    other_key = scored_episode(bundle, scene, logs, LogKey.random(), np.eye(4))
    app = create_app(bundle, scene=scene, log_dir=logs, mode="training", log_key=key, warm_up=False, limits=LIMITS)
    with TestClient(app, base_url="http://localhost") as client:
        eid = client.post("/episodes", json={"target": TARGET, "seed": SEED, "width": 96, "height": 72,
                                             "rgb": "none", "agent": "cheat"}).json()["episode_id"]
        client.post(f"/episodes/{eid}/estimates", json={"estimates": []})
    training = logs / f"{eid}.jsonl"
    assert evaluate(logs, bundle, key_file, tmp_path / "board") == 0
    out = capsys.readouterr().out
    board = json.loads((tmp_path / "board" / "leaderboard.json").read_text())
    assert [e["episode_id"] for e in board["episodes"]] == [scored.stem]
    apart = {n["episode_id"]: n for n in board["not_ranked"]}
    assert set(apart) == {other_key.stem, training.stem}
    assert apart[training.stem]["mode"] == "training" and "training mode" in apart[training.stem]["reason"]
    assert apart[other_key.stem]["digest"] == "unknown key" and "--log-key" in apart[other_key.stem]["reason"]
    assert training.stem in out and other_key.stem in out and "Not ranked" in out
    csv_rows = (tmp_path / "board" / "not_ranked.csv").read_text().splitlines()
    assert len(csv_rows) == 3 and csv_rows[0].startswith("agent,episode_id")
    assert "mode" in (tmp_path / "board" / "episodes.csv").read_text().splitlines()[0].split(",")
    # a development board ranks the training episode instead
    assert evaluate(logs, bundle, key_file, tmp_path / "dev", "--mode", "training") == 0
    dev = json.loads((tmp_path / "dev" / "leaderboard.json").read_text())
    assert [e["episode_id"] for e in dev["episodes"]] == [training.stem] and dev["agents"][0]["mode"] == "training"
    # only training episodes: a scored board refuses, naming them
    only = tmp_path / "only_training"
    only.mkdir()
    shutil.copy2(training, only / training.name)
    with pytest.raises(DataError, match=f"{training.stem} \\(cheat\\): training mode"):
        evaluate(only, bundle, key_file, tmp_path / "none")
    # the library: the same ranking
    lb = score_episodes(read_episodes([logs], key), models_from_bundle(bundle), mode="scored")
    assert [a.agent for a in lb.agents] == ["honest"] and len(lb.not_ranked) == 2

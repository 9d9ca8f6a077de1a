"""The render server on a real uvicorn server (loopback, free port): Python client, Gymnasium-style
environment, concurrent clients, WebSocket, limits over real sockets, the demo stages."""

from __future__ import annotations

import importlib.util
import json
import threading
from pathlib import Path
from types import SimpleNamespace

import httpx
import gymnasium
import numpy as np
import pytest

from brave6d.core.transforms import look_at
from brave6d.serve.app import ServerLimits, create_app
from brave6d.serve.bundle import Bundle, load_bundle
from brave6d.serve.client import BraveClient, ServerError
from brave6d.serve import SceneServer, read_episode_log
from brave6d.serve import BraveEnv
from brave6d.serve.runner import ServerThread
from brave6d.serve.toy_scene import make_synthetic_bundle

REPO = Path(__file__).resolve().parent.parent
FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
IN_POST = look_at((0.30, 0.25, 0.15), (0.46, 0.0, 0.01))


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("live_scene")
    make_synthetic_bundle(root, n_gaussians=8000)
    return root


@pytest.fixture(scope="module")
def bundle(scene_dir: Path) -> Bundle:
    return load_bundle(scene_dir / "bundle")


@pytest.fixture(scope="module")
def server(bundle: Bundle, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    log_dir = tmp_path_factory.mktemp("live_episodes")
    # training mode: these agents read the ground truth (tests/test_scored_mode.py plays the default, scored)
    app = create_app(bundle, device="cpu", log_dir=log_dir, limits=ServerLimits(max_episodes=64), mode="training")
    with ServerThread(app) as srv:
        srv.log_dir = log_dir
        yield srv


def test_server_binds_loopback(server: ServerThread) -> None:
    assert server.host == "127.0.0.1" and server.url.startswith("http://127.0.0.1:")
    assert httpx.get(server.url + "/health").json()["status"] == "ok"


def test_python_client_episode(server: ServerThread, bundle: Bundle) -> None:
    with BraveClient(server.url) as client:
        assert client.health()["device"] == "cpu"
        assert client.bundle()["name"] == bundle.name
        step = client.reset(target="cube_blue", width=200, height=150, start=FREE)
        obs = step.observation
        assert obs.rgb.shape == (150, 200, 3) and obs.depth.dtype == np.float32 and obs.depth.shape == (150, 200)
        assert obs.target().name == "cube_blue" and step.adjustments == 0
        step = client.move(linear=(0, 0, 0.03), duration=0.5)
        assert step.accepted and step.adjustments == 1
        np.testing.assert_allclose(step.observation.world_T_cam[:3, 3], FREE[:3, 3] + 0.015 * FREE[:3, 2], atol=1e-9)
        refused = client.set_pose(IN_POST)
        assert not refused.accepted and refused.refusal["box"] == "post" and refused.adjustments == 1
        np.testing.assert_array_equal(refused.observation.world_T_cam, step.observation.world_T_cam)
        arrays = client.observation_npz()
        np.testing.assert_array_equal(arrays["depth"], step.observation.depth)
        assert client.model(1).startswith(b"ply")
        with pytest.raises(ServerError) as info:
            client.set_pose({"world_T_cam": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.3], [0, 0, 0, 1]]})
        assert info.value.status == 422 and "orthonormal" in info.value.message
        summary = client.close()
        assert summary["adjustments"] == 1 and summary["refusals"] == 1
        with pytest.raises(ServerError) as info:
            client.move(linear=(0, 0, 0.01), duration=0.5, episode_id=step.episode_id)
        assert info.value.status == 409


def test_gym_style_environment(server: ServerThread) -> None:
    env = BraveEnv(server.url, target="cube_red", width=160, height=120, max_steps=4, step_duration=0.5,
                   mode="training")
    obs, info = env.reset(seed=3)
    assert set(obs) == {"rgb", "depth", "K", "world_T_cam"}
    assert isinstance(env, gymnasium.Env) and isinstance(env.observation_space, gymnasium.spaces.Dict)
    assert env.observation_space.contains(obs)  # dtypes and shapes are what the space promises
    assert env.observation_space["rgb"].shape == (120, 160, 3) and obs["rgb"].shape == (120, 160, 3)
    assert env.action_space.shape == (6,) and env.action_space.contains(env.action_space.sample())
    assert info["target"]["name"] == "cube_red" and info["adjustments"] == 0
    # forward towards the target: the visible area grows -> positive reward
    obs2, reward, terminated, truncated, info = env.step(np.array([0, 0, 1.0, 0, 0, 0]))
    assert info["accepted"] and reward > 0 and not terminated and not truncated
    assert info["adjustments"] == 1
    # a teleport into the post: refused, no reward, same observation
    obs3, reward, terminated, truncated, info = env.step({"world_T_cam": IN_POST})
    assert not info["accepted"] and reward == 0.0 and info["adjustments"] == 1
    np.testing.assert_array_equal(obs3["world_T_cam"], obs2["world_T_cam"])
    _, _, terminated, truncated, _ = env.step({"linear": [0, 0, -0.02], "duration": 0.5})
    assert not truncated
    _, _, terminated, truncated, info = env.step(np.zeros(6))
    assert truncated and not terminated  # max_steps = 4
    with pytest.raises(RuntimeError):
        env.step(np.zeros(6))
    obs, info = env.reset(seed=3, options={"start": FREE})
    np.testing.assert_allclose(obs["world_T_cam"], FREE, atol=1e-12)
    _, _, terminated, truncated, info = env.step({"stop": True})
    assert terminated and info["stopped"]
    env.close()


def test_concurrent_clients_get_their_own_episodes(server: ServerThread) -> None:
    n = 6
    results: dict[int, dict] = {}
    errors: list[str] = []
    barrier = threading.Barrier(n)

    def worker(k: int) -> None:
        try:
            with BraveClient(server.url) as client:
                start = look_at((0.25 + 0.02 * k, -0.15, 0.30), (0.46, 0.0, 0.01))
                barrier.wait(timeout=30)
                step = client.reset(width=96, height=72, start=start)
                for _ in range(k % 3 + 1):
                    step = client.move(linear=(0, 0, 0.02), duration=0.5)
                results[k] = {"episode": step.episode_id, "adjustments": step.adjustments,
                              "pose": step.observation.world_T_cam, "start": start, "moves": k % 3 + 1,
                              "state": client.state()}
                client.close()
        except Exception as exc:  # noqa: BLE001
            errors.append(f"{k}: {exc!r}")

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    assert len({r["episode"] for r in results.values()}) == n
    for r in results.values():
        assert r["adjustments"] == r["moves"] == r["state"]["adjustments"]
        expected = r["start"][:3, 3] + 0.01 * r["moves"] * r["start"][:3, 2]
        np.testing.assert_allclose(r["pose"][:3, 3], expected, atol=1e-9)


def test_websocket_over_a_real_socket(server: ServerThread) -> None:
    from websockets.sync.client import connect

    with BraveClient(server.url) as client:
        eid = client.reset(start=FREE, width=64, height=48).episode_id
    ws_url = server.url.replace("http://", "ws://") + f"/episodes/{eid}/ws"
    with connect(ws_url, max_size=None) as ws:
        ws.send(json.dumps({"op": "move", "linear": [0, 0, 0.02], "duration": 0.5, "depth": "none"}))
        r = json.loads(ws.recv(timeout=60))
        assert r["accepted"] and r["adjustments"] == 1
        ws.send(json.dumps({"op": "set_pose", "pose": {"world_T_cam": IN_POST.tolist()}}))
        r = json.loads(ws.recv(timeout=60))
        assert not r["accepted"] and r["refusal"]["reason"] == "collision"
        ws.send(json.dumps({"op": "close"}))
        assert json.loads(ws.recv(timeout=60))["closed"]


def test_limits_over_real_sockets(server: ServerThread) -> None:
    with BraveClient(server.url) as client:
        eid = client.reset(start=FREE, width=64, height=48).episode_id
    r = httpx.post(f"{server.url}/episodes/{eid}/set_pose", content=b"{" + b" " * 200_000 + b"}",
                   headers={"content-type": "application/json"})
    assert r.status_code == 413
    r = httpx.post(f"{server.url}/episodes/{eid}/set_pose", content=b'{"pose": {"world_T_cam": [[NaN]]}}',
                   headers={"content-type": "application/json"})
    assert r.status_code == 422
    # the WebSocket transport refuses frames above the limit (uvicorn's ws_max_size)
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with connect(server.url.replace("http://", "ws://") + f"/episodes/{eid}/ws", max_size=None) as ws:
        ws.send(json.dumps({"op": "get", "pad": "x" * 200_000}))
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=30)
    assert httpx.get(server.url + "/health").json()["status"] == "ok"


def test_load_test_small(server: ServerThread) -> None:
    spec = importlib.util.spec_from_file_location("brave6d_load_test", REPO / "benchmarks" / "load_test.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    result = module.run_load_test(server.url, clients=4, requests=12, width=96, height=72, max_seconds=120)
    assert result["errors"] == 0, result["error_messages"]
    assert result["requests"] == 4 * 12
    lat = result["latency_ms"]
    # percentiles in order, and no request took longer than the whole run
    assert lat["p50"] <= lat["p90"] <= lat["p99"] <= lat["max"] <= result["wall_s"] * 1000.0
    assert result["throughput_rps"] == pytest.approx(result["requests"] / result["wall_s"])


def test_demo_stages_run_one_agent_episode(scene_dir: Path, tmp_path: Path) -> None:
    from brave6d.core.layout import SceneDir
    from brave6d.serve.demo import stage_export, stage_serve

    scene = SceneDir(scene_dir)
    ctx = SimpleNamespace(scene=scene, spec=scene.load_spec(), quick=True, device="cpu", workdir=tmp_path)
    exported = stage_export(ctx)
    assert exported.name == "export" and exported.figures["objects"] == 2
    served = stage_serve(ctx)
    assert served.name == "serve" and served.status == "ok"
    assert served.figures["adjustments"] >= 1 and served.figures["refusals"] == 1
    logs = list((tmp_path / "episodes").glob("*.jsonl"))
    assert len(logs) == 1
    events = [r.event for r in read_episode_log(logs[0])]
    assert events[0] == "reset" and events[-2:] == ["close", "digest"] and "set_pose" in events
    assert served.figures["mode"] == "training"  # the scripted agent steers with the ground truth


def test_scripted_agent_approaches_the_target(server: ServerThread) -> None:
    from brave6d.serve.demo import run_scripted_episode

    with BraveClient(server.url) as client:
        report = run_scripted_episode(client, target="cube_blue", width=160, height=120, seed=11, max_steps=10)
    assert report.refusal_kept_pose and report.refusals == 1
    assert report.final_distance_m < report.start_distance_m
    assert report.final_visib_fract is not None and report.final_visib_fract > 0.5


def test_scene_server_without_open3d_still_serves_poses(bundle: Bundle, monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins

    real_import = builtins.__import__

    def no_open3d(name, *args, **kwargs):  # type: ignore[no-untyped-def]
        if name == "open3d" or name.startswith("open3d."):
            raise ImportError("No module named 'open3d' (simulated)")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_open3d)
    scene = SceneServer(bundle, device="cpu")
    assert scene.visibility is None
    obs = scene.observe(FREE, bundle.camera.scaled(64, 48), 0)
    assert obs.objects[0].visib_fract is None and obs.objects[0].px_count_all is None

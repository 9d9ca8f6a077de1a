"""Hardening of the render server (issue #16): no request answers 500 or leaves counted-but-unlogged
state, whatever its numbers; the Host allow-list, the token and the remote-bind opt-in; one image-size
cap for requests, exports and bundle defaults; malformed WebSocket messages get the error object."""

from __future__ import annotations

import json
import logging
import math
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import event, given
from hypothesis import strategies as st
from starlette.testclient import WebSocketDenialResponse

from brave6d.core.errors import BraveError
from brave6d.core.transforms import look_at
from brave6d.serve.app import ServerLimits, create_app
from brave6d.serve.bundle import Bundle, BundleError, export_bundle, load_bundle
from brave6d.serve import EpisodeLog, SceneServer, read_episode_log
from brave6d.serve.episode_manager import EpisodeManager
from brave6d.serve.episodes import InvalidAction
from brave6d.serve.limits import MAX_HEIGHT, MAX_WIDTH, fit_image_size
from brave6d.serve.toy_scene import make_synthetic_bundle, make_synthetic_scene

FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
IN_POST = look_at((0.30, 0.25, 0.15), (0.46, 0.0, 0.01))
LOCAL = "http://localhost"
WS_LOCAL = "ws://localhost"
TOKEN = "s3cret-token-for-tests-0123"
TINY = {"rgb": "none", "depth": "none"}


def strict_json(text: str) -> Any:
    """``json.loads`` that refuses NaN/Infinity (which are not JSON)."""
    def refuse(name: str) -> None:
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("hardening_scene"), n_gaussians=2000))


@pytest.fixture(scope="module")
def scene(bundle: Bundle) -> SceneServer:
    return SceneServer(bundle, device="cpu")


@pytest.fixture(scope="module")
def log_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("hardening_episodes")


@pytest.fixture(scope="module")
def client(bundle: Bundle, scene: SceneServer, log_dir: Path) -> TestClient:
    app = create_app(bundle, scene=scene, log_dir=log_dir, limits=ServerLimits(max_episodes=1000), warm_up=False)
    with TestClient(app, base_url=LOCAL) as c:
        yield c


def new_episode(client: TestClient) -> str:
    r = client.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, "width": 16, "height": 16, **TINY})
    assert r.status_code == 201, r.text
    return r.json()["episode_id"]


def snapshot(client: TestClient, log_dir: Path, eid: str) -> tuple[list, int, int, int, int]:
    """(pose, adjustments, steps, refusals, log records) of an episode."""
    s = client.get(f"/episodes/{eid}").json()
    return (s["world_T_cam"], s["adjustments"], s["steps"], s["refusals"],
            len(read_episode_log(log_dir / f"{eid}.jsonl")))


def send(client: TestClient, eid: str, op: str, body: dict[str, Any], websocket: bool) -> tuple[int, dict[str, Any]]:
    """(status, reply) of one action sent over HTTP or the WebSocket (NaN/inf as JSON's extensions)."""
    text = json.dumps({**body, **TINY})
    if not websocket:
        r = client.post(f"/episodes/{eid}/{op}", content=text.encode(),
                        headers={"content-type": "application/json"})
        return r.status_code, strict_json(r.text)
    with client.websocket_connect(f"{WS_LOCAL}/episodes/{eid}/ws") as ws:
        ws.send_text(json.dumps({"op": op, **json.loads(text)}))
        reply = strict_json(ws.receive_text())
    return reply.get("status", 200), reply


# ----------------------------------------------------------------------------- item 7: magnitudes
HUGE_ACTIONS = [
    ("move", {"linear": [1e300, 0, 0], "duration": 1.0}, "linear.0"),
    ("move", {"angular": [1e308, 0, 0], "duration": 10.0}, "angular.0"),
    ("move", {"linear": [0, 1e300, 1e300], "duration": 1.0}, "linear.1"),
    ("set_pose", {"pose": {"look_at": {"eye": [1e308, 0, 0], "target": [-1e308, 0, 0]}}}, "pose.look_at.eye.0"),
    ("set_pose", {"pose": {"position": [0.3, 0, 5e3], "quaternion_wxyz": [1, 0, 0, 0]}}, "pose.position.2"),
    ("set_pose", {"pose": {"world_T_cam": [[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}},
     "pose.world_T_cam.0.3"),
]


@pytest.mark.parametrize("websocket", [False, True], ids=["http", "ws"])
@pytest.mark.parametrize("op,body,field", HUGE_ACTIONS, ids=[a[2] for a in HUGE_ACTIONS])
def test_huge_magnitudes_are_422_and_change_nothing(client: TestClient, log_dir: Path, op: str, body: dict,
                                                    field: str, websocket: bool) -> None:
    eid = new_episode(client)
    before = snapshot(client, log_dir, eid)
    status, reply = send(client, eid, op, body, websocket)
    assert status == 422, reply
    assert reply["field"].endswith(field) and field in reply["error"], reply
    assert snapshot(client, log_dir, eid) == before


def test_a_failed_log_write_changes_nothing(scene: SceneServer, tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """The step is one transaction: when the log line cannot be written (disk full), neither the
    counters nor the pose change, for a refusal as for an accepted move."""
    manager = EpisodeManager(scene, tmp_path)
    eid = manager.reset(start=FREE, width=16, height=16).episode_id
    ep = manager.get(eid)

    def disk_full(self: EpisodeLog, line: str) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(EpisodeLog, "append", disk_full)
    with pytest.raises(OSError):
        manager.set_pose(eid, IN_POST)  # refused: would count a refusal
    with pytest.raises(OSError):
        manager.move(eid, [0, 0, 0.02], [0, 0, 0], 0.5)  # accepted: would count an adjustment
    assert (ep.steps, ep.refusals, ep.adjustments) == (0, 0, 0)
    np.testing.assert_array_equal(ep.world_T_cam, FREE)
    monkeypatch.undo()
    manager.set_pose(eid, IN_POST)
    assert [r.event for r in read_episode_log(tmp_path / f"{eid}.jsonl")] == ["reset", "set_pose"]
    assert (ep.steps, ep.refusals) == (1, 1)


def test_the_manager_refuses_non_finite_poses_and_twists(scene: SceneServer, tmp_path: Path) -> None:
    """Callers that bypass the request models get InvalidAction naming the field, and nothing changes."""
    manager = EpisodeManager(scene, tmp_path)
    eid = manager.reset(start=FREE, width=16, height=16).episode_id
    bad_pose = FREE.copy()
    bad_pose[0, 3] = np.nan
    with pytest.raises(InvalidAction) as info:
        manager.set_pose(eid, bad_pose)
    assert info.value.field == "pose"
    for linear, angular, duration, field in [([1e300, 0, 0], [0, 0, 0], 1.0, "linear"),
                                             ([0, 0, 0], [np.inf, 0, 0], 1.0, "angular"),
                                             ([0, 0, 0.1], [0, 0, 0], np.nan, "duration")]:
        with pytest.raises(InvalidAction) as info:
            manager.move(eid, linear, angular, duration)
        assert info.value.field == field
    ep = manager.get(eid)
    assert (ep.steps, ep.refusals, ep.adjustments) == (0, 0, 0)
    assert len(read_episode_log(tmp_path / f"{eid}.jsonl")) == 1


# hypothesis: any numbers, over HTTP and the WebSocket
EXTREMES = [0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1e-160, 1e300, -1e300, 1e308, -1e308,
            1.7976931348623157e308, math.inf, -math.inf, math.nan]


def numbers(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Mostly sensible values in [lo, hi], plus extremes and any float at all."""
    return st.one_of(st.floats(lo, hi), st.floats(lo, hi), st.sampled_from(EXTREMES), st.floats())


def vec(n: st.SearchStrategy[float], size: int = 3) -> st.SearchStrategy[list[float]]:
    return st.lists(n, min_size=size, max_size=size)


MOVES = st.fixed_dictionaries(
    {"duration": numbers(0.0, 2.0)},
    optional={"linear": vec(numbers(-0.1, 0.1)), "angular": vec(numbers(-0.5, 0.5)),
              "frame": st.sampled_from(["camera", "world"])})


def _world_T_cam(entry: tuple[int, int, float]) -> dict[str, Any]:
    T = FREE.tolist()
    T[entry[0]][entry[1]] = entry[2]
    return {"world_T_cam": T}


POSES = st.one_of(
    st.builds(lambda p, q: {"position": p, "quaternion_wxyz": q},
              vec(numbers(0.1, 0.5)), st.one_of(vec(numbers(-1.0, 1.0), 4), st.just([0.0, 1.0, 0.0, 0.0]))),
    st.builds(lambda e, t, u: {"look_at": {"eye": e, "target": t, **({"up": u} if u is not None else {})}},
              vec(numbers(0.1, 0.5)), vec(numbers(0.0, 0.5)), st.none() | vec(numbers(-1.0, 1.0))),
    st.builds(_world_T_cam, st.tuples(st.integers(0, 3), st.integers(0, 3), numbers(-1.0, 1.0))),
)
ACTIONS = st.one_of(st.tuples(st.just("move"), MOVES),
                    st.tuples(st.just("set_pose"), st.builds(lambda p: {"pose": p}, POSES)))


@pytest.fixture(scope="module")
def fuzz_episode(client: TestClient) -> str:
    """The episode all the examples act on (module scope: fixtures are not made per example)."""
    return new_episode(client)


@given(action=ACTIONS, websocket=st.booleans())
def test_random_actions_never_500_and_failures_change_nothing(client: TestClient, log_dir: Path, fuzz_episode: str,
                                                              action: tuple[str, dict], websocket: bool) -> None:
    eid = fuzz_episode
    op, body = action
    before = snapshot(client, log_dir, eid)
    status, reply = send(client, eid, op, body, websocket)
    after = snapshot(client, log_dir, eid)
    event(f"{op} {status}" + (" refused" if status == 200 and not reply["accepted"] else ""))
    assert status in (200, 422), reply
    if status == 422:
        assert isinstance(reply["field"], str) and reply["field"] and reply["error"], reply
        assert after == before
    else:
        assert after[2] == before[2] + 1 and after[4] == before[4] + 1
    assert after[4] == 1 + after[2]  # the log holds the reset and every counted step



# ----------------------------------------------------------------------------- item 12: WebSocket messages
def test_deeply_nested_json_gets_the_error_object(client: TestClient) -> None:
    eid = new_episode(client)
    with client.websocket_connect(f"{WS_LOCAL}/episodes/{eid}/ws") as ws:
        ws.send_text("[" * 5000 + "]" * 5000)
        reply = strict_json(ws.receive_text())
        assert reply["status"] == 400 and reply["field"] == "message" and "nested" in reply["error"]
        ws.send_text('{"op": "get", "request_id": ' + "9" * 5000 + "}")  # an integer too long to parse
        assert strict_json(ws.receive_text())["status"] == 400
        ws.send_text(json.dumps({"op": "get", "request_id": "still-open"}))
        assert strict_json(ws.receive_text())["request_id"] == "still-open"


@pytest.mark.parametrize("request_id", ["NaN", "Infinity", "-Infinity", "1e400", "1.5", "[1]"])
def test_request_ids_are_echoed_only_when_valid_json(client: TestClient, request_id: str) -> None:
    eid = new_episode(client)
    with client.websocket_connect(f"{WS_LOCAL}/episodes/{eid}/ws") as ws:
        ws.send_text('{"op": "get", "request_id": ' + request_id + "}")
        reply = strict_json(ws.receive_text())  # fails on a NaN echoed back
        assert reply["status"] == 422 and reply["field"] == "request_id" and reply["request_id"] is None, reply


def test_http_deeply_nested_json_is_400(client: TestClient) -> None:
    eid = new_episode(client)
    r = client.post(f"/episodes/{eid}/set_pose", content=("[" * 5000 + "]" * 5000).encode(),
                    headers={"content-type": "application/json"})
    assert r.status_code == 400 and set(r.json()) == {"error", "field", "status"}


# ----------------------------------------------------------------------------- item 9: exposure
@pytest.mark.parametrize("host", ["evil.example", "evil.example:8765", "127.0.0.1.evil.example", "[::2]:8765"])
def test_foreign_host_headers_are_refused(client: TestClient, host: str) -> None:
    r = client.get("/health", headers={"host": host})
    assert r.status_code == 400, r.text
    assert client.get("/bundle", headers={"host": host}).status_code == 400
    with pytest.raises(WebSocketDenialResponse) as info:
        with client.websocket_connect(f"ws://{host}/episodes/x/ws"):
            pass
    assert info.value.status_code == 400


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.1:8765", "localhost:1", "LOCALHOST", "[::1]", "[::1]:8765"])
def test_loopback_host_headers_are_served(client: TestClient, host: str) -> None:
    assert client.get("/health", headers={"host": host}).status_code == 200


def test_allowed_hosts_extend_the_list(bundle: Bundle, scene: SceneServer) -> None:
    app = create_app(bundle, scene=scene, warm_up=False, allowed_hosts=["lab-pc.example", "*.cluster.example"])
    with TestClient(app, base_url=LOCAL) as c:
        for host, status in [("lab-pc.example:8765", 200), ("gpu3.cluster.example", 200), ("localhost", 200),
                             ("evil.example", 400)]:
            assert c.get("/health", headers={"host": host}).status_code == status, host


@pytest.fixture(scope="module")
def token_client(bundle: Bundle, scene: SceneServer) -> TestClient:
    with TestClient(create_app(bundle, scene=scene, warm_up=False, token=TOKEN), base_url=LOCAL) as c:
        yield c


def test_token_is_required_over_http(token_client: TestClient) -> None:
    c = token_client
    for headers, params in [({}, {}), ({"Authorization": "Bearer wrong-token-0123456789"}, {}),
                            ({"Authorization": f"Basic {TOKEN}"}, {}), ({}, {"token": TOKEN[:-1]})]:
        r = c.get("/health", headers=headers, params=params)
        assert r.status_code == 401 and r.json()["field"] == "token" and "token" in r.json()["error"], r.text
        assert r.headers["www-authenticate"] == "Bearer"
    assert c.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}}).status_code == 401
    assert c.get("/health", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
    assert c.get("/health", params={"token": TOKEN}).status_code == 200
    r = c.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, "width": 16, "height": 16, **TINY},
               headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 201
    # the viewer's static files and the API docs are public; the viewer then sends the token
    assert c.get("/viewer/").status_code == 200 and c.get("/viewer/viewer.js").status_code == 200
    assert c.get("/openapi.json").status_code == 200
    r = c.get("/", params={"token": TOKEN}, follow_redirects=False)
    assert r.headers["location"] == f"/viewer/?token={TOKEN}"


def test_token_is_required_over_the_websocket(token_client: TestClient) -> None:
    c = token_client
    r = c.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, "width": 16, "height": 16, **TINY},
               headers={"Authorization": f"Bearer {TOKEN}"})
    eid = r.json()["episode_id"]
    for url in [f"{WS_LOCAL}/episodes/{eid}/ws", f"{WS_LOCAL}/episodes/{eid}/ws?token=nope"]:
        with pytest.raises(WebSocketDenialResponse) as info:
            with c.websocket_connect(url):
                pass
        assert info.value.status_code == 401
    with c.websocket_connect(f"{WS_LOCAL}/episodes/{eid}/ws?token={TOKEN}") as ws:
        ws.send_text(json.dumps({"op": "get"}))
        assert ws.receive_json()["episode_id"] == eid
    with c.websocket_connect(f"{WS_LOCAL}/episodes/{eid}/ws", headers={"Authorization": f"Bearer {TOKEN}"}) as ws:
        ws.send_text(json.dumps({"op": "get"}))
        assert ws.receive_json()["episode_id"] == eid


def test_short_tokens_are_refused(bundle: Bundle, scene: SceneServer) -> None:
    with pytest.raises(BraveError, match="at least 16 characters"):
        create_app(bundle, scene=scene, warm_up=False, token="1234")


def test_cli_refuses_a_remote_bind_without_the_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.cli import main

    # (refused before the bundle is read: this one does not even exist)
    for host in ["0.0.0.0", "::", "192.0.2.7", "lab-pc.example"]:
        assert main(["serve", str(tmp_path / "no-bundle"), "--host", host, "--port", "0"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--allow-remote" in err and host in err, err


def test_cli_access_settings() -> None:
    from brave6d.serve.cli import access_for

    loop = access_for("127.0.0.1", False, None, [], environ={})
    assert loop.token is None and loop.allowed_hosts == ()
    assert access_for("127.0.0.1", False, None, [], environ={"BRAVE6D_TOKEN": TOKEN}).token == TOKEN
    remote = access_for("0.0.0.0", True, None, ["lab-pc.example"], environ={})
    assert remote.token_generated and len(remote.token or "") >= 16 and remote.allowed_hosts == ("lab-pc.example",)
    assert access_for("0.0.0.0", True, None, [], environ={}).token != remote.token
    assert access_for("192.0.2.7", True, TOKEN, [], environ={}).allowed_hosts == ("192.0.2.7",)
    v6 = access_for("2001:db8::1", True, None, [], environ={"BRAVE6D_TOKEN": TOKEN})
    assert v6.allowed_hosts == ("[2001:db8::1]",) and v6.token == TOKEN and not v6.token_generated
    with pytest.raises(BraveError, match="at least 16"):
        access_for("0.0.0.0", True, "short", [], environ={})


VIEWER_HARNESS = r"""
// Runs serve/viewer/viewer.js in Node with a minimal fake DOM against a live server and prints
// what the page reached and the Authorization header of each API request it made.
const [viewerPath, base, search] = process.argv.slice(2);
const sent = [];
function fake() {
  const store = { dataset: {}, style: {}, classList: { add() {}, remove() {} } };
  return new Proxy(store, {
    get(t, k) {
      if (k in t) return t[k];
      if (k === "getContext") return () => ctx;
      if (k === "value") return "";
      return () => fake();
    },
    set(t, k, v) { t[k] = v; return true; },
  });
}
const ctx = new Proxy({}, { get: (t, k) => (k === "measureText" ? () => ({ width: 1 }) : () => {}),
                            set: () => true });
const elements = {};
const body = fake();
globalThis.document = { body, getElementById: (id) => (elements[id] ||= fake()), querySelector: () => fake(),
                        createElement: () => fake() };
globalThis.window = { location: { search }, addEventListener() {} };
Object.defineProperty(globalThis, "navigator", { value: { sendBeacon() { return true; } }, configurable: true });
globalThis.Image = class { set src(v) { setTimeout(() => this.onload(), 0); } };
const realFetch = globalThis.fetch;
globalThis.fetch = (path, init) => {
  sent.push({ path, auth: (init.headers || {}).Authorization || null });
  return realFetch(base + path, init);
};
require(viewerPath);
const t0 = Date.now();
(function poll() {
  const state = body.dataset.state;
  if (state === "ready" || state === "error" || Date.now() - t0 > 60000) {
    console.log(JSON.stringify({ state, frames: Number(body.dataset.frames || 0), sent }));
    process.exit(0);
  }
  setTimeout(poll, 50);
})();
"""


@pytest.mark.skipif(shutil.which("node") is None, reason="Node.js not installed")
def test_viewer_sends_the_token(bundle: Bundle, scene: SceneServer, tmp_path: Path) -> None:
    from brave6d.serve.app import VIEWER_DIR
    from brave6d.serve.runner import ServerThread

    harness = tmp_path / "harness.js"
    harness.write_text(VIEWER_HARNESS)

    def open_viewer(base: str, search: str) -> dict[str, Any]:
        out = subprocess.run(["node", str(harness), str(VIEWER_DIR / "viewer.js"), base, search],
                             capture_output=True, text=True, timeout=120, check=True)
        return json.loads(out.stdout.strip().splitlines()[-1])

    app = create_app(bundle, scene=scene, warm_up=False, token=TOKEN, log_dir=tmp_path / "episodes")
    with ServerThread(app) as server:
        page = open_viewer(server.url, f"?token={TOKEN}&seed=3&width=64&height=48")
        assert page["state"] == "ready" and page["frames"] >= 1, page
        assert {s["path"] for s in page["sent"]} >= {"/bundle", "/episodes"}
        assert all(s["auth"] == f"Bearer {TOKEN}" for s in page["sent"]), page["sent"]
        assert open_viewer(server.url, "?seed=3&width=64&height=48")["state"] == "error"


# ----------------------------------------------------------------------------- item 11: one size cap
def test_fit_image_size() -> None:
    assert fit_image_size(320, 240) == (320, 240)
    assert fit_image_size(2048, 1536) == (MAX_WIDTH, MAX_HEIGHT)
    assert fit_image_size(4000, 1000) == (MAX_WIDTH, 320)
    for size in [(8, 240), (100000, 20)]:
        with pytest.raises(ValueError):
            fit_image_size(*size)


def test_export_refuses_a_size_beyond_the_cap(tmp_path: Path) -> None:
    scene = make_synthetic_scene(tmp_path / "scene", n_gaussians=200, n_views=4)
    for width, height in [(2048, 1536), (MAX_WIDTH + 1, None), (None, MAX_HEIGHT + 1), (15, None)]:
        with pytest.raises(BraveError, match=r"render (width|height) must be in 16\.\.(1280|960)"):
            export_bundle(scene.root, tmp_path / "bundle", width=width, height=height)
    assert not (tmp_path / "bundle").exists()


def test_large_camera_defaults_are_fitted_to_the_cap(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A scene shot at 2048x1536 exports (and serves) default views of 1280x960, the largest an
    explicit request may ask for, instead of 2048x1536 replies."""
    scene = make_synthetic_scene(tmp_path / "scene", n_gaussians=200, n_views=4, width=2048, height=1536)
    with caplog.at_level(logging.WARNING, logger="brave6d.serve.bundle"):
        root = export_bundle(scene.root, tmp_path / "bundle").root
    assert "exceed the server's image-size cap" in caplog.text
    b = load_bundle(root)
    assert (b.render.width, b.render.height) == (MAX_WIDTH, MAX_HEIGHT)
    assert (b.camera.width, b.camera.height) == (2048, 1536)  # the intrinsics stay those of the images
    with TestClient(create_app(b, device="cpu", warm_up=False), base_url=LOCAL) as c:
        r = c.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, "depth": "none", "rgb": "none"})
        assert r.status_code == 201, r.text
        obs = r.json()["observation"]
        assert (obs["width"], obs["height"]) == (MAX_WIDTH, MAX_HEIGHT)
        r = c.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, "width": 2048, "height": 1536})
        assert r.status_code == 422 and r.json()["field"] == "body.width"
        limits = c.get("/bundle").json()["limits"]
        assert (limits["max_width"], limits["max_height"]) == (MAX_WIDTH, MAX_HEIGHT)


def test_loaded_defaults_beyond_the_cap_are_fitted_or_refused(bundle: Bundle, tmp_path: Path,
                                                              caplog: pytest.LogCaptureFixture) -> None:
    """A bundle written by an older exporter (render defaults 2048x1536 in scene.json) loads with
    its defaults fitted to the cap; one that cannot be fitted is refused."""
    root = tmp_path / "bundle"
    shutil.copytree(bundle.root, root)
    scene_json = json.loads((root / "scene.json").read_text())
    scene_json["render"].update({"width": 2048, "height": 1536})
    (root / "scene.json").write_text(json.dumps(scene_json))
    with caplog.at_level(logging.WARNING, logger="brave6d.serve.bundle"):
        b = load_bundle(root, verify=False)
    assert (b.render.width, b.render.height) == (MAX_WIDTH, MAX_HEIGHT) and "2048x1536" in caplog.text
    scene_json["render"].update({"width": 100000, "height": 16})
    (root / "scene.json").write_text(json.dumps(scene_json))
    with pytest.raises(BundleError, match="cannot be fitted"):
        load_bundle(root, verify=False)

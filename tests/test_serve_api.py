"""The render server's HTTP/WebSocket API (FastAPI TestClient): observations, refusals,
adjustment counting, ground truth, bad inputs, limits, timeouts, logs."""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from brave6d.core.transforms import check_rigid, invert, look_at
from brave6d.serve.app import ServerLimits, create_app
from brave6d.serve.bundle import Bundle, load_bundle
from brave6d.serve.client import decode_observation
from brave6d.serve import LOG_FORMAT_VERSION, SceneServer, read_episode_log
from brave6d.serve.toy_scene import make_synthetic_bundle

FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
FREE2 = look_at((0.30, 0.10, 0.35), (0.46, 0.0, 0.01))
IN_POST = look_at((0.30, 0.25, 0.15), (0.46, 0.0, 0.01))
BELOW_FLOOR = look_at((0.40, 0.0, 0.01), (0.46, 0.0, 0.0))
LOCAL = "http://localhost"  # the server answers only to loopback Host names by default


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("api_scene"), n_gaussians=8000))


@pytest.fixture(scope="module")
def scene(bundle: Bundle) -> SceneServer:
    return SceneServer(bundle, device="cpu")


@pytest.fixture(scope="module")
def log_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("episodes")


@pytest.fixture(scope="module")
def client(bundle: Bundle, scene: SceneServer, log_dir: Path) -> TestClient:
    with TestClient(create_app(bundle, scene=scene, log_dir=log_dir, limits=ServerLimits(max_episodes=1000),
                               mode="training"),
                    base_url=LOCAL) as c:
        yield c


def reset(client: TestClient, **body: object) -> dict:
    r = client.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, **body})
    assert r.status_code == 201, r.text
    return r.json()


def state(client: TestClient, eid: str) -> dict:
    r = client.get(f"/episodes/{eid}")
    assert r.status_code == 200
    return r.json()


def assert_serving(client: TestClient) -> None:
    assert client.get("/health").json()["status"] == "ok"
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    r = client.post(f"/episodes/{eid}/move", json={"linear": [0, 0, 0.02], "duration": 0.5, "rgb": "none",
                                                  "depth": "none"})
    assert r.status_code == 200 and r.json()["accepted"]
    client.post(f"/episodes/{eid}/close")


# ----------------------------------------------------------------------------- observations
def test_reset_returns_an_observation(client: TestClient, bundle: Bundle) -> None:
    r = client.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, "target": "cube_blue"})
    assert r.status_code == 201
    assert float(r.headers["X-Render-Ms"]) > 0 and "render;dur=" in r.headers["Server-Timing"]
    body = r.json()
    assert body["accepted"] and body["adjustments"] == 0 and body["target"]["name"] == "cube_blue"
    assert body["timings_ms"]["render"] > 0 and body["timings_ms"]["total"] >= body["timings_ms"]["render"]
    obs = decode_observation(body["observation"])
    assert obs.rgb is not None and obs.rgb.shape == (240, 320, 3) and obs.rgb.dtype == np.uint8
    assert obs.depth is not None and obs.depth.shape == (240, 320) and obs.depth.dtype == np.float32
    np.testing.assert_allclose(obs.K, bundle.camera.K)
    np.testing.assert_allclose(obs.world_T_cam, FREE, atol=1e-12)
    check_rigid(obs.world_T_cam)
    # the table fills the view: valid depths between the camera's distance to the table and the far wall
    valid = obs.depth[obs.depth > 0]
    assert valid.size > 0.9 * obs.depth.size
    assert 0.2 < float(np.median(valid)) < 0.8
    assert obs.rgb.std() > 10  # a textured image, not a flat colour
    # both objects, the target flagged, well visible from here
    assert [o.name for o in obs.objects] == ["cube_red", "cube_blue"]
    assert [o.is_target for o in obs.objects] == [False, True]
    for o in obs.objects:
        assert o.visib_fract is not None and o.visib_fract > 0.8 and o.px_count_visib > 50
    # the centre pixel of the blue cube is blue in the render
    t = obs.objects[1].cam_T_obj @ np.array([0, 0, 0.02, 1.0])  # centre of the top face (seen from above)
    u, v = (obs.K @ (t[:3] / t[2]))[:2].round().astype(int)
    r_, g_, b_ = obs.rgb[v, u].astype(int)
    assert b_ > r_ + 60 and b_ > g_ + 40, obs.rgb[v, u]
    # and the depth there is the cube's
    assert abs(float(obs.depth[v, u]) - t[2]) < 0.004


def test_image_size_and_random_starts(client: TestClient, bundle: Bundle) -> None:
    a = client.post("/episodes", json={"seed": 7, "width": 160, "height": 120, "depth": "none"}).json()
    b = client.post("/episodes", json={"seed": 7, "width": 160, "height": 120, "depth": "none"}).json()
    c = client.post("/episodes", json={"seed": 8, "width": 160, "height": 120, "depth": "none"}).json()
    assert a["episode_id"] != b["episode_id"]
    Ta, Tb, Tc = (np.asarray(x["observation"]["world_T_cam"]) for x in (a, b, c))
    np.testing.assert_array_equal(Ta, Tb)
    assert not np.allclose(Ta, Tc)
    obs = decode_observation(a["observation"])
    assert obs.rgb.shape == (120, 160, 3) and obs.depth is None
    np.testing.assert_allclose(obs.K, bundle.camera.scaled(160, 120).K)
    # the random start looks at the target from a free pose
    assert bundle.world.check(Ta) is None
    tgt = obs.target()
    assert tgt is not None and tgt.cam_T_obj[2, 3] > 0.1
    assert state(client, a["episode_id"])["seed"] == 7


def test_ground_truth_in_the_camera_frame(client: TestClient, bundle: Bundle) -> None:
    eid = reset(client)["episode_id"]
    steps = [client.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": FREE2.tolist()}}),
             client.post(f"/episodes/{eid}/move", json={"linear": [0.01, -0.02, 0.05], "angular": [0.1, -0.2, 0.3],
                                                        "duration": 0.7}),
             client.post(f"/episodes/{eid}/move", json={"linear": [0.0, 0.0, 0.03], "angular": [0, 0, 0.5],
                                                        "duration": 0.5, "frame": "world"})]
    for r in steps:
        assert r.status_code == 200 and r.json()["accepted"], r.text
        obs = decode_observation(r.json()["observation"])
        cam_T_world = invert(obs.world_T_cam)
        for o, b in zip(obs.objects, bundle.objects):
            assert (o.gt_id, o.obj_id) == (b.gt_id, b.obj_id)
            np.testing.assert_allclose(o.cam_T_obj, cam_T_world @ b.world_T_obj, atol=1e-9, rtol=0)
            np.testing.assert_allclose(o.cam_t_m2c_mm, 1000.0 * (cam_T_world @ b.world_T_obj)[:3, 3], atol=1e-6)


def test_pose_forms_are_equivalent(client: TestClient) -> None:
    from brave6d.core.transforms import matrix_to_quat_wxyz

    eid = reset(client, rgb="none", depth="none")["episode_id"]
    eye, target = (0.28, -0.12, 0.31), (0.46, 0.0, 0.01)
    T = look_at(eye, target)
    forms = [{"world_T_cam": T.tolist()}, {"look_at": {"eye": list(eye), "target": list(target)}},
             {"position": T[:3, 3].tolist(), "quaternion_wxyz": matrix_to_quat_wxyz(T[:3, :3]).tolist()}]
    for pose in forms:
        r = client.post(f"/episodes/{eid}/set_pose", json={"pose": pose, "rgb": "none", "depth": "none"})
        assert r.status_code == 200, r.text
        np.testing.assert_allclose(r.json()["observation"]["world_T_cam"], T, atol=1e-9)
    rounded = np.round(T, 6)  # six printed digits and a column norm of 1.000001: accepted, projected
    rounded[:3, 0] *= 1.000001
    r = client.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": rounded.tolist()}, "rgb": "none",
                                                       "depth": "none"})
    assert r.status_code == 200, r.text
    got = np.asarray(r.json()["observation"]["world_T_cam"])
    np.testing.assert_allclose(got[:3, :3].T @ got[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(got, T, atol=1e-5)


# ----------------------------------------------------------------------------- refusals and adjustments
def test_collision_refusal_leaves_pose_and_adjustments_unchanged(client: TestClient) -> None:
    start = reset(client)
    eid = start["episode_id"]
    r = client.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": FREE2.tolist()}})
    assert r.json()["accepted"] and r.json()["adjustments"] == 1
    before = state(client, eid)
    r = client.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": IN_POST.tolist()}})
    assert r.status_code == 200
    body = r.json()
    assert not body["accepted"] and body["collided"]
    assert body["refusal"]["reason"] == "collision" and body["refusal"]["box"] == "post"
    assert "post" in body["refusal"]["message"]
    assert body["adjustments"] == 1
    np.testing.assert_array_equal(body["observation"]["world_T_cam"], before["world_T_cam"])
    after = state(client, eid)
    assert after["world_T_cam"] == before["world_T_cam"]
    assert after["adjustments"] == 1 and after["refusals"] == 1 and after["steps"] == before["steps"] + 1
    # out of the workspace: refused too
    r = client.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": BELOW_FLOOR.tolist()}}).json()
    assert not r["accepted"] and r["refusal"]["reason"] == "workspace" and r["adjustments"] == 1
    assert state(client, eid)["world_T_cam"] == before["world_T_cam"]
    # the next accepted move counts again
    r = client.post(f"/episodes/{eid}/move", json={"linear": [0, 0, 0.02], "duration": 0.5}).json()
    assert r["accepted"] and r["adjustments"] == 2


def test_move_stops_at_the_first_collision(client: TestClient, bundle: Bundle) -> None:
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    # straight down in the world frame: the workspace floor (z = 0.02) stops the camera
    r = client.post(f"/episodes/{eid}/move", json={"linear": [0, 0, -0.2], "duration": 5.0, "frame": "world",
                                                  "rgb": "none", "depth": "none"}).json()
    assert r["accepted"] and r["collided"] and r["refusal"]["reason"] == "workspace"
    assert 0 < r["move"]["fraction"] < 1
    z = r["observation"]["world_T_cam"][2][3]
    assert 0.02 <= z < 0.026
    assert r["adjustments"] == 1
    # again: blocked at the first substep -> refused, nothing changes
    before = state(client, eid)
    r = client.post(f"/episodes/{eid}/move", json={"linear": [0, 0, -0.2], "duration": 1.0, "frame": "world",
                                                  "rgb": "none", "depth": "none"}).json()
    assert not r["accepted"] and r["move"]["fraction"] == 0 and r["adjustments"] == 1
    assert state(client, eid)["world_T_cam"] == before["world_T_cam"]
    # towards the post: stops with the sphere clear of it
    start = look_at((0.30, 0.10, 0.15), (0.30, 0.25, 0.15))  # looking at the post, 15 cm away
    eid = reset(client, start={"world_T_cam": start.tolist()}, rgb="none", depth="none")["episode_id"]
    r = client.post(f"/episodes/{eid}/move", json={"linear": [0, 0, 0.1], "duration": 2.0, "rgb": "none",
                                                  "depth": "none"}).json()
    assert r["accepted"] and r["collided"] and r["refusal"]["box"] == "post"
    post = next(b for b in bundle.world.boxes if b.name == "post")
    d = post.distance(np.asarray(r["observation"]["world_T_cam"])[:3, 3])
    assert bundle.world.camera_radius <= d < bundle.world.camera_radius + 0.006


def test_splat_occludes_objects(client: TestClient) -> None:
    # the post stands between this camera and the red cube
    cube, post = np.array([0.45, -0.03, 0.01]), np.array([0.30, 0.25, 0.15])
    eye = cube + 1.6 * (post - cube)
    r = client.post("/episodes", json={"start": {"look_at": {"eye": eye.tolist(), "target": cube.tolist()}},
                                       "rgb": "none", "depth": "none"})
    assert r.status_code == 201, r.text
    red = r.json()["observation"]["objects"][0]
    assert red["name"] == "cube_red" and red["px_count_all"] > 20 and red["visib_fract"] < 0.2, red


# ----------------------------------------------------------------------------- bad inputs
def raw(client: TestClient, path: str, text: str):  # type: ignore[no-untyped-def]
    return client.post(path, content=text.encode(), headers={"content-type": "application/json"})


BAD_POSES = [
    ('{"pose": {"world_T_cam": [[NaN,0,0,0],[0,1,0,0],[0,0,1,0.3],[0,0,0,1]]}}', "finite"),
    ('{"pose": {"position": [0.3, Infinity, 0.3], "quaternion_wxyz": [1,0,0,0]}}', "finite"),
    ('{"pose": {"position": [0.3, 0, 0.3], "quaternion_wxyz": [1e400,0,0,0]}}', "finite"),
    ('{"pose": {"world_T_cam": [[2,0,0,0.3],[0,1,0,0],[0,0,1,0.3],[0,0,0,1]]}}', "not orthonormal"),
    ('{"pose": {"world_T_cam": [[1,0.2,0,0.3],[0,1,0,0],[0,0,1,0.3],[0,0,0,1]]}}', "not orthonormal"),
    ('{"pose": {"world_T_cam": [[-1,0,0,0.3],[0,1,0,0],[0,0,1,0.3],[0,0,0,1]]}}', "reflection"),
    ('{"pose": {"world_T_cam": [[1,0,0,0.3],[0,1,0,0],[0,0,1,0.3],[0,0,1,1]]}}', "bottom row"),
    ('{"pose": {"world_T_cam": [[1,0,0],[0,1,0],[0,0,1]]}}', "at least 4"),
    ('{"pose": {"position": [0.3, 0, 0.3], "quaternion_wxyz": [2,0,0,0]}}', "unit quaternion"),
    ('{"pose": {"position": [0.3, 0, 0.3], "quaternion_wxyz": [0,0,0,0]}}', "unit quaternion"),
    ('{"pose": {"position": [0.3, 0, 0.3]}}', "go together"),
    ('{"pose": {}}', "exactly one"),
    ('{"pose": {"look_at": {"eye": [0.3,0,0.3], "target": [0.3,0,0.3]}}}', "coincide"),
    ('{"pose": {"world_T_cam": "identity"}}', "list"),
    ('{"pose": {"world_T_cam": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}, "colour": 1}', "Extra inputs"),
    ('{"pose": ', "malformed JSON"),
    ('not json at all', "malformed JSON"),
    ('', "malformed JSON"),
    ('[]', "valid dictionary"),
]


@pytest.mark.parametrize("text,message", BAD_POSES)
def test_bad_poses_are_4xx_with_a_clear_message(client: TestClient, text: str, message: str) -> None:
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    r = raw(client, f"/episodes/{eid}/set_pose", text)
    assert 400 <= r.status_code < 500, r.text
    body = r.json()
    assert set(body) == {"error", "field", "status"} and body["status"] == r.status_code
    assert message.lower() in body["error"].lower(), body
    assert state(client, eid)["adjustments"] == 0
    assert_serving(client)


BAD_RESETS = [
    ({"width": 100000, "height": 240}, "width"), ({"width": 0}, "width"), ({"height": -5}, "height"),
    ({"width": 15}, "width"), ({"height": 961}, "height"), ({"width": "big"}, "width"),
    ({"width": 320.5}, "width"), ({"target": "nothing"}, "no object named"), ({"target": 99}, "gt_id 99"),
    ({"seed": -1}, "seed"), ({"start": {"world_T_cam": IN_POST.tolist()}}, "start: refused"),
    ({"rgb": "bmp"}, "rgb"), ({"depth": "u16"}, "depth"),
]


@pytest.mark.parametrize("body,message", BAD_RESETS)
def test_bad_resets_are_4xx(client: TestClient, body: dict, message: str) -> None:
    r = client.post("/episodes", json=body)
    assert 400 <= r.status_code < 500, r.text
    assert message in r.json()["error"], r.json()
    assert_serving(client)


BAD_MOVES = [
    ({"linear": [0, 0, 0.1]}, "duration"), ({"linear": [0, 0, 0.1], "duration": 0}, "duration"),
    ({"linear": [0, 0, 0.1], "duration": -1}, "duration"), ({"linear": [0, 0, 0.1], "duration": 11}, "duration"),
    ({"linear": [0, 0], "duration": 1}, "linear"), ({"duration": 1}, "does nothing"),
    ({"linear": [0, 0, 0.1], "duration": 1, "frame": "tool"}, "frame"),
    ({"linear": [10, 10, 10], "duration": 10}, "too long"), ({"linear": [0, 0, 11], "duration": 1}, "linear.2"),
]


@pytest.mark.parametrize("body,message", BAD_MOVES)
def test_bad_moves_are_4xx(client: TestClient, body: dict, message: str) -> None:
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    r = client.post(f"/episodes/{eid}/move", json=body)
    assert 400 <= r.status_code < 500, r.text
    assert message in r.json()["error"], r.json()
    assert state(client, eid)["adjustments"] == 0


def test_nan_duration_is_refused(client: TestClient) -> None:
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    r = raw(client, f"/episodes/{eid}/move", '{"linear": [0, 0, 0.1], "duration": NaN}')
    assert r.status_code == 422 and "finite" in r.json()["error"]


def test_unknown_and_closed_episodes(client: TestClient) -> None:
    move = {"linear": [0, 0, 0.1], "duration": 1}
    for method, path, body in [("POST", "/episodes/nope/set_pose", {"pose": {"world_T_cam": FREE.tolist()}}),
                               ("POST", "/episodes/nope/move", move), ("GET", "/episodes/nope", None),
                               ("POST", "/episodes/nope/close", None), ("GET", "/episodes/nope/observation.npz", None)]:
        r = client.request(method, path, json=body)
        assert r.status_code == 404 and "unknown episode 'nope'" in r.json()["error"], (path, r.text)
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    summary = client.post(f"/episodes/{eid}/close").json()
    assert summary["closed"] and summary["adjustments"] == 0
    r = client.post(f"/episodes/{eid}/move", json=move)
    assert r.status_code == 409 and "closed" in r.json()["error"]
    assert client.post(f"/episodes/{eid}/close").status_code == 409
    assert state(client, eid)["closed"] is True
    assert client.get("/no/such/thing").status_code == 404
    assert client.put("/episodes").status_code == 405
    assert_serving(client)


def test_request_body_limit(client: TestClient) -> None:
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    big = '{"pose": {"world_T_cam": ' + json.dumps(FREE.tolist()) + '}, "pad": "' + "x" * 70_000 + '"}'
    r = raw(client, f"/episodes/{eid}/set_pose", big)
    assert r.status_code == 413 and "larger than" in r.json()["error"]

    def chunks():  # no Content-Length: the limit applies to the bytes received
        for _ in range(20):
            yield b" " * 8192

    r = client.post(f"/episodes/{eid}/set_pose", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert_serving(client)


def test_too_many_episodes(bundle: Bundle, scene: SceneServer) -> None:
    with TestClient(create_app(bundle, scene=scene, limits=ServerLimits(max_episodes=2), warm_up=False),
                    base_url=LOCAL) as c:
        ids = [reset(c, rgb="none", depth="none")["episode_id"] for _ in range(2)]
        r = c.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}})
        assert r.status_code == 429 and "too many open episodes" in r.json()["error"]
        c.post(f"/episodes/{ids[0]}/close")
        assert c.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}}).status_code == 201


class SlowRenderer:
    """Wraps a renderer and sleeps before each render (to trigger request timeouts)."""

    def __init__(self, inner, delay: float) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.delay = inner, delay

    def __getattr__(self, name: str):  # type: ignore[no-untyped-def]
        return getattr(self.inner, name)

    def render(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        time.sleep(self.delay)
        return self.inner.render(*args, **kwargs)


@pytest.mark.slow
def test_timed_out_actions_are_withdrawn(bundle: Bundle, scene: SceneServer) -> None:
    slow = SceneServer(bundle, renderer=SlowRenderer(scene.renderer, 0.0))
    limits = ServerLimits(request_timeout_s=1.0)
    with TestClient(create_app(bundle, scene=slow, limits=limits, warm_up=False), base_url=LOCAL) as c:
        eid = reset(c, rgb="none", depth="none", width=16, height=16)["episode_id"]
        slow.renderer.delay = 2.0
        r = c.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": FREE2.tolist()}})
        assert r.status_code == 504 and "withdrawn" in r.json()["error"]
        time.sleep(2.0)  # let the render finish: it must not be committed
        st = state(c, eid)
        np.testing.assert_allclose(st["world_T_cam"], FREE, atol=1e-12)
        assert st["adjustments"] == 0 and st["steps"] == 0
        r = c.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}})
        assert r.status_code == 504
        time.sleep(2.0)
        assert len([e for e in c.get("/episodes").json()["episodes"] if not e["closed"]]) == 1
        slow.renderer.delay = 0.0
        r = c.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": FREE2.tolist()}})
        assert r.status_code == 200 and r.json()["adjustments"] == 1


# ----------------------------------------------------------------------------- other endpoints
def test_npz_bundle_models_openapi_viewer(client: TestClient, bundle: Bundle) -> None:
    body = reset(client)
    eid = body["episode_id"]
    r = client.get(f"/episodes/{eid}/observation.npz")
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    with np.load(io.BytesIO(r.content)) as npz:
        obs = decode_observation(body["observation"])
        assert npz["depth"].dtype == np.float32
        np.testing.assert_array_equal(npz["depth"], obs.depth)
        np.testing.assert_allclose(npz["cam_T_obj"][1], obs.objects[1].cam_T_obj)
        assert npz["rgb"].shape == (240, 320, 3)
        np.testing.assert_array_equal(npz["obj_id"], [1, 2])
    b = client.get("/bundle").json()
    assert b["name"] == bundle.name and len(b["objects"]) == 2 and b["collision"]["camera_radius"] == 0.02
    assert b["limits"]["max_width"] == 1280 and b["versions"]["numpy"]
    model = client.get("/bundle/models/2")
    assert model.status_code == 200 and model.content.startswith(b"ply")
    assert client.get("/bundle/models/7").status_code == 404
    schema = client.get("/openapi.json").json()
    for path in ("/episodes", "/episodes/{episode_id}/set_pose", "/episodes/{episode_id}/move",
                 "/episodes/{episode_id}/close", "/health", "/bundle"):
        assert path in schema["paths"], path
    assert "PoseIn" in schema["components"]["schemas"]
    page = client.get("/viewer/")
    assert page.status_code == 200 and "viewer.js" in page.text
    assert client.get("/", follow_redirects=False).status_code in (302, 307)


def test_websocket_actions(client: TestClient) -> None:
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    with client.websocket_connect(f"ws://localhost/episodes/{eid}/ws") as ws:
        ws.send_text(json.dumps({"op": "set_pose", "pose": {"world_T_cam": FREE2.tolist()}, "request_id": 1}))
        r = ws.receive_json()
        assert r["accepted"] and r["adjustments"] == 1 and r["request_id"] == 1
        assert r["observation"]["rgb"]["encoding"] == "png"
        ws.send_text(json.dumps({"op": "move", "linear": [0, 0, 0.02], "duration": 0.5, "rgb": "none", "depth": "none"}))
        r = ws.receive_json()
        assert r["accepted"] and r["adjustments"] == 2 and r["observation"]["rgb"] is None
        ws.send_text(json.dumps({"op": "set_pose", "pose": {"world_T_cam": IN_POST.tolist()}, "rgb": "none"}))
        r = ws.receive_json()
        assert not r["accepted"] and r["refusal"]["box"] == "post" and r["adjustments"] == 2
        ws.send_text("{not json")
        assert ws.receive_json()["status"] == 400
        ws.send_text(json.dumps({"op": "move", "linear": [0, 0, "NaN"], "duration": 1}))
        assert ws.receive_json()["status"] == 422
        ws.send_text(json.dumps({"op": "fly"}))
        assert ws.receive_json()["status"] == 422
        ws.send_text(json.dumps({"op": "move", "linear": [0, 0, 0.1]}))
        assert "duration" in ws.receive_json()["error"]
        ws.send_text(json.dumps({"op": "set_pose", "pad": "x" * 70_000}))
        assert ws.receive_json()["status"] == 413
        ws.send_text(json.dumps({"op": "get"}))
        r = ws.receive_json()
        assert r["adjustments"] == 2 and r["refusals"] == 1
        ws.send_text(json.dumps({"op": "close"}))
        assert ws.receive_json()["closed"] is True
    with client.websocket_connect("ws://localhost/episodes/nope/ws") as ws:
        assert ws.receive_json()["status"] == 404


def test_episode_log(client: TestClient, log_dir: Path) -> None:
    eid = reset(client, rgb="none", depth="none")["episode_id"]
    client.post(f"/episodes/{eid}/set_pose", json={"pose": {"world_T_cam": IN_POST.tolist()}})
    client.post(f"/episodes/{eid}/move", json={"linear": [0, 0, 0.02], "duration": 0.5})
    client.post(f"/episodes/{eid}/close")
    records = read_episode_log(log_dir / f"{eid}.jsonl")
    assert [r.event for r in records] == ["reset", "set_pose", "move", "close", "digest"]  # digest: the signature
    reset_rec, refused, moved, closed, _ = records
    assert reset_rec.format_version == LOG_FORMAT_VERSION and reset_rec.scene == "synthetic_tabletop" and reset_rec.scene_id is None
    assert reset_rec.mode == "training"
    assert reset_rec.target.name == "cube_red" and reset_rec.width == 320
    np.testing.assert_allclose(reset_rec.world_T_cam, FREE)
    assert refused.accepted is False and refused.refusal["box"] == "post"
    np.testing.assert_array_equal(refused.world_T_cam, refused.world_T_cam_before)
    assert refused.adjustments == 0
    assert moved.accepted and moved.adjustments == 1 and moved.timings_ms["render"] > 0
    assert not np.array_equal(moved.world_T_cam, moved.world_T_cam_before) and moved.target_cam_T_obj is not None
    assert closed.adjustments == 1 and closed.refusals == 1 and closed.steps == 2
    assert all(r.time.startswith("20") for r in records)

"""Free viewing (issue #47): ``POST /render`` draws the splat at a pose without an episode, on a
bundle without objects (an imported capture nobody annotated), under the same limits as episodes;
the Python client's ``render`` and the viewer's free view use it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import event, given, settings
from hypothesis import strategies as st

from brave6d.core.transforms import look_at, matrix_to_quat_wxyz
from brave6d.serve.app import ServerLimits, create_app
from brave6d.serve.bundle import Bundle, load_bundle
from brave6d.serve.client import BraveClient, ServerError, decode_observation
from brave6d.serve.renderer import SplatRenderer
from brave6d.serve.runner import ServerThread
from brave6d.serve.toy_scene import TARGET, make_synthetic_bundle
from brave6d.serve import SceneServer
from test_serve_api import BAD_POSES, SlowRenderer
from test_serve_hardening import POSES

LOCAL = "http://localhost"
FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
IN_POST = look_at((0.30, 0.25, 0.15), (0.46, 0.0, 0.01))
VIEWER = Path(__file__).resolve().parents[1] / "src" / "brave6d" / "serve" / "viewer"


@pytest.fixture(scope="module")
def bare(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    """A bundle without objects (the toy scene exported with an empty annotation, as an import is)."""
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("bare"), n_gaussians=6000, objects=False))


@pytest.fixture(scope="module")
def client(bare: Bundle) -> TestClient:
    with TestClient(create_app(bare, scene=SceneServer(bare, device="cpu")), base_url=LOCAL) as c:
        yield c


def render(client: TestClient, pose: dict, **body: object):  # type: ignore[no-untyped-def]
    return client.post("/render", json={"pose": pose, **body})


def test_a_bundle_without_objects_renders_what_the_renderer_draws(client: TestClient, bare: Bundle) -> None:
    assert not bare.objects
    r = render(client, {"world_T_cam": FREE.tolist()}, width=200, height=150)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["scene"] == bare.name and body["observation"]["objects"] == []  # no ground truth leaves
    assert float(r.headers["X-Render-Ms"]) >= 0.0
    obs = decode_observation(body["observation"])
    assert obs.rgb.shape == (150, 200, 3) and obs.depth.shape == (150, 200)
    assert obs.rgb.std() > 10.0 and np.ptp(obs.depth) > 0.0  # a real view, not a constant image
    camera = bare.camera.scaled(200, 150)
    np.testing.assert_allclose(obs.K, camera.K)
    d = bare.render
    own = SplatRenderer(bare.splat_path, "cpu", antialiasing=d.antialiasing).render(
        FREE, camera, near=d.near, far=d.far, background=d.background, depth_alpha_min=d.depth_alpha_min,
        depth_mode=d.depth_mode)
    np.testing.assert_array_equal(obs.rgb, own.rgb)  # png: lossless
    np.testing.assert_array_equal(obs.depth, own.depth)


def test_episodes_on_it_say_how_to_look_at_it(client: TestClient) -> None:
    r = client.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}})
    assert r.status_code == 422 and r.json()["field"] == "target" and "POST /render" in r.json()["error"]


def test_the_three_pose_forms_give_the_same_view(client: TestClient) -> None:
    forms = [{"world_T_cam": FREE.tolist()},
             {"position": FREE[:3, 3].tolist(), "quaternion_wxyz": matrix_to_quat_wxyz(FREE[:3, :3]).tolist()},
             {"look_at": {"eye": [0.25, -0.15, 0.30], "target": [0.46, 0.0, 0.01]}}]
    views = [decode_observation(render(client, f, width=64, height=48, depth="none").json()["observation"])
             for f in forms]
    for v in views[1:]:
        assert np.abs(v.rgb.astype(int) - views[0].rgb.astype(int)).max() <= 2
    assert views[0].depth is None  # the observation options are an episode's


SHEARED = FREE.copy()
SHEARED[0, 1] += 0.2


@pytest.mark.parametrize("pose, field, words", [
    ('{"world_T_cam": ' + json.dumps(FREE.tolist()).replace("0.0,", "NaN,", 1) + "}", "pose", "finite"),
    ('{"position": [0.3, 0, 0.3], "quaternion_wxyz": [1, 0, 0, 0.1]}', "pose", "not a unit quaternion"),
    ('{"world_T_cam": ' + json.dumps(SHEARED.tolist()) + "}", "pose", "not a rigid transform"),
    ('{"world_T_cam": ' + json.dumps(IN_POST.tolist()) + "}", "pose", "collide with box 'post'"),
    ('{"look_at": {"eye": [3, 0, 0.3], "target": [0.46, 0, 0]}}', "pose", "outside the workspace"),
])
def test_bad_poses_are_422_naming_the_field(client: TestClient, pose: str, field: str, words: str) -> None:
    r = client.post("/render", content=f'{{"pose": {pose}}}', headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    assert field in r.json()["field"] and words in r.json()["error"], r.json()


@pytest.mark.parametrize("size", [{"width": 5000}, {"height": 961}, {"width": 8}])
def test_image_sizes_beyond_the_cap_are_refused_as_resets_are(client: TestClient, size: dict) -> None:
    free = render(client, {"world_T_cam": FREE.tolist()}, **size)
    reset = client.post("/episodes", json={"start": {"world_T_cam": FREE.tolist()}, **size})
    assert free.status_code == reset.status_code == 422
    assert free.json()["field"] == reset.json()["field"] == f"body.{next(iter(size))}"


def test_body_limit_and_unknown_scene(bare: Bundle) -> None:
    app = create_app(bare, scene=SceneServer(bare, device="cpu"), limits=ServerLimits(max_body_bytes=2048))
    with TestClient(app, base_url=LOCAL) as c:
        big = {"pose": {"world_T_cam": FREE.tolist()}, "scene": "x" * 4000}
        assert c.post("/render", json=big).status_code == 413
        r = render(c, {"world_T_cam": FREE.tolist()}, scene="elsewhere")
        assert r.status_code == 404 and r.json()["field"] == "scene"


def test_a_render_past_the_request_timeout_is_504(bare: Bundle) -> None:
    scene = SceneServer(bare, device="cpu")
    scene.renderer = SlowRenderer(scene.renderer, 1.0)  # type: ignore[assignment]
    app = create_app(bare, scene=scene, warm_up=False, limits=ServerLimits(request_timeout_s=0.2))
    with TestClient(app, base_url=LOCAL) as c:
        r = render(c, {"world_T_cam": FREE.tolist()}, width=32, height=24)
        assert r.status_code == 504 and "withdrawn" in r.json()["error"]


def test_the_python_client_renders_a_free_view(bare: Bundle) -> None:
    app = create_app(bare, scene=SceneServer(bare, device="cpu"))
    with ServerThread(app) as server, BraveClient(server.url) as client:
        view = client.render(FREE, width=96, height=72)
        assert view.rgb.shape == (72, 96, 3) and view.rgb.std() > 10.0 and view.objects == []
        np.testing.assert_allclose(view.world_T_cam, FREE, atol=1e-9)
        assert client.episode_id is None  # no episode was made
        looked = client.render({"look_at": {"eye": [0.25, -0.15, 0.30], "target": list(TARGET)}}, width=96, height=72)
        assert looked.rgb.shape == (72, 96, 3)
        with pytest.raises(ServerError) as info:
            client.render(IN_POST)
        assert info.value.status == 422 and info.value.field == "pose"


def test_the_viewer_has_a_free_view_that_asks_post_render() -> None:
    js = (VIEWER / "viewer.js").read_text(encoding="utf-8")
    html = (VIEWER / "index.html").read_text(encoding="utf-8")
    assert 'api("POST", "/render"' in js and "startFree" in js
    assert 'id="free"' in html


@settings(max_examples=40, deadline=None)
@given(pose=POSES)
def test_any_pose_gives_a_finite_image_or_a_422(client: TestClient, pose: dict) -> None:
    r = client.post("/render", content=json.dumps({"pose": pose, "width": 16, "height": 16}),
                    headers={"Content-Type": "application/json"})
    event(str(r.status_code))
    assert r.status_code in (200, 422), r.text
    if r.status_code == 422:
        assert r.json()["field"] and r.json()["error"]
        return
    obs = decode_observation(r.json()["observation"])
    assert obs.rgb.shape == (16, 16, 3) and np.all(np.isfinite(obs.depth))
    assert all(math.isfinite(v) for row in r.json()["observation"]["world_T_cam"] for v in row)


@pytest.mark.parametrize("text,message", BAD_POSES)
def test_bad_bodies_get_the_set_pose_answers(client: TestClient, text: str, message: str) -> None:
    r = client.post("/render", content=text.encode(), headers={"content-type": "application/json"})
    assert 400 <= r.status_code < 500, r.text
    body = r.json()
    assert set(body) == {"error", "field", "status"} and message.lower() in body["error"].lower(), body


@pytest.mark.slow
def test_an_imported_capture_trained_and_exported_serves_free_views(tmp_path: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    """The acceptance on a real capture: the skull imported (no objects), trained briefly, exported;
    the server renders it over HTTP at a held-out camera, refuses episodes naming POST /render, and its
    load warning no longer advises exporting again."""
    from brave6d.core.layout import SceneDir
    from brave6d.serve.bundle import export_bundle
    from brave6d.training import get_preset, import_capture, train_scene
    from test_import_real import MODEL, options

    import_capture(MODEL, tmp_path / "scene", options(downscale=4))
    scene = SceneDir(tmp_path / "scene")
    preset = get_preset("fast").with_overrides(steps=30, coarse_steps=0, downscale=1, refine_start=10,
                                               refine_every=10, refine_stop=20, max_init_points=2000,
                                               checkpoint_every=30, curve_every=10, depth_lambda=0.0)
    train_scene(scene, preset, device="cpu", init_method="imported", show_progress=False)
    bundle = load_bundle(export_bundle(scene.root).root)
    assert not bundle.objects and bundle.holdout
    pose = bundle.holdout[0].world_T_cam
    with caplog.at_level("WARNING"), TestClient(create_app(bundle, device="cpu"), base_url=LOCAL) as c:
        r = render(c, {"world_T_cam": pose.tolist()}, width=120, height=80)
        assert r.status_code == 200, r.text
        obs = decode_observation(r.json()["observation"])
        assert obs.rgb.shape == (80, 120, 3) and obs.rgb.std() > 5.0
        d = bundle.render
        own = SplatRenderer(bundle.splat_path, "cpu", antialiasing=d.antialiasing).render(
            pose, bundle.camera.scaled(120, 80), near=d.near, far=d.far, background=d.background,
            depth_alpha_min=d.depth_alpha_min, depth_mode=d.depth_mode)
        np.testing.assert_array_equal(obs.rgb, own.rgb)
        episode = c.post("/episodes", json={})
        assert episode.status_code == 422 and "POST /render" in episode.json()["error"]
    warning = next(m.getMessage() for m in caplog.records if m.name == "brave6d.serve.reference")
    assert "POST /render" in warning and "export the bundle again" not in warning

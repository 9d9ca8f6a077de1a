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

from brave6d.errors import BraveError
from brave6d.transforms import look_at
from serve.app import ServerLimits, create_app
from serve.bundle import Bundle, BundleError, export_bundle, load_bundle
from serve.episodes import EpisodeLog, EpisodeManager, InvalidAction, SceneServer, read_episode_log
from serve.limits import MAX_HEIGHT, MAX_WIDTH, fit_image_size
from serve.synthetic import make_synthetic_bundle, make_synthetic_scene

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
    with caplog.at_level(logging.WARNING, logger="serve.bundle"):
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
    with caplog.at_level(logging.WARNING, logger="serve.bundle"):
        b = load_bundle(root, verify=False)
    assert (b.render.width, b.render.height) == (MAX_WIDTH, MAX_HEIGHT) and "2048x1536" in caplog.text
    scene_json["render"].update({"width": 100000, "height": 16})
    (root / "scene.json").write_text(json.dumps(scene_json))
    with pytest.raises(BundleError, match="cannot be fitted"):
        load_bundle(root, verify=False)

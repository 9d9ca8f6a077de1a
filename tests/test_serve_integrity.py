"""A scene whose files fail their checks is the server's problem, not the client's (issue #32
item 9): the catalog remakes the bundle folder from its source once (``SceneSource.refresh``: a
release re-unpacks its verified zip) and loads again; when that cannot repair it, or the source
has no refresh, or locating / unpacking the scene fails (a release error, a full disk), the reset
gets 503 with a message naming the scene and the cause (never 422), and the server keeps serving."""

from __future__ import annotations

import errno
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from brave6d.core.errors import BraveError
from brave6d.core.transforms import look_at
from brave6d.serve import SceneCatalog, SceneSource, bundle_scene_source, create_app, make_synthetic_bundle

FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01)).tolist()
RESET = {"scene": "s", "start": {"world_T_cam": FREE}, "width": 16, "height": 16, "rgb": "none", "depth": "none"}


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_synthetic_bundle(tmp_path_factory.mktemp("integrity_scene"), n_gaussians=500, n_views=4)


def tampered(pristine: Path, folder: Path, victim: str = "objects.json") -> Path:
    """A copy of the bundle at ``folder`` with one bit of ``victim`` flipped (its checksum fails)."""
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(pristine, folder)
    data = bytearray((folder / victim).read_bytes())
    data[len(data) // 2] ^= 0x01
    (folder / victim).write_bytes(bytes(data))
    return folder


def serve(pristine: Path, tmp_path: Path, locate: Callable[[], Path],
          refresh: Callable[[], Path] | None = None) -> TestClient:
    """A TestClient of a server of one scene ``s`` (and a pristine scene ``ok`` beside it)."""
    base = bundle_scene_source(pristine)
    sources = [SceneSource("s", 1, base.objects, base.memory_bytes, locate, "test scene s", refresh),
               SceneSource("ok", 2, base.objects, base.memory_bytes, base.locate, "pristine scene")]
    app = create_app(SceneCatalog(sources, device="cpu", warm_up=False), log_dir=tmp_path / "episodes")
    return TestClient(app, base_url="http://localhost")


def server_error(r: Any, *words: str) -> None:
    """``r`` is a 503 whose JSON error names the scene and ``words``."""
    body = r.json()
    assert r.status_code == 503 and body["status"] == 503 and body["field"] == "scene", (r.status_code, body)
    assert "'s'" in body["error"] and all(w in body["error"] for w in words), body


def still_serving(c: TestClient) -> None:
    assert c.get("/health").status_code == 200
    assert c.post("/episodes", json={**RESET, "scene": "ok"}).status_code == 201


def test_a_tampered_cache_is_remade_once_and_served(pristine: Path, tmp_path: Path) -> None:
    cache = tampered(pristine, tmp_path / "cache")
    calls: list[int] = []

    def refresh() -> Path:  # what the release unpacker does: unpack the verified zip again
        calls.append(1)
        shutil.rmtree(cache)
        shutil.copytree(pristine, cache)
        return cache

    with serve(pristine, tmp_path, lambda: cache, refresh) as c:
        r = c.post("/episodes", json=RESET)
        assert r.status_code == 201, r.text
        assert calls == [1]
        assert c.post("/episodes", json=RESET).status_code == 201 and calls == [1]


@pytest.mark.parametrize("victim", ["objects.json", "splat.ply"])
def test_a_tampered_scene_that_cannot_be_remade_is_a_server_error(pristine: Path, tmp_path: Path,
                                                                  victim: str) -> None:
    cache = tampered(pristine, tmp_path / "cache", victim)
    with serve(pristine, tmp_path, lambda: cache) as c:
        for _ in range(2):  # every reset, not only the first
            server_error(c.post("/episodes", json=RESET), victim, "sha256")
        server_error(c.get("/bundle", params={"scene": "s"}), victim)
        still_serving(c)


def test_a_refresh_that_does_not_repair_is_a_server_error(pristine: Path, tmp_path: Path) -> None:
    cache = tampered(pristine, tmp_path / "cache")
    calls: list[int] = []

    def refresh() -> Path:
        calls.append(1)
        return tampered(pristine, cache)

    with serve(pristine, tmp_path, lambda: cache, refresh) as c:
        server_error(c.post("/episodes", json=RESET), "objects.json", "sha256", "remade")
        assert calls == [1]
        still_serving(c)


def _full_disk() -> Path:
    raise OSError(errno.ENOSPC, "No space left on device", "/cache/demo/bundles/000001")


def _bad_release() -> Path:
    raise BraveError("release.zip: sha256 0123... does not match SHA256SUMS; the release was modified")


@pytest.mark.parametrize("locate,words", [(_full_disk, ("No space left on device", "/cache/demo/bundles/000001")),
                                          (_bad_release, ("release.zip", "does not match SHA256SUMS"))],
                         ids=["enospc", "release-error"])
def test_a_scene_that_cannot_be_located_is_a_server_error(pristine: Path, tmp_path: Path,
                                                          locate: Callable[[], Path], words: tuple[str, ...]) -> None:
    with serve(pristine, tmp_path, locate) as c:
        server_error(c.post("/episodes", json=RESET), *words)
        still_serving(c)

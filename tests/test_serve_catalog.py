"""The scene catalog behind a multi-scene server: scenes load on first use, stay while episodes are
open on them, are evicted least-recently-used first within the bound, and a load that cannot fit is
refused with 503 naming the scenes that hold the memory; the same through HTTP (``/scenes``,
``reset`` naming the scene)."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brave6d.core.errors import BraveError
from brave6d.core.transforms import look_at
from brave6d.serve import (
    EpisodeManager,
    SceneCacheFull,
    SceneCatalog,
    SceneObject,
    SceneServer,
    SceneSource,
    bundle_scene_source,
    create_app,
    load_bundle,
    make_synthetic_bundle,
    open_scenes,
)
from brave6d.serve.episodes import EpisodeNotFound, InvalidAction

FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01)).tolist()
MB = 2**20


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_synthetic_bundle(tmp_path_factory.mktemp("catalog_scene"), n_gaussians=3000)


def sources(bundle_dir: Path, names: str = "abc", mb: int = 100) -> list[SceneSource]:
    """Scenes ``names`` served from one bundle folder (each loads its own renderer), ``mb`` MB each."""
    base = bundle_scene_source(bundle_dir)
    return [SceneSource(n, i + 1, base.objects, mb * MB, base.locate, f"test scene {n}") for i, n in enumerate(names)]


def reset(manager: EpisodeManager, scene: str | int | None) -> str:
    import numpy as np

    return manager.reset(scene=scene, start=np.array(FREE), width=64, height=48).episode_id


def test_scenes_load_on_first_use_and_lru_eviction(bundle_dir: Path, tmp_path: Path) -> None:
    catalog = SceneCatalog(sources(bundle_dir), device="cpu", max_loaded=2, warm_up=False)
    manager = EpisodeManager(catalog, tmp_path)
    assert catalog.loaded_names() == []
    for name in ("a", "b", "a", "c"):
        manager.close(reset(manager, name))
    # a was used after b, so b (least recently used) made room for c
    assert sorted(catalog.loaded_names()) == ["a", "c"]
    assert catalog.stats.loads == 3 and catalog.stats.evictions == 1
    described = {s["name"]: s for s in catalog.describe()["scenes"]}
    assert described["b"]["loaded"] is False and described["c"]["gaussians"] > 0
    assert described["a"]["load_s"] > 0 and described["a"]["objects"][0]["obj_id"] == 1


def test_open_episodes_pin_their_scene(bundle_dir: Path, tmp_path: Path) -> None:
    catalog = SceneCatalog(sources(bundle_dir), device="cpu", memory_budget_bytes=250 * MB, warm_up=False)
    manager = EpisodeManager(catalog, tmp_path)
    ea, eb = reset(manager, "a"), reset(manager, 2)  # by name and by scene_id
    with pytest.raises(SceneCacheFull, match=r"'c'.*a \(1 open\), b \(1 open\)") as info:
        reset(manager, "c")
    assert info.value.status == 503 and catalog.stats.refusals == 1
    assert manager.open_count() == 2  # the refused reset left nothing behind
    manager.close(ea)
    manager.close(reset(manager, "c"))
    assert sorted(catalog.loaded_names()) == ["b", "c"]
    assert manager.set_pose(eb, __import__("numpy").array(FREE)).accepted  # b was never evicted under its episode


def test_a_scene_is_loaded_once_under_concurrent_resets(bundle_dir: Path, tmp_path: Path) -> None:
    catalog = SceneCatalog(sources(bundle_dir, "ab"), device="cpu", warm_up=False)
    manager = EpisodeManager(catalog, tmp_path)
    ids: list[str] = []
    threads = [threading.Thread(target=lambda: ids.append(reset(manager, "a"))) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(ids) == 4 and catalog.stats.loads == 1 and catalog.loaded_names() == ["a"]
    assert catalog.describe()["scenes"][0]["open_episodes"] == 4


def test_unknown_or_unnamed_scene_and_impossible_bound(bundle_dir: Path, tmp_path: Path) -> None:
    manager = EpisodeManager(SceneCatalog(sources(bundle_dir), device="cpu", warm_up=False), tmp_path)
    with pytest.raises(InvalidAction, match=r"serves 3 scenes: name one in 'scene' \(one of \['a', 'b', 'c'\]\)"):
        reset(manager, None)
    with pytest.raises(EpisodeNotFound, match=r"no scene 'shelf' on this server \(scenes: \['a', 'b', 'c'\]\)"):
        reset(manager, "shelf")
    with pytest.raises(EpisodeNotFound, match="no scene 9"):
        reset(manager, 9)
    with pytest.raises(BraveError, match=r"scene 'a' needs about 100 MB, more than the memory budget of 50 MB"):
        SceneCatalog(sources(bundle_dir), memory_budget_bytes=50 * MB)
    with pytest.raises(BraveError, match="two scenes are named 'a'"):
        SceneCatalog(sources(bundle_dir, "aa"))


class _Light:
    """A loaded scene for the bookkeeping property test: a real bundle, no renderer (loading 200
    renderers would test the renderer, not the catalog)."""

    def __init__(self, bundle: object, device: str) -> None:
        self.bundle = bundle
        self.device = device
        self.renderer = type("R", (), {"num_gaussians": 1, "renders": 0})()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=st.lists(st.tuples(st.sampled_from(["acquire", "release"]), st.integers(0, 4)), max_size=40),
       max_loaded=st.integers(1, 4), budget_scenes=st.integers(1, 5))
def test_bound_is_never_exceeded_and_pinned_scenes_stay(bundle_dir: Path, ops: list[tuple[str, int]],
                                                        max_loaded: int, budget_scenes: int) -> None:
    sizes = [10, 20, 30, 40, 50]
    srcs = [SceneSource(n, i, (SceneObject(1, "x"),), sizes[i] * MB, lambda: bundle_dir, "t")
            for i, n in enumerate("abcde")]
    budget = max(sizes) * MB * budget_scenes // 2 + 50 * MB
    catalog = SceneCatalog(srcs, max_loaded=max_loaded, memory_budget_bytes=budget, warm_up=False,
                           load_scene=_Light)  # type: ignore[arg-type]
    held: list[tuple[str, object]] = []
    for op, i in ops:
        name = "abcde"[i]
        if op == "acquire":
            pinned_before = {n for n, _ in held}
            try:
                held.append((name, catalog.acquire(name)))
            except SceneCacheFull:
                # refused only when the pinned scenes leave no room
                pinned = [s for s in srcs if s.name in pinned_before]
                need = sum(s.memory_bytes for s in pinned) + srcs[i].memory_bytes
                assert len(pinned) + 1 > max_loaded or need > budget
            assert pinned_before <= set(catalog.loaded_names())  # a pinned scene is never evicted
        else:
            mine = [h for h in held if h[0] == name]
            if mine:
                held.remove(mine[0])
                catalog.release(mine[0][1])  # type: ignore[arg-type]
        assert len(catalog.loaded_names()) <= max_loaded
        assert catalog.loaded_bytes() <= budget


def test_http_multi_scene_server(bundle_dir: Path, tmp_path: Path) -> None:
    catalog = SceneCatalog(sources(bundle_dir, "ab"), device="cpu", max_loaded=1, warm_up=False)
    with TestClient(create_app(catalog, log_dir=tmp_path), base_url="http://localhost") as client:
        listed = client.get("/scenes").json()
        assert [s["name"] for s in listed["scenes"]] == ["a", "b"] and listed["bound"]["max_loaded"] == 1
        assert not any(s["loaded"] for s in listed["scenes"])
        r = client.post("/episodes", json={"start": {"world_T_cam": FREE}})
        assert r.status_code == 422 and r.json()["field"] == "scene"
        r = client.post("/episodes", json={"scene": "a", "start": {"world_T_cam": FREE}, "rgb": "none"})
        assert r.status_code == 201, r.text
        ea = r.json()["episode_id"]
        r = client.post("/episodes", json={"scene": "b", "start": {"world_T_cam": FREE}, "rgb": "none"})
        assert r.status_code == 503 and r.json()["field"] == "scene" and "a (1 open)" in r.json()["error"]
        assert client.get(f"/episodes/{ea}").json()["scene"] == "a"
        assert client.post(f"/episodes/{ea}/close").status_code == 200
        r = client.post("/episodes", json={"scene": 2, "start": {"world_T_cam": FREE}, "rgb": "none"})
        assert r.status_code == 201, r.text
        assert client.get("/health").json()["loaded_scenes"] == ["b"]
        assert client.get("/bundle").json()["field"] == "scene"
        assert client.get("/bundle", params={"scene": "2"}).json()["scene_id"] == 2
        assert client.get("/bundle/models/1", params={"scene": "a"}).status_code == 200
        assert client.get("/bundle", params={"scene": "zz"}).status_code == 404
    from brave6d.serve import read_episode_log

    first = read_episode_log(tmp_path / f"{ea}.jsonl")[0]
    assert first.scene == "a" and first.scene_id == 1


def test_open_scenes_of_a_bundle_folder(bundle_dir: Path) -> None:
    catalog = open_scenes(bundle_dir, device="cpu", warm_up=False)
    assert catalog.names() == [load_bundle(bundle_dir).name] and catalog.source(None).scene_id is None
    with pytest.raises(BraveError, match="no such bundle"):
        open_scenes(bundle_dir / "missing")
    with pytest.raises(BraveError, match="not a bundle"):
        open_scenes(bundle_dir.parent)  # serve opens a bundle; a release's sources come from the command line


def test_the_command_line_tells_a_bundle_from_a_release(bundle_dir: Path) -> None:
    from brave6d.commands.scenes import scene_sources

    assert [s.name for s in scene_sources(bundle_dir)] == [load_bundle(bundle_dir).name]
    with pytest.raises(BraveError, match="no such bundle or release"):
        scene_sources(bundle_dir / "missing")
    with pytest.raises(BraveError, match="neither a bundle"):
        scene_sources(bundle_dir.parent)  # a scene folder: neither a bundle nor a release


def test_single_scene_server_keeps_its_api(bundle_dir: Path, tmp_path: Path) -> None:
    """A server of one bundle needs no scene name (every existing client keeps working)."""
    bundle = load_bundle(bundle_dir)
    with TestClient(create_app(bundle, scene=SceneServer(bundle, "cpu"), log_dir=tmp_path),
                    base_url="http://localhost") as client:
        assert client.post("/episodes", json={"start": {"world_T_cam": FREE}, "rgb": "none"}).status_code == 201
        assert client.get("/bundle").json()["name"] == bundle.name
        assert client.get("/health").json()["bundle"] == bundle.name
        assert client.get("/scenes").json()["scenes"][0]["open_episodes"] == 1

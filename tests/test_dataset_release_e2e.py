"""The dataset as the unit of work, end to end: the quick demo dataset through `brave6d dataset run
--executor local`, `brave6d release build` and `brave6d release verify` (what CI runs), then the
release served from one server (every scene, loaded on first use), a baseline agent on each scene,
and the leaderboard per scene and per category."""

from __future__ import annotations

import zipfile
from pathlib import Path

import pytest

from brave6d.annotation import read_models_info, read_scene_gt
from brave6d.cli import main as cli_main
from brave6d.core.dataset_spec import load_dataset_spec

ROOT = Path(__file__).resolve().parent.parent
DEMO_DATASET = ROOT / "data" / "demo" / "dataset.yaml"

pytestmark = pytest.mark.slow  # two quick scenes: about a minute


def test_demo_dataset_runs_releases_and_verifies(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    work, out = tmp_path / "work", tmp_path / "release"
    assert cli_main(["dataset", "run", str(DEMO_DATASET), str(work), "--quick", "--device", "cpu",
                     "--executor", "local", "--no-learn"]) == 0  # the learned model: test_dataset_learned
    assert cli_main(["release", "build", str(work), str(out)]) == 0
    capsys.readouterr()
    assert cli_main(["release", "verify", str(out)]) == 0
    assert "OK" in capsys.readouterr().out

    # the release holds both scenes under their dataset scene_ids, with the library's obj_ids
    dataset = load_dataset_spec(work / "dataset.yaml")
    library = dataset.spec.obj_ids()
    name = dataset.spec.name
    unpacked = tmp_path / "unpacked"
    for part in ("models", "test_all"):
        with zipfile.ZipFile(out / f"{name}_{part}.zip") as zf:
            zf.extractall(unpacked)
    assert sorted(p.name for p in (unpacked / "test").iterdir()) == ["000001", "000002"]
    for scene in dataset.scenes:
        gt = read_scene_gt(unpacked / "test" / f"{scene.scene_id:06d}" / "scene_gt.json")
        used = {g.obj_id for poses in gt.values() for g in poses}
        assert used == {library[o.name] for o in scene.spec.objects}, scene.name
    shared = {o.name for o in dataset.scenes[0].spec.objects} & {o.name for o in dataset.scenes[1].spec.objects}
    assert shared and {library[n] for n in shared} <= set(read_models_info(unpacked / "models" / "models_info.json"))
    # each scene's bundle zip ships the viewer PLY (the 3D filter baked in, issue 45), listed in its manifest
    for scene in dataset.scenes:
        with zipfile.ZipFile(out / f"{name}_bundle_{scene.scene_id:06d}.zip") as zf:
            members = set(zf.namelist())
        assert f"bundles/{scene.scene_id:06d}/splat_viewer.ply" in members, scene.name

    # one server serves every scene of the release; the leaderboard scores across scenes
    _serve_and_score(out, tmp_path, [s.name for s in dataset.scenes], capsys)

    # one altered byte anywhere is caught, naming the file
    victim = out / f"{name}_test_all.zip"
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    capsys.readouterr()
    assert cli_main(["release", "verify", str(out)]) == 2
    assert victim.name in capsys.readouterr().err


def _serve_and_score(release: Path, tmp_path: Path, scenes: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.evaluation.agents import STATIC_AGENT, make_agent, run_episode
    from brave6d.commands.scenes import scene_sources
    from brave6d.serve import BraveClient, ServerThread, create_app, open_scenes

    logs = tmp_path / "logs"
    catalog = open_scenes(scene_sources(release, tmp_path / "cache"), device="cpu", max_loaded=1)
    with ServerThread(create_app(catalog, log_dir=logs)) as server, BraveClient(server.url) as client:
        listed = client.scenes()["scenes"]
        assert [s["name"] for s in listed] == scenes and not any(s["loaded"] for s in listed)
        assert {o["category"] for s in listed for o in s["objects"]} >= {"industry", "laboratory"}
        agent = make_agent(STATIC_AGENT, client)
        for name in scenes:
            target = client.bundle(name)["objects"][0]["gt_id"]
            run_episode(client, agent, target, seed=1, width=160, height=120, scene=name)
        assert client.health()["loaded_scenes"] == [scenes[-1]]  # max_loaded=1: the first was unloaded
    capsys.readouterr()
    assert cli_main(["evaluate", str(logs), "--out", str(tmp_path / "board")]) == 0
    # the static baseline plays a scored server (the default): its episodes are ranked
    assert f"2 scored episodes ranked on 2 scene(s) ({', '.join(sorted(scenes))})" in capsys.readouterr().out
    rows = (tmp_path / "board" / "per_scene.csv").read_text().splitlines()
    assert sorted(r.split(",")[1] for r in rows[1:]) == sorted(scenes)
    assert len((tmp_path / "board" / "per_category.csv").read_text().splitlines()) >= 2

"""The time-to-quality benchmark: when a PSNR level is reached, configurations, and configuration A
trained by a worker process on another source tree (``--a-source``)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
from pathlib import Path

import pytest

SPEC = importlib.util.spec_from_file_location(
    "time_to_quality", Path(__file__).resolve().parent.parent / "benchmarks" / "time_to_quality.py")
ttq = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(ttq)  # type: ignore[union-attr]

POINTS = [{"psnr": 20.0, "time_s": 0.0, "cpu_s": 0.0}, {"psnr": 26.0, "time_s": 10.0, "cpu_s": 18.0},
          {"psnr": 28.0, "time_s": 20.0, "cpu_s": 38.0}, {"psnr": 27.5, "time_s": 30.0, "cpu_s": 58.0}]


def test_time_to_a_level_interpolates_between_evaluations() -> None:
    assert ttq.time_to(POINTS, 27.0, "time_s") == pytest.approx(15.0)
    assert ttq.time_to(POINTS, 27.0, "cpu_s") == pytest.approx(28.0)
    assert ttq.time_to(POINTS, 28.0, "time_s") == pytest.approx(20.0)  # reached exactly at an evaluation
    assert ttq.time_to(POINTS, 19.0, "time_s") == 0.0  # already there at the start
    assert ttq.time_to(POINTS, 30.0, "time_s") is None  # never reached (a later dip does not count)


def test_configurations_parse_to_typed_preset_overrides() -> None:
    assert ttq.parse_config("new=fast,steps=1000,downscale=4,grow_grad2d=2e-4,max_gaussians=none") == (
        "new", "fast", {"steps": 1000, "downscale": 4, "grow_grad2d": 2e-4, "max_gaussians": None})
    # a text value (failed before: int('mip') raised a ValueError traceback)
    assert ttq.parse_config("mip=fast,antialiasing=mip,depth_lambda=0")[2] == {"antialiasing": "mip", "depth_lambda": 0}
    with pytest.raises(SystemExit, match="'stepz' is not a Preset field"):
        ttq.parse_config("x=fast,stepz=3")
    with pytest.raises(SystemExit, match="NAME=PRESET"):
        ttq.parse_config("fast")


# ----------------------------------------------------------------------------- configuration A in a worker
REPO = Path(__file__).resolve().parent.parent
TINY = "fast,steps=4,coarse_steps=0,downscale=1,max_init_points={}"


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.core.camera import PinholeCamera
    from brave6d.training.toy_scenes import plane_views, write_scene

    cam = PinholeCamera(80, 50, 62.5, 62.5, 39.5, 24.5)
    return write_scene(tmp_path_factory.mktemp("ttq") / "scene", cam, plane_views(cam, [0.45, 0.6], 5)).root


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_a_trained_by_a_worker_on_another_source_tree(tiny_scene: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """The worker protocol end to end: A in a worker on a source directory (this checkout), B here."""
    out = tmp_path / "ttq.json"
    assert ttq.main([str(tiny_scene), "--a-source", str(REPO), "--a", "old=" + TINY.format(1000),
                     "--b", "new=" + TINY.format(2000), "--every", "2", "--chunk", "2", "--init", "depth",
                     "--device", "cpu", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"A = old (fast at {REPO}), B = new (fast at this tree)" in printed
    data = json.loads(out.read_text())
    a, b = data["a"], data["b"]
    assert [p["step"] for p in a["points"]] == [0, 2, 4] == [p["step"] for p in b["points"]]
    assert a["steps"] == b["steps"] == 4
    # A's configuration reached the worker: its preset, and at most 1000 initial Gaussians against B's more
    assert a["preset"]["max_init_points"] == 1000 and a["preset"]["eval_every"] == 2
    assert a["preset"]["time_budget_s"] is None
    assert a["points"][0]["gaussians"] <= 1000 < b["points"][0]["gaussians"]
    package = REPO / "src" / "brave6d"
    assert a["source"] == {"dir": str(REPO), "modules": {"brave6d.training": str(package / "training" / "__init__.py"),
                                                         "brave6d": str(package / "__init__.py")}}
    assert b["source"] == {"dir": str(REPO)}
    for run in (a, b):
        assert isinstance(run["train_s"], float) and run["train_s"] > 0
        assert isinstance(run["time_to_own_final"], float) and 0 < run["time_to_own_final"] <= run["train_s"]
        assert isinstance(run["warmup_s"], float) and run["jit_compiles_while_timed"] == 0
        assert all(isinstance(p["psnr"], float) and p["time_s"] <= run["train_s"] for p in run["points"])
        assert run["final_psnr"] == run["points"][-1]["psnr"]
    assert isinstance(data["ratio_time_to_a_final"], float) or (
        data["ratio_time_to_a_final"] is None and b["time_to_other_final"] is None)
    assert data["memory_a_worker"]["peak_rss_mb"] > 0


def test_the_warm_up_leaves_the_training_as_it_was(tiny_scene: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from brave6d.core.layout import SceneDir
    from brave6d.training import get_preset

    preset = ttq.configure(get_preset("fast"), {"steps": 3, "coarse_steps": 0, "downscale": 1,
                                                "max_init_points": 500})

    def trained() -> list[float]:
        run = ttq.Run("x", preset, SceneDir(tiny_scene), 1, "cpu", "depth")
        run.advance(3)
        return [p["psnr"] for p in run.points]

    warm = trained()
    monkeypatch.setattr(ttq.Run, "warm_up", lambda self: 0.0)
    assert trained() == warm  # bit for bit: the throwaway step touched neither the model nor the RNG
    assert len(warm) == 4 and warm[-1] != warm[0]


@pytest.mark.timeout(60)
def test_a_source_without_training_stops_naming_it(tiny_scene: Path, tmp_path: Path) -> None:
    empty = tmp_path / "not-a-checkout"
    empty.mkdir()
    with pytest.raises(SystemExit, match=r"the worker running the source tree .*not-a-checkout") as info:
        ttq.main([str(tiny_scene), "--a-source", str(empty), "--a", "old=fast", "--b", "new=" + TINY.format(500),
                  "--device", "cpu", "--worker-timeout", "50", "--json", str(tmp_path / "x.json")])
    assert "ModuleNotFoundError" in str(info.value) or "holds no such package" in str(info.value)
    assert not (tmp_path / "x.json").exists()


@pytest.mark.timeout(60)
def test_a_worker_that_dies_stops_with_its_exit_code_and_stderr(tiny_scene: Path, tmp_path: Path) -> None:
    fake = tmp_path / "fake"
    (fake / "src" / "brave6d" / "core").mkdir(parents=True)
    (fake / "src" / "brave6d" / "__init__.py").write_text("")
    (fake / "src" / "brave6d" / "core" / "__init__.py").write_text("")
    (fake / "src" / "brave6d" / "core" / "runtime.py").write_text(
        "import os, sys\n\ndef prepare_process():\n    print('fake tree: giving up', file=sys.stderr, flush=True)\n"
        "    os._exit(7)\n")
    with pytest.raises(SystemExit, match=r"source tree .*fake.* exited while setting up \(exit code 7\)") as info:
        ttq.main([str(tiny_scene), "--a-source", str(fake), "--device", "cpu", "--worker-timeout", "50",
                  "--json", str(tmp_path / "x.json")])
    assert "fake tree: giving up" in str(info.value)


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_a_bad_configuration_for_the_source_tree_is_reported_by_its_worker(tiny_scene: Path,
                                                                          tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=r"'stepz' is not a Preset field"):
        ttq.main([str(tiny_scene), "--a-source", str(REPO), "--a", "old=fast,stepz=3", "--device", "cpu",
                  "--worker-timeout", "50", "--json", str(tmp_path / "x.json")])
    with pytest.raises(SystemExit, match=r"no preset 'fast-9000' in"):
        ttq.main([str(tiny_scene), "--a-source", str(REPO), "--a", "old=fast-9000", "--device", "cpu",
                  "--worker-timeout", "50", "--json", str(tmp_path / "x.json")])


def test_a_revision_is_extracted_and_removed(tmp_path: Path) -> None:
    if subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True).returncode != 0:
        pytest.skip("not a git checkout")
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    source = ttq.resolve_source("HEAD")
    try:
        assert source.info == {"rev": "HEAD", "commit": head} and source.label == "HEAD"
        assert (source.root / "src" / "brave6d" / "training" / "__init__.py").is_file()
    finally:
        source.cleanup()
    assert not source.root.exists()
    with pytest.raises(SystemExit, match="neither a directory nor a git revision"):
        ttq.resolve_source("no-such-revision-0123")


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_revision_before_the_src_layout_trains_in_its_worker(tiny_scene: Path, tmp_path: Path) -> None:
    """A tree from before ``src/brave6d`` (top-level ``training``, kernel modules in ``brave6d/``):
    the worker imports its own modules under today's names, so old code can still be compared."""
    moved = subprocess.run(["git", "-C", str(REPO), "log", "-1", "--format=%H", "--", "brave6d/atomic.py"],
                           capture_output=True, text=True)
    if moved.returncode != 0 or not moved.stdout.strip():
        pytest.skip("not a git checkout with the history of the src layout")
    old = moved.stdout.strip() + "^"  # the commit before the move: brave6d/atomic.py still at the top
    out = tmp_path / "ttq.json"
    assert ttq.main([str(tiny_scene), "--a-source", old, "--a", "old=" + TINY.format(1000),
                     "--b", "new=" + TINY.format(1000), "--every", "2", "--device", "cpu", "--json", str(out)]) == 0
    a = json.loads(out.read_text())["a"]
    assert a["source"]["rev"] == old and a["steps"] == 4 and a["final_psnr"] > 0
    assert a["source"]["modules"]["training"].endswith("/training/__init__.py")  # the old tree's own package

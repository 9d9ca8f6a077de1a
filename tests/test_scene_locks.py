"""One scene, one job (issue 32, item 11): a scene's job holds the scene's lock; a second job on
the scene is refused while the first one's process lives, naming its host and pid, and leaves the
status alone; the lock of a killed job is taken over; ``dataset status`` and the driver do not
call a stage ``running`` when its process is gone."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from lock_holder import kill_holder, spawn_holder

import brave6d.pipeline.stages
import brave6d.dataset.runner
from brave6d.cli import main as cli_main
from brave6d.core.locks import read_holder
from brave6d.dataset import JOB_STAGES, ExecutorOptions, SceneJob, read_scene_status, read_summary, run_dataset
from brave6d.dataset.status import mark, scene_status_path
from brave6d.dataset.workdir import prepare_workdir

ROOT = Path(__file__).resolve().parent.parent
DEMO_DATASET = ROOT / "data" / "demo" / "dataset.yaml"
SCENE = "demo_tabletop"


def scene_lock_path(work: Path, scene: str) -> Path:
    """Where a scene's job keeps its lock (``brave6d.dataset.status.scene_lock_path``, written out: it is documented)."""
    return work / "status" / f"{scene}.lock"


@pytest.fixture()
def work(tmp_path: Path) -> Path:
    """The demo dataset's work directory with its scenes initialised (no stage run yet)."""
    prepare_workdir(DEMO_DATASET, tmp_path / "work", quick=True)
    return tmp_path / "work"


@pytest.fixture()
def ran(work: Path, monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, int | None]]:
    """Stand-in stages that note their name and the pid holding the scene's lock when they ran."""
    ran: list[tuple[str, int | None]] = []

    def stage(name: str) -> Any:
        def run(ctx: Any) -> Any:
            holder = read_holder(scene_lock_path(work, SCENE))
            ran.append((name, holder.process.pid if holder else None))
            return SimpleNamespace(figures={})
        return SimpleNamespace(name=name, resolve=lambda: run)

    monkeypatch.setattr(brave6d.pipeline.stages, "STAGES", tuple(stage(n) for n in JOB_STAGES))
    return ran


def test_a_second_job_is_refused_while_the_first_runs(work: Path, ran: list[tuple[str, int | None]]) -> None:
    proc, first = spawn_holder(scene_lock_path(work, SCENE))
    try:
        before = scene_status_path(work, SCENE).read_bytes()
        outcome = SceneJob(work, SCENE, 1, {}, quick=True, device="cpu")()
        assert outcome.busy == f"{first.host} (pid {first.pid})"
        assert not outcome.ok and outcome.failed_stage is None  # not a failure of the scene
        assert ran == []
        assert scene_status_path(work, SCENE).read_bytes() == before  # no stage marked running or failed
        assert read_holder(scene_lock_path(work, SCENE)).process == first
    finally:
        kill_holder(proc)


def test_the_lock_of_a_killed_job_is_taken_over(work: Path, ran: list[tuple[str, int | None]],
                                                caplog: pytest.LogCaptureFixture) -> None:
    lock = scene_lock_path(work, SCENE)
    proc, first = spawn_holder(lock)
    kill_holder(proc)  # SIGKILL: its lock file stays behind
    with caplog.at_level(logging.WARNING, logger="brave6d.core.locks"):
        outcome = SceneJob(work, SCENE, 1, {}, quick=True, device="cpu")()
    assert outcome.ok
    assert ran == [(name, os.getpid()) for name in JOB_STAGES]  # every stage ran under this job's lock
    assert f"took over the lock of {first.host} (pid {first.pid}), which is gone" in caplog.text
    assert all(read_scene_status(work, SCENE).done(s) for s in JOB_STAGES)
    assert not lock.exists()  # released when the job ended


def test_the_lock_is_released_when_a_stage_fails_or_the_job_raises(work: Path, ran: list[tuple[str, int | None]],
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(ctx: Any) -> Any:
        raise RuntimeError("disk on fire")

    stages = list(brave6d.pipeline.stages.STAGES)
    stages[1] = SimpleNamespace(name=stages[1].name, resolve=lambda: broken)
    monkeypatch.setattr(brave6d.pipeline.stages, "STAGES", tuple(stages))
    outcome = SceneJob(work, SCENE, 1, {}, quick=True, device="cpu")()
    assert outcome.failed_stage == JOB_STAGES[1] and "disk on fire" in (outcome.error or "")
    assert not scene_lock_path(work, SCENE).exists()
    monkeypatch.setattr("brave6d.core.layout.SceneDir.load_spec", lambda self: (_ for _ in ()).throw(OSError("gone")))
    with pytest.raises(OSError, match="gone"):
        SceneJob(work, SCENE, 1, {}, quick=True, device="cpu")()
    assert not scene_lock_path(work, SCENE).exists()


def test_status_says_interrupted_once_the_running_process_is_gone(work: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    proc, job = spawn_holder(scene_lock_path(work, SCENE))
    status = read_scene_status(work, SCENE)
    mark(work, status, "calibrate", "running", **job.to_json())  # as that job's process records it
    try:
        assert cli_main(["dataset", "status", str(work)]) == 0
        assert f"running ({job.host}:{job.pid})" in capsys.readouterr().out
    finally:
        kill_holder(proc)
    assert cli_main(["dataset", "status", str(work)]) == 0
    table = capsys.readouterr().out
    row = next(line for line in table.splitlines() if SCENE in line)
    assert f"interrupted ({job.host}:{job.pid} gone)" in row and "running" not in row
    scene = next(s for s in read_summary(work)["scenes"] if s["scene"] == SCENE)
    assert scene["stages"]["calibrate"]["interrupted"] is True


def test_the_driver_does_not_start_a_second_job_on_a_busy_scene(work: Path, monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    def no_jobs(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("a second job was started on a scene whose job still runs")

    monkeypatch.setattr(brave6d.dataset.runner, "make_executor", no_jobs)
    proc, job = spawn_holder(scene_lock_path(work, SCENE))
    try:
        summary = run_dataset(DEMO_DATASET, work, quick=True, device="cpu", scenes=[SCENE], learn=False,
                              options=ExecutorOptions(executor="local", time_min=5))
    finally:
        kill_holder(proc)
    assert f"{SCENE}: already running on {job.host} (pid {job.pid}), not started again" in capsys.readouterr().err
    assert summary.busy == {SCENE: f"{job.host} (pid {job.pid})"}
    assert summary.failed == {} and summary.ran == []


def test_the_command_says_which_scene_it_did_not_start_and_exits_non_zero(
        work: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``brave6d dataset run`` with a busy scene: not a success (exit 1), and the last lines say why."""
    from brave6d.cli import main

    monkeypatch.setattr(brave6d.dataset.runner, "make_executor", lambda *a, **k: pytest.fail("a second job was started"))
    proc, job = spawn_holder(scene_lock_path(work, SCENE))
    try:
        code = main(["dataset", "run", str(DEMO_DATASET), str(work), "--quick", "--device", "cpu", "--scenes", SCENE,
                     "--no-learn"])
    finally:
        kill_holder(proc)
    assert code == 1
    assert f"NOT STARTED {SCENE}: its job still runs on {job.host} (pid {job.pid})" in capsys.readouterr().out


def test_init_writes_nothing_while_the_scene_job_runs(work: Path) -> None:
    """The driver's ``init`` of a re-run (here with a changed spec, which would record ``init``
    failed) leaves the record of a scene whose job still runs untouched."""
    from brave6d.core.dataset_spec import load_dataset_spec
    from brave6d.dataset.workdir import init_scene

    scene = load_dataset_spec(DEMO_DATASET).scene(SCENE)
    record = scene_status_path(work, SCENE)
    before = record.read_bytes()
    proc, _ = spawn_holder(scene_lock_path(work, SCENE))
    try:
        assert init_scene(work, scene, quick=False) == "busy"  # quick=False: another fingerprint
        assert record.read_bytes() == before
    finally:
        kill_holder(proc)
    assert init_scene(work, scene, quick=False) == "failed"  # once the job is gone: the usual refusal

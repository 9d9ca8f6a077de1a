"""``brave6d dataset run`` / ``status``: executors, status records, and the quick demo dataset end to end."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest
import submitit
import yaml

from brave6d.annotation import BopLayout, read_scene_gt
from brave6d.cli import main as cli_main
from brave6d.core.dataset_spec import ClusterSpec, load_dataset_spec
from brave6d.core.layout import SceneDir
from brave6d.core.locks import Process
from brave6d.dataset import (
    SCENE_STAGES,
    ExecutorOptions,
    SceneJob,
    SceneStatus,
    make_executor,
    read_scene_status,
    read_summary,
    status_table,
)

ROOT = Path(__file__).resolve().parent.parent
DEMO_DATASET = ROOT / "data" / "demo" / "dataset.yaml"


def test_slurm_executor_gets_the_flags_and_the_cluster_block(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(submitit.SlurmExecutor, "affinity", classmethod(lambda cls: 1))  # pretend srun exists
    cluster = ClusterSpec(executor="slurm", partition="gpu", cpus_per_task=6, setup=["source /shared/venv/bin/activate"])
    options = ExecutorOptions.from_cluster(cluster, time_min=600, mem_gb=48.0, array_parallelism=4, partition=None)
    executor = make_executor(options, tmp_path / "jobs")
    assert isinstance(executor, submitit.SlurmExecutor)
    params = executor.parameters
    assert (params["partition"], params["time"], params["cpus_per_task"], params["mem"]) == ("gpu", 600, 6, "48GB")
    assert (params["gpus_per_node"], params["ntasks_per_node"], params["array_parallelism"]) == (1, 1, 4)
    sbatch = executor._make_submission_file_text("python -m submitit.core._submit X", "uid")
    for line in ("#SBATCH --partition=gpu", "#SBATCH --time=600", "#SBATCH --gpus-per-node=1",
                 "#SBATCH --mem=48GB", "#SBATCH --cpus-per-task=6", "#SBATCH --signal=USR2@120",
                 "source /shared/venv/bin/activate"):
        assert line in sbatch, line


def test_local_executor_hides_gpus_for_cpu_runs(tmp_path: Path) -> None:
    options = ExecutorOptions(executor="local", time_min=30)
    assert make_executor(options, tmp_path, device="cpu").parameters["gpus_per_node"] == 0
    assert make_executor(options, tmp_path, device="auto").parameters["gpus_per_node"] == 1
    assert make_executor(options, tmp_path).parameters["timeout_min"] == 30


def test_the_scene_job_is_requeued_with_its_own_state(tmp_path: Path) -> None:
    job = SceneJob(tmp_path, "a", 1, {"nut": 2}, quick=True, device="cpu")
    assert isinstance(job, submitit.helpers.Checkpointable)
    again = job.checkpoint()
    assert again.function is job and (job.scene, job.obj_ids) == ("a", {"nut": 2})


def test_status_table_shows_every_state(tmp_path: Path) -> None:
    from brave6d.dataset.status import write_scene_status

    write_scene_status(tmp_path, SceneStatus("a", 1, "f", {
        "init": {"state": "done", "seconds": 0.0}, "calibrate": {"state": "failed", "error": "board unreachable"},
    }))
    me = Process.current()
    write_scene_status(tmp_path, SceneStatus("b", 2, "g", {"init": {"state": "running", **me.to_json()}}))
    write_scene_status(tmp_path, SceneStatus("c", 3, "h", {"init": {"state": "running", "host": "n1", "pid": 7}}))
    table = status_table(tmp_path, [(1, "a"), (2, "b"), (3, "c")])
    rows = {cells[2]: cells[3:-1] for line in table.splitlines()[2:5] if (cells := [c.strip() for c in line.split("|")])}
    assert rows["a"] == ["done 0s", "FAILED", "pending", "pending", "pending", "pending"]
    assert rows["b"] == [f"running ({me.host}:{me.pid})", *["pending"] * 5]
    assert rows["c"] == ["interrupted (n1:7 gone)", *["pending"] * 5]  # no live job holds scene c's lock
    assert "a / calibrate: board unreachable" in table
    assert read_scene_status(tmp_path, "a").first_failure() == ("calibrate", "board unreachable")


def _dataset_with_a_broken_scene(tmp_path: Path) -> Path:
    """A copy of the demo dataset (a dataset names files inside its folder) plus a third scene whose
    clutter mesh is not a mesh."""
    folder = Path(shutil.copytree(DEMO_DATASET.parent, tmp_path / "demo",
                                  ignore=shutil.ignore_patterns("*.py", "__pycache__")))
    broken = yaml.safe_load((folder / "workbench.yaml").read_text())
    (folder / "junk.obj").write_text("this is not a mesh\n")
    broken["static_meshes"].append({"name": "junk", "mesh": "junk.obj"})
    broken["name"] = "demo_broken"
    (folder / "broken.yaml").write_text(yaml.safe_dump(broken))
    path = folder / "dataset.yaml"
    data = yaml.safe_load(path.read_text())
    data["scenes"].append({"spec": "broken.yaml"})
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.mark.slow
def test_quick_demo_dataset_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = _dataset_with_a_broken_scene(tmp_path)
    work = tmp_path / "work"
    argv = ["dataset", "run", str(spec), str(work), "--quick", "--device", "cpu", "--executor", "local", "--no-learn"]
    t0 = time.perf_counter()
    assert cli_main(argv) == 1  # the broken scene fails ...
    first = time.perf_counter() - t0
    out = capsys.readouterr()
    assert "FAILED demo_broken at" in out.out
    good = ["demo_tabletop", "demo_workbench"]
    for name in good:  # ... and the other two finish
        assert all(read_scene_status(work, name).done(s) for s in SCENE_STAGES), name
    assert read_scene_status(work, "demo_broken").first_failure() is not None
    assert "[1/3] demo_tabletop  train     done in" in out.err  # one line per scene and stage

    # every scene's BOP export uses the library's obj_ids
    dataset = load_dataset_spec(work / "dataset.yaml")
    library = dataset.spec.obj_ids()
    for scene in dataset.scenes[:2]:
        gt = read_scene_gt(BopLayout.of_scene(SceneDir(work / "scenes" / scene.name)).scene_gt_path)
        used = {g.obj_id for poses in gt.values() for g in poses}
        assert used == {library[o.name] for o in scene.spec.objects}, scene.name
    assert [s.scene_id for s in dataset.scenes] == [1, 2, 3]

    # a second run redoes nothing that is done
    stamps = {n: {s: r["at"] for s, r in read_scene_status(work, n).stages.items()} for n in good}
    t0 = time.perf_counter()
    assert cli_main(argv) == 1
    rerun = time.perf_counter() - t0
    assert {n: {s: r["at"] for s, r in read_scene_status(work, n).stages.items()} for n in good} == stamps
    with capsys.disabled():
        print(f"\nquick demo dataset (2 scenes + 1 broken): first run {first:.1f} s, re-run {rerun:.1f} s")

    capsys.readouterr()
    assert cli_main(["dataset", "status", str(work)]) == 0
    table = capsys.readouterr().out
    assert table.count("done") >= 2 * len(SCENE_STAGES) and "demo_broken" in table
    summary = read_summary(work)
    assert [r["scene"] for r in summary["scenes"]] == [*good, "demo_broken"]


def test_the_public_api_resolves_and_stays_light() -> None:
    import subprocess
    import sys

    from brave6d import dataset

    assert all(hasattr(dataset, n) for n in dataset.__all__)
    code = "import sys, brave6d.dataset; print(','.join(m for m in ('torch', 'submitit', 'open3d') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "", out.stdout + out.stderr

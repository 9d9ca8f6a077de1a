"""``brave6d dataset run``: every stage of every scene, one submitit job per scene.

The driver initialises the scenes (:mod:`brave6d.dataset.workdir`), submits one :class:`SceneJob` per
scene that has stages left (local: one after another, or ``array_parallelism`` at a time;
Slurm: one job array), prints one line per scene and stage as the scenes' status records change,
and ends with the scene x stage table, naming every failed scene and its error, and every captured
scene that is not ready for the cluster with what it misses (:mod:`brave6d.dataset.captured`; it gets
no job, the others go on). Every scene trains with one preset: ``--preset``, else the ``cluster``
block's ``preset``, else the training stage's default (``fast``). Once per run, not per scene, the
dataset's object library gets its learned model (:mod:`brave6d.dataset.learn`: a job of its own
through the same executor, after the scene jobs on this machine, beside them on Slurm). Running it again
redoes nothing that is recorded ``done``. A scene whose job from an earlier run still runs (its
lock has a live holder, :mod:`brave6d.dataset.job`) is not started again: the run says where it runs.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import submitit

from brave6d.core.dataset_spec import Dataset
from brave6d.core.errors import BraveError
from brave6d.dataset.captured import RIG_STAGES
from brave6d.dataset.executor import ExecutorOptions, make_executor
from brave6d.dataset.job import JOB_STAGES, SceneJob, SceneOutcome
from brave6d.dataset.learn import (LearnOptions, LearnOutcome, LibraryLearnJob, learn_fingerprint, learn_is_done,
                                   learn_options, write_library_spec)
from brave6d.dataset.status import (SCENE_STAGES, live_scene_holder, read_scene_status, running_text, status_table,
                            write_summary)
from brave6d.dataset.workdir import prepare_workdir

#: Seconds between two looks at the status records while jobs run.
POLL_S = 1.0


@dataclass
class RunSummary:
    """What a run did: the scenes it ran, those that failed (name -> (stage, error)), the captured
    scenes not ready for the cluster (name -> (stage, what is missing): a rig stage's outputs are
    not in the scene directory), those already running elsewhere (name -> ``HOST (pid N)``, not
    started again), the training preset every scene was given (None: the stage's default), the table;
    ``learn``: the learn step's options (None: no learn step) and ``learned``: how it ended (``done``,
    ``done earlier``, ``failed: ERROR``, ``busy: HOST (pid N)``, ``not run: WHY``)."""

    dataset: str
    ran: list[str] = field(default_factory=list)
    failed: dict[str, tuple[str, str]] = field(default_factory=dict)
    missing: dict[str, tuple[str, str]] = field(default_factory=dict)
    busy: dict[str, str] = field(default_factory=dict)
    preset: str | None = None
    table: str = ""
    seconds: float = 0.0
    learn: LearnOptions | None = None
    learned: str = ""


def run_dataset(dataset_file: Path, workdir: Path, *, quick: bool = False, device: str = "auto",
                options: ExecutorOptions | None = None, scenes: Sequence[str] | None = None,
                echo: bool = True, mesh_dirs: Sequence[Path | str] = (), scene_dirs: Sequence[Path | str] = (),
                preset: str | None = None, learn: LearnOptions | bool = True) -> RunSummary:
    """Run every pending stage of every (selected) scene of ``dataset_file`` in ``workdir``
    (``mesh_dirs``, ``scene_dirs``: the user's ``--mesh-dir`` and ``--scene-dir`` folders,
    :func:`brave6d.dataset.workdir.prepare_workdir`). ``preset``: the training preset of every scene
    (``--preset``; None: the ``cluster`` block's ``preset``, else the training stage's default).
    ``learn``: the learned model's options (True: the ``cluster`` block's, else the defaults; False: none)."""
    start, started = time.perf_counter(), time.strftime("%Y-%m-%dT%H:%M:%S%z")
    workdir = Path(workdir).resolve()
    dataset, inits = prepare_workdir(Path(dataset_file), workdir, quick, mesh_dirs, scene_dirs)
    preset = scene_preset(dataset, preset)
    options = options or ExecutorOptions.from_cluster(dataset.spec.cluster)
    names = [s.name for s in dataset.scenes]
    unknown = sorted(set(scenes or ()) - set(names))
    if unknown:
        raise BraveError(f"--scenes: {unknown} are not scenes of {dataset_file} (it has {names})")
    selected = [s for s in dataset.scenes if not scenes or s.name in scenes]
    ids = [(s.scene_id, s.name) for s in dataset.scenes]
    printer = _Printer(workdir, [s.name for s in selected], echo, started)
    printer.poll()
    todo = [s for s in selected if inits[s.name] not in ("failed", "missing")
            and not all(read_scene_status(workdir, s.name).done(st) for st in JOB_STAGES)]
    busy: dict[str, str] = {}
    for s in todo:
        holder = live_scene_holder(workdir, s.name)
        if holder is not None:
            busy[s.name] = holder.describe()
            printer.say(_busy_line(s.name, busy[s.name]))
    jobs = [SceneJob(workdir, s.name, s.scene_id, s.obj_ids, quick, device, preset, s.dir)
            for s in todo if s.name not in busy]
    learn_opts = learn if isinstance(learn, LearnOptions) else \
        learn_options(dataset.spec.cluster, quick) if learn else None
    learn_job, learned = _learn_job(workdir, learn_opts, device, all(r != "failed" for r in inits.values()))
    if learned:
        printer.say(f"learned model: {learned}")
    outcomes: dict[str, SceneOutcome] = {}
    if jobs or learn_job is not None:
        executor = make_executor(options, workdir / "jobs", device)
        if options.executor == "local":
            for i in range(0, len(jobs), max(1, options.array_parallelism)):
                batch = jobs[i:i + max(1, options.array_parallelism)]
                outcomes.update(_wait(printer, [executor.submit(j) for j in batch], batch))
            if learn_job is not None:
                learned = _wait_learn(printer, executor.submit(learn_job))
        else:
            learn_submitted = executor.submit(learn_job) if learn_job is not None else None
            if jobs:
                submitted = _submit_array(executor, jobs)
                printer.say(f"submitted {len(submitted)} Slurm jobs ({submitted[0].job_id.split('_')[0]}); "
                            f"logs in {workdir / 'jobs'}")
                outcomes.update(_wait(printer, submitted, jobs))
            if learn_submitted is not None:
                learned = _wait_learn(printer, learn_submitted)
    for name, outcome in outcomes.items():
        if outcome.busy is not None:  # its job started between the look above and the job's own
            busy[name] = outcome.busy
            printer.say(_busy_line(name, outcome.busy))
    write_summary(workdir, dataset.spec.name, ids)
    summary = RunSummary(dataset.spec.name, ran=[j.scene for j in jobs if j.scene not in busy], preset=preset,
                         table=status_table(workdir, ids), seconds=time.perf_counter() - start, busy=busy,
                         learn=learn_opts, learned=learned)
    for s in selected:
        if s.name in busy:
            continue  # its record belongs to the job that runs it
        failure = read_scene_status(workdir, s.name).first_failure()
        if failure is not None and inits[s.name] == "missing" and failure[0] in RIG_STAGES:
            summary.missing[s.name] = failure
        elif failure is not None:
            summary.failed[s.name] = failure
        elif s.name in outcomes and not outcomes[s.name].ok:
            outcome = outcomes[s.name]
            summary.failed[s.name] = (outcome.failed_stage or "?", outcome.error or "")
    return summary


def scene_preset(dataset: Dataset, flag: str | None) -> str | None:
    """The training preset of every scene: ``flag`` (``--preset``), else the ``cluster`` block's
    ``preset``, else None (the training stage's default); an unknown name is an error naming where it came from."""
    from brave6d.training import get_preset

    name = flag if flag is not None else dataset.spec.cluster.preset
    if name is not None:
        try:
            get_preset(name)
        except BraveError as exc:
            where = "--preset" if flag is not None else f"{dataset.spec.source}: field 'cluster.preset'"
            raise BraveError(f"{where}: {exc}") from None
    return name


def _learn_job(workdir: Path, options: LearnOptions | None, device: str,
               ready: bool) -> tuple[LibraryLearnJob | None, str]:
    """The learn step's job, or None and why not (``""``: no learn step)."""
    if options is None:
        return None, ""
    if not ready:
        return None, "not run: a scene's init failed, so WORKDIR/dataset.yaml was not written"
    write_library_spec(workdir)
    fingerprint = learn_fingerprint(workdir, options, device)
    if learn_is_done(workdir, fingerprint):
        return None, "done earlier, not redone"
    return LibraryLearnJob(workdir, options, device, fingerprint), ""


def _wait_learn(printer: _Printer, job: submitit.Job) -> str:
    """Wait for the learn step's job; its outcome as :attr:`RunSummary.learned` says it (and printed)."""
    while not job.done():
        printer.poll()
        time.sleep(POLL_S)
    printer.poll()
    try:
        outcome: LearnOutcome = job.result()
    except Exception as exc:  # noqa: BLE001 - the job process died (killed, out of memory, ...)
        last = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        outcome = LearnOutcome(error=f"{last} (log: {job.paths.stderr})")
    if outcome.busy is not None:
        text = f"busy: already running on {outcome.busy}"
    elif outcome.error is not None:
        text = f"failed: {outcome.error}"
    else:
        text = "done  " + ", ".join(f"{k}={v}" for k, v in (outcome.figures or {}).items())
    printer.say(f"learned model: {text}")
    return text


def _busy_line(scene: str, where: str) -> str:
    return f"{scene}: already running on {where}, not started again"


def _submit_array(executor: submitit.Executor, jobs: list[SceneJob]) -> list[submitit.Job]:
    """One Slurm job array: every scene's job in one ``sbatch``."""
    with executor.batch():
        submitted = [executor.submit(job) for job in jobs]
    return submitted


def _wait(printer: _Printer, submitted: list[submitit.Job], jobs: list[SceneJob]) -> dict[str, SceneOutcome]:
    """Wait for ``submitted``, printing stage lines; a job that dies is a failed scene, not a crash."""
    while not all(job.done() for job in submitted):
        printer.poll()
        time.sleep(POLL_S)
    printer.poll()
    outcomes = {}
    for job, scene_job in zip(submitted, jobs):
        try:
            outcomes[scene_job.scene] = job.result()
        except Exception as exc:  # noqa: BLE001 - the job process died (killed, out of memory, ...)
            last = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
            outcomes[scene_job.scene] = SceneOutcome(scene_job.scene, "job", f"{last} (log: {job.paths.stderr})")
    return outcomes


class _Printer:
    """One line per scene and stage, printed when a status record changes state."""

    def __init__(self, workdir: Path, scenes: list[str], echo: bool, started: str) -> None:
        self.workdir, self.scenes, self.echo, self.started = workdir, scenes, echo, started
        self.seen: dict[tuple[str, str], str] = {}

    def say(self, text: str) -> None:
        if self.echo:
            print(text, file=sys.stderr, flush=True)

    def poll(self) -> None:
        width = max((len(s) for s in self.scenes), default=0)
        for n, scene in enumerate(self.scenes, start=1):
            status = read_scene_status(self.workdir, scene)
            for stage in SCENE_STAGES:
                state, record = status.state(stage), status.stages.get(stage, {})
                stamp = f"{state} {record.get('at')}"
                if state == "pending" or self.seen.get((scene, stage)) == stamp:
                    continue
                self.seen[(scene, stage)] = stamp
                prefix = f"[{n}/{len(self.scenes)}] {scene:<{width}} {stage:<9}"
                if state == "done" and str(record.get("at", "")) < self.started:
                    self.say(f"{prefix} done earlier ({record.get('at')}), not redone")
                elif state == "done":
                    figures = ", ".join(f"{k}={v}" for k, v in record.get("figures", {}).items())
                    self.say(f"{prefix} done in {record.get('seconds', 0):.1f} s  {figures}")
                elif state == "failed":
                    self.say(f"{prefix} FAILED: {record.get('error', '')}")
                else:
                    self.say(f"{prefix} {running_text(self.workdir, scene, record)} ...")

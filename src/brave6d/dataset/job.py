"""One scene's job: run its remaining stages in order, recording each in the scene's status.

:class:`SceneJob` is what submitit runs (in a child process or on a Slurm node). It is a
``submitit.helpers.Checkpointable``: when Slurm preempts it or its time runs out, submitit
requeues the same job, which skips the stages recorded ``done`` and continues the training from
its checkpoints (``RunContext.resume``). The job's context carries the run's choices (training
preset, device, quick) to the stage functions. A captured scene's job runs only its training and
export: its rig stages were found done by the driver (:mod:`brave6d.dataset.captured`), and the job
runs none of them. A failing stage is recorded with its error and ends
the job (later stages need its outputs); the job returns a :class:`SceneOutcome`, it never
raises for a stage's failure, so one scene never stops another.

One scene, one job: the job holds the scene's lock (``status/<scene>.lock``, :mod:`brave6d.core.locks`)
while it runs. A second job on the scene while the first one's process is alive (a re-run after
only the driver was killed) does nothing and returns an outcome naming the first one's host and
pid (``busy``), leaving the status record to it; the lock of a job that is gone is taken over.
"""

from __future__ import annotations

import logging
import math
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import submitit

from brave6d.core.errors import BraveError
from brave6d.core.locks import FileLock, LockHeld
from brave6d.core.progress import Stopwatch
from brave6d.dataset.captured import RIG_STAGES
from brave6d.dataset.status import mark, read_scene_status, scene_lock_path

log = logging.getLogger(__name__)

#: The stages a job runs, in order (named as in ``brave6d.pipeline.STAGES``, whose functions run them).
JOB_STAGES = ("calibrate", "capture", "annotate", "train", "export")


@dataclass(frozen=True)
class SceneOutcome:
    """How a scene's job ended: the failed stage and its error, or ``None`` for both; ``busy``
    names the live job already running the scene (``HOST (pid N)``) when this one did nothing."""

    scene: str
    failed_stage: str | None = None
    error: str | None = None
    busy: str | None = None

    @property
    def ok(self) -> bool:
        return self.failed_stage is None and self.busy is None


class SceneJob(submitit.helpers.Checkpointable):
    """Run the pending stages of one scene of a dataset work directory (module docstring)."""

    def __init__(self, workdir: Path, scene: str, scene_id: int, obj_ids: dict[str, int],
                 quick: bool = False, device: str = "auto", preset: str | None = None,
                 captured_dir: Path | None = None) -> None:
        self.workdir, self.scene, self.scene_id = Path(workdir), scene, scene_id
        self.obj_ids, self.quick, self.device, self.preset = dict(obj_ids), quick, device, preset
        self.captured_dir = Path(captured_dir) if captured_dir is not None else None

    def __call__(self) -> SceneOutcome:
        from brave6d.core.runtime import prepare_process

        prepare_process()  # before any stage loads torch / numba, as the CLI does
        lock = FileLock(scene_lock_path(self.workdir, self.scene), f"dataset scene {self.scene}")
        try:
            lock.acquire()
        except LockHeld as exc:
            log.warning("%s: already running on %s; this job does nothing", self.scene, exc.holder.describe())
            return SceneOutcome(self.scene, busy=exc.holder.describe())
        with lock:
            return self._run_stages(lock)

    def _run_stages(self, lock: FileLock) -> SceneOutcome:
        """Run the stages not recorded ``done``, in order, while holding the scene's ``lock``."""
        from brave6d.pipeline import RunContext, stage_named

        status = read_scene_status(self.workdir, self.scene, self.scene_id)
        if not status.done("init"):
            return SceneOutcome(self.scene, "init", "the scene directory was not initialised")
        root = self.captured_dir if self.captured_dir is not None else self.workdir / "scenes" / self.scene
        ctx = RunContext.for_scene(root, workdir=self.workdir / "work" / self.scene, preset=self.preset,
                                   quick=self.quick, device=self.device, obj_ids=self.obj_ids, resume=True)
        ctx.workdir.mkdir(parents=True, exist_ok=True)
        for name in JOB_STAGES:
            if status.done(name):
                continue
            if self.captured_dir is not None and name in RIG_STAGES:  # the driver found its outputs missing
                return SceneOutcome(self.scene, name, f"{name} is not done in {root}, and dataset run never runs "
                                                      "it for a captured scene")
            if lock.lost is not None:  # another job took the scene over (this one looked dead): leave it be
                return SceneOutcome(self.scene, name, f"{lock.lost}; stopped before {name}")
            mark(self.workdir, status, name, "running")
            with Stopwatch() as watch:
                try:
                    result = stage_named(name).resolve()(ctx)
                except Exception as exc:  # noqa: BLE001 - recorded and reported; the other scenes go on
                    error = str(exc) if isinstance(exc, BraveError) else f"{type(exc).__name__}: {exc}"
                    if not isinstance(exc, BraveError):
                        log.error("%s / %s:\n%s", self.scene, name, traceback.format_exc())
                    mark(self.workdir, status, name, "failed", seconds=round(watch.seconds, 1),
                         error=error.splitlines()[0] if error else type(exc).__name__)
                    return SceneOutcome(self.scene, name, error)
            mark(self.workdir, status, name, "done", seconds=round(watch.seconds, 1),
                 figures=_plain(result.figures))
        return SceneOutcome(self.scene)


def _plain(figures: dict[str, Any]) -> dict[str, Any]:
    """Figures as JSON values (numpy scalars to Python, NaN/inf to text)."""
    out: dict[str, Any] = {}
    for key, value in figures.items():
        if hasattr(value, "item"):
            value = value.item()
        if isinstance(value, float) and not math.isfinite(value):
            value = str(value)
        out[str(key)] = value if isinstance(value, (int, float, str, bool)) or value is None else str(value)
    return out

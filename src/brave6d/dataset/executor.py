"""The job engine of ``brave6d dataset run``: submitit's local or Slurm executor, configured once.

One job per scene. ``local`` runs each job as a child process on this machine (what CI runs);
``slurm`` submits them as one Slurm job array (one task and ``gpus_per_task`` GPUs per scene, at
most ``array_parallelism`` at a time). Both need the work directory on a filesystem that the
driver and every job see (on a cluster: a shared filesystem), since jobs exchange nothing else:
they read the scene directories and write their status records there.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import submitit

from brave6d.core.dataset_spec import ClusterSpec
from brave6d.core.errors import BraveError

#: Seconds between Slurm's warning signal and the kill: time to reach the checkpoint and requeue.
SIGNAL_DELAY_S = 120


@dataclass(frozen=True)
class ExecutorOptions:
    """Where and how the scene jobs run (the ``cluster`` block of ``dataset.yaml``, then the flags)."""

    executor: str = "local"
    partition: str | None = None
    time_min: int = 240
    gpus_per_task: int = 1
    cpus_per_task: int = 8
    mem_gb: float = 32.0
    array_parallelism: int = 16
    account: str | None = None
    qos: str | None = None
    setup: tuple[str, ...] = field(default_factory=tuple)

    @classmethod
    def from_cluster(cls, cluster: ClusterSpec, **overrides: Any) -> ExecutorOptions:
        """The dataset's ``cluster`` block with the flags that were given (``None`` = not given);
        its training ``preset`` and ``learn*`` fields are the run's choices, not the executor's."""
        base = cls(**{**cluster.model_dump(exclude={"preset", "learn", "learn_preset", "learn_images"}),
                      "setup": tuple(cluster.setup)})
        return replace(base, **{k: v for k, v in overrides.items() if v is not None})


def make_executor(options: ExecutorOptions, folder: Path, device: str = "auto") -> submitit.Executor:
    """A configured submitit executor whose logs and pickles go to ``folder``.

    The local executor gets no GPU when ``device`` is ``cpu`` and ``gpus_per_task`` otherwise
    (it sets ``CUDA_VISIBLE_DEVICES``); its time limit is ``time_min`` too. Making a Slurm
    executor needs Slurm's ``srun`` on the PATH.
    """
    folder = Path(folder)
    if options.executor == "local":
        executor = submitit.LocalExecutor(folder=folder)
        executor.update_parameters(timeout_min=options.time_min, signal_delay_s=SIGNAL_DELAY_S,
                                   gpus_per_node=0 if device == "cpu" else options.gpus_per_task)
        return executor
    if options.executor != "slurm":
        raise BraveError(f"unknown executor {options.executor!r} (local or slurm)")
    try:
        executor = submitit.SlurmExecutor(folder=folder)
    except RuntimeError as exc:  # submitit: 'Could not detect "srun"'
        raise BraveError(f"--executor slurm: {exc}; run this on a Slurm login node") from None
    executor.update_parameters(**slurm_parameters(options))
    return executor


def slurm_parameters(options: ExecutorOptions) -> dict[str, Any]:
    """The ``SlurmExecutor`` parameters (sbatch's names) of ``options``: one task per scene."""
    params: dict[str, Any] = {
        "job_name": "brave6d-dataset", "time": options.time_min, "nodes": 1, "ntasks_per_node": 1,
        "cpus_per_task": options.cpus_per_task, "mem": _mem(options.mem_gb),
        "array_parallelism": options.array_parallelism, "signal_delay_s": SIGNAL_DELAY_S,
    }
    if options.gpus_per_task:
        params["gpus_per_node"] = options.gpus_per_task  # one task per node: the task's GPUs
    for key in ("partition", "account", "qos"):
        if getattr(options, key):
            params[key] = getattr(options, key)
    if options.setup:
        params["setup"] = list(options.setup)
    return params


def _mem(mem_gb: float) -> str:
    return f"{int(mem_gb)}GB" if mem_gb == int(mem_gb) else f"{int(mem_gb * 1024)}MB"

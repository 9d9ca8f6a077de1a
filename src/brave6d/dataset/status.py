"""Which stage of which scene is done: ``WORKDIR/status/<scene>.json`` and ``WORKDIR/status.json``.

Each scene's job is the only writer of its own record (``status/<scene>.json``), so jobs running
side by side on a cluster never write the same file; every write is atomic. A stage is
``running`` (with host, pid, start time), ``done`` (seconds, figures) or ``failed`` (the error);
a stage with no record is ``pending``. ``WORKDIR/status.json`` is the whole table gathered from
the records (``dataset run`` and ``dataset status`` rewrite it), for people and for the release.

A scene's job holds the scene's lock ``status/<scene>.lock`` (:mod:`brave6d.core.locks`) while it runs,
so a stage recorded ``running`` whose job is gone (killed, its node lost) shows as
``interrupted (host:pid gone)`` rather than ``running``; a re-run redoes it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.core.errors import DataError
from brave6d.core.locks import Holder, Process, read_holder
from brave6d.core.progress import format_table

FORMAT = "brave6d-dataset-status/1"
SCENE_FORMAT = "brave6d-dataset-scene-status/1"
#: Every stage a scene goes through, in order (``init`` runs in the driver, the rest in the scene's job).
SCENE_STAGES = ("init", "calibrate", "capture", "annotate", "train", "export")
STATES = ("pending", "running", "done", "failed")


def status_dir(workdir: Path) -> Path:
    return Path(workdir) / "status"


def scene_status_path(workdir: Path, scene: str) -> Path:
    return status_dir(workdir) / f"{scene}.json"


def scene_lock_path(workdir: Path, scene: str) -> Path:
    """The lock that the job running ``scene``'s stages holds (one job per scene)."""
    return status_dir(workdir) / f"{scene}.lock"


def live_scene_holder(workdir: Path, scene: str) -> Holder | None:
    """The live holder of ``scene``'s lock (a job running its stages), or None."""
    holder = read_holder(scene_lock_path(workdir, scene))
    return holder if holder is not None and holder.dead_because() is None else None


def summary_path(workdir: Path) -> Path:
    return Path(workdir) / "status.json"


@dataclass
class SceneStatus:
    """One scene's record: its id, the fingerprint its stages were run for, and each stage's state."""

    scene: str
    scene_id: int
    fingerprint: str = ""
    stages: dict[str, dict[str, Any]] = field(default_factory=dict)

    def state(self, stage: str) -> str:
        return str(self.stages.get(stage, {}).get("state", "pending"))

    def done(self, stage: str) -> bool:
        return self.state(stage) == "done"

    def first_failure(self) -> tuple[str, str] | None:
        """``(stage, error)`` of the first failed stage, if any."""
        for stage in SCENE_STAGES:
            if self.state(stage) == "failed":
                return stage, str(self.stages[stage].get("error", ""))
        return None

    def to_json(self) -> dict[str, Any]:
        return {"format": SCENE_FORMAT, "scene": self.scene, "scene_id": self.scene_id,
                "fingerprint": self.fingerprint, "stages": self.stages}


def read_scene_status(workdir: Path, scene: str, scene_id: int = 0) -> SceneStatus:
    """The record of ``scene`` (an empty one before its first stage)."""
    path = scene_status_path(workdir, scene)
    if not path.exists():
        return SceneStatus(scene, scene_id)
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != SCENE_FORMAT or not isinstance(data.get("stages"), dict):
        raise DataError(f"{path}: not a scene status record (expected format {SCENE_FORMAT!r})")
    for name, record in data["stages"].items():
        if name not in SCENE_STAGES or not isinstance(record, dict) or record.get("state") not in STATES:
            raise DataError(f"{path}: field 'stages.{name}': unknown stage or state")
    return SceneStatus(str(data.get("scene", scene)), int(data.get("scene_id", scene_id)),
                       str(data.get("fingerprint", "")), dict(data["stages"]))


def write_scene_status(workdir: Path, status: SceneStatus) -> None:
    atomic_write_json(scene_status_path(workdir, status.scene), status.to_json())


def mark(workdir: Path, status: SceneStatus, stage: str, state: str, **details: Any) -> None:
    """Record ``stage``'s new state (with when, where and ``details``) and write the record."""
    record: dict[str, Any] = {"state": state, "at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    if state == "running":
        record.update(Process.current().to_json())
    record.update(details)
    status.stages[stage] = record
    write_scene_status(workdir, status)


def running_text(workdir: Path, scene: str, record: dict[str, Any]) -> str:
    """``running (host:pid)`` for a stage recorded ``running`` whose process still runs, else
    ``interrupted (host:pid gone)``.

    It runs while the scene's lock has a live holder, or (a stage run outside a job, such as
    ``init`` in the driver) while the recorded process is found running on this machine.
    """
    holder = live_scene_holder(workdir, scene)
    if holder is not None:
        return f"running ({holder.process.host}:{holder.process.pid})"
    recorded = Process.from_json(record)
    if recorded.on_this_machine() and recorded.gone() is None:
        return f"running ({recorded.host}:{recorded.pid})"
    return f"interrupted ({recorded.host}:{recorded.pid} gone)"


def write_summary(workdir: Path, dataset: str, scenes: list[tuple[int, str]]) -> Path:
    """Gather the scenes' records into ``WORKDIR/status.json`` (scene_id, name, stages)."""
    rows = []
    for scene_id, name in scenes:
        st = read_scene_status(workdir, name, scene_id)
        stages = {s: dict(st.stages.get(s, {"state": "pending"})) for s in SCENE_STAGES}
        for record in stages.values():
            if record["state"] == "running" and running_text(workdir, name, record).startswith("interrupted"):
                record["interrupted"] = True  # its process is gone; a re-run redoes the stage
        rows.append({"scene_id": scene_id, "scene": name, "stages": stages})
    return atomic_write_json(summary_path(workdir), {"format": FORMAT, "dataset": dataset,
                                                     "updated_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                                     "scenes": rows})


def read_summary(workdir: Path) -> dict[str, Any]:
    """``WORKDIR/status.json`` as written by :func:`write_summary`."""
    path = summary_path(workdir)
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise DataError(f"{path}: not a dataset status file (expected format {FORMAT!r})")
    return data


def status_table(workdir: Path, scenes: list[tuple[int, str]]) -> str:
    """The scene x stage table: ``done 12.3s``, ``FAILED``, ``running``, ``pending``; errors below it."""
    rows, errors = [], []
    for scene_id, name in scenes:
        st = read_scene_status(workdir, name, scene_id)
        cells = []
        for stage in SCENE_STAGES:
            state, record = st.state(stage), st.stages.get(stage, {})
            if state == "done":
                cells.append(f"done {record['seconds']:.0f}s" if "seconds" in record else "done")
            elif state == "failed":
                cells.append("FAILED")
                errors.append(f"{name} / {stage}: {record.get('error', '')}")
            elif state == "running":
                cells.append(running_text(workdir, name, record))
            else:
                cells.append("pending")
        rows.append((scene_id, name, *cells))
    table = format_table(["id", "scene", *SCENE_STAGES], rows)
    return table + ("\n\nfailed:\n" + "\n".join(f"  {e}" for e in errors) if errors else "")

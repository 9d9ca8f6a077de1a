"""The report's measurement cache: one JSON file per measurement, and sweeps that resume.

A measurement (``<workdir>/report/measurements/<name>.json``, written atomically) holds its
``key`` (the inputs' fingerprints and the sweep settings), the machine it ran on, its status,
its points and a summary. Re-running the report reuses a complete measurement whose key still
matches, so the report is cheap to rebuild; a sweep saves itself after every point, so one
interrupted halfway resumes with the points still missing. ``refresh`` measures everything again.

Statuses: ``complete``, ``partial`` (a sweep in progress or interrupted), ``missing`` (an input
does not exist: ``note`` says which) and ``failed`` (``note`` says why).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import logging
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.core.errors import DataError
from brave6d.core.progress import progress_bar

log = logging.getLogger(__name__)

SCHEMA = "brave6d.report.measurement/1"
T = TypeVar("T")

#: Files up to this size are fingerprinted by content, larger ones by size and modification time.
HASH_LIMIT_BYTES = 8 * 2**20


@dataclass
class Measurement:
    """One cached measurement (see the module docstring)."""

    name: str
    key: dict[str, Any] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)
    machine: dict[str, Any] = field(default_factory=dict)
    status: str = "partial"
    note: str = ""
    points: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0  # wall time spent measuring, over all runs that added to it
    measured_at: str = ""

    @property
    def done_ids(self) -> set[str]:
        return {str(p["id"]) for p in self.points if "id" in p}

    @property
    def usable(self) -> bool:
        """True when there is something to show (complete, or partial with points)."""
        return self.status == "complete" or (self.status == "partial" and bool(self.points))

    def to_json(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "name": self.name, "status": self.status, "note": self.note,
                "measured_at": self.measured_at, "seconds": self.seconds, "machine": self.machine,
                "settings": self.settings, "key": self.key, "summary": self.summary, "points": self.points}

    @staticmethod
    def from_json(data: dict[str, Any], source: str = "measurement") -> Measurement:
        if not isinstance(data, dict) or data.get("schema") != SCHEMA or "name" not in data:
            raise DataError(f"{source}: not a report measurement (schema {SCHEMA})")
        return Measurement(
            name=str(data["name"]), key=dict(data.get("key") or {}), settings=dict(data.get("settings") or {}),
            machine=dict(data.get("machine") or {}), status=str(data.get("status", "partial")),
            note=str(data.get("note") or ""), points=list(data.get("points") or []),
            summary=dict(data.get("summary") or {}), seconds=float(data.get("seconds") or 0.0),
            measured_at=str(data.get("measured_at") or ""),
        )


class MeasurementStore:
    """The folder of measurement JSONs; ``refresh`` ignores what is cached (once per name)."""

    def __init__(self, folder: Path | str, refresh: bool = False) -> None:
        self.folder = Path(folder)
        self.refresh = refresh
        self._refreshed: set[str] = set()

    def path(self, name: str) -> Path:
        return self.folder / f"{name}.json"

    def load(self, name: str) -> Measurement | None:
        """The cached measurement ``name`` whatever its status, or None (absent or unreadable)."""
        path = self.path(name)
        if not path.is_file():
            return None
        try:
            return Measurement.from_json(read_json(path), str(path))
        except DataError as exc:
            log.warning("ignoring %s", exc)
            return None

    def save(self, m: Measurement) -> Path:
        m.measured_at = _dt.datetime.now().isoformat(timespec="seconds")
        return atomic_write_json(self.path(m.name), _finite(m.to_json()))

    def cached(self, name: str, key: dict[str, Any]) -> Measurement | None:
        """The cached measurement ``name`` when its key matches (complete or partial), else None."""
        if self.refresh and name not in self._refreshed:
            return None
        m = self.load(name)
        if m is not None and m.key == _finite(key) and m.status in ("complete", "partial"):
            return m
        return None

    def complete(self, name: str, key: dict[str, Any]) -> Measurement | None:
        """The cached measurement when it is complete for ``key`` (nothing to measure), else None."""
        m = self.cached(name, key)
        return m if m is not None and m.status == "complete" else None

    def resume(self, name: str, key: dict[str, Any], settings: dict[str, Any], machine: dict[str, Any]
               ) -> Measurement:
        """The cached measurement if its key matches (complete or to be continued), else a new one."""
        cached = self.cached(name, key)
        self._refreshed.add(name)
        if cached is not None:
            if cached.status == "partial":
                log.info("%s: resuming a partial measurement (%d points done)", name, len(cached.points))
            return cached
        return Measurement(name=name, key=_finite(key), settings=_finite(settings), machine=machine)

    def missing(self, name: str, note: str) -> Measurement:
        """Record that ``name`` cannot be measured (an input is absent); nothing is kept from before."""
        m = Measurement(name=name, status="missing", note=note)
        self.save(m)
        return m

    def require(self, name: str, inputs: Sequence[tuple[Path, str]]) -> Measurement | None:
        """:meth:`missing` for the first absent input file (``(path, the stage that writes it)``), else None."""
        for path, stage in inputs:
            if not Path(path).is_file():
                return self.missing(name, f"no `{path}` (run the {stage} stage)")
        return None

    def failed(self, name: str, note: str) -> Measurement:
        """Record that measuring ``name`` failed; points measured so far stay in the file."""
        m = self.load(name) or Measurement(name=name)
        m.status, m.note = "failed", note
        self.save(m)
        return m


def run_sweep(
    store: MeasurementStore,
    m: Measurement,
    items: Sequence[tuple[str, T]],
    measure: Callable[[T], dict[str, Any]],
    desc: str,
    unit: str = "pt",
) -> Measurement:
    """Measure every item not in ``m`` yet (``(id, item)`` pairs), saving after each point.

    A progress bar with ETA counts the points already cached as done; points are kept in the
    order of ``items``.
    """
    done = m.done_ids
    todo = [(i, item) for i, item in items if str(i) not in done]
    if todo:
        bar = progress_bar(total=len(items), desc=desc, unit=unit, initial=len(items) - len(todo))
        try:
            for point_id, item in todo:
                t0 = time.perf_counter()
                point = {"id": str(point_id), **measure(item)}
                m.seconds += time.perf_counter() - t0
                m.points.append(_finite(point))
                m.status = "partial"
                store.save(m)
                bar.update(1)
        finally:
            bar.close()
    order = {str(i): k for k, (i, _) in enumerate(items)}
    m.points.sort(key=lambda p: order.get(str(p.get("id")), len(order)))
    m.status = "complete"
    store.save(m)
    return m


def _finite(obj: Any) -> Any:
    """NaN/inf -> None, recursively (JSON has no NaN; a plot must see the gap, not a number)."""
    if isinstance(obj, float):
        return obj if obj == obj and obj not in (float("inf"), float("-inf")) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


# ----------------------------------------------------------------------------- fingerprints
def file_stamp(path: Path | str) -> dict[str, Any] | None:
    """What identifies a file's content: its SHA-256 (small files) or size and mtime; None if absent."""
    p = Path(path)
    if not p.is_file():
        return None
    st = p.stat()
    if st.st_size <= HASH_LIMIT_BYTES:
        return {"sha256": hashlib.sha256(p.read_bytes()).hexdigest()}
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}


# ----------------------------------------------------------------------------- the machine
def machine_info(device: str = "cpu") -> dict[str, Any]:
    """CPU model, cores, GPU (when ``device`` is CUDA), torch version and threads, OS."""
    info: dict[str, Any] = {"cpu": _cpu_model(), "cores": os.cpu_count(), "os": f"{platform.system()} "
                            f"{platform.machine()}", "python": platform.python_version(), "device": device}
    if hasattr(os, "sched_getaffinity"):
        info["usable_cores"] = len(os.sched_getaffinity(0))
    if hasattr(os, "getloadavg"):  # other jobs on the machine slow every timing down
        info["load_1min"] = round(os.getloadavg()[0], 2)
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a dependency
        return info
    info["torch"] = torch.__version__.split("+")[0]
    info["torch_threads"] = torch.get_num_threads()
    info["gpu"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return info


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    if sys.platform == "darwin":
        import subprocess

        try:
            return subprocess.run(["sysctl", "-n", "machdep.cpu.brand_string"], capture_output=True, text=True,
                                  timeout=5).stdout.strip() or platform.processor()
        except (OSError, subprocess.SubprocessError):
            pass
    return platform.processor() or platform.machine() or "unknown CPU"


def describe_machine(info: dict[str, Any], with_load: bool = True) -> str:
    """One line, e.g. ``AMD EPYC, 2 cores, no GPU (ran on cpu), torch 2.13.0, 2 threads, load 1.2``."""
    if not info:
        return "machine not recorded"
    cores = info.get("usable_cores") or info.get("cores")
    gpu = info.get("gpu")
    parts = [str(info.get("cpu", "unknown CPU")), f"{cores} cores" if cores else "cores unknown",
             f"GPU {gpu}" if gpu else "no GPU"]
    if info.get("device"):
        parts[-1] += f" (ran on {info['device']})"
    if info.get("torch"):
        parts.append(f"torch {info['torch']}, {info.get('torch_threads', '?')} threads")
    if with_load and info.get("load_1min") is not None:
        parts.append(f"load {info['load_1min']:g} at start")
    return ", ".join(parts)

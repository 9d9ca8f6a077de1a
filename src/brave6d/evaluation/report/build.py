"""The accuracy-vs-time report: one Markdown page with PNG plots, from real measurements.

``build_report(workdir, settings)`` measures (or reuses cached measurements of) the demo scene
``<workdir>/scene`` (or any scene directory and output folder: :class:`ReportTarget`) and writes
``<workdir>/report/report.md`` with ``training.png``,
``handeye.png``, ``latency.png``, ``views.png`` and ``baseline.png`` beside it:

1. holdout PSNR/SSIM against training time, steps and Gaussians (:mod:`brave6d.evaluation.report.sections.training`);
2. hand-eye error against calibration poses and solve time (:mod:`brave6d.evaluation.report.sections.handeye`);
3. render latency against resolution and Gaussians (:mod:`brave6d.evaluation.report.sections.latency`);
4. holdout PSNR against views per distance level and their robot time (:mod:`brave6d.evaluation.report.sections.views`);
5. baseline AR against adjustments (:mod:`brave6d.evaluation.report.sections.baseline`).

The sections are known only through the registry :data:`brave6d.evaluation.report.sections.SECTIONS`
(each a :class:`~brave6d.evaluation.report.protocol.Section`), so this module never names one.

Measurements are cached under ``report/measurements/`` (:mod:`brave6d.evaluation.report.measurements`);
:func:`write_report` renders the page from that folder alone. A section whose input is missing,
or whose measurement fails, says so on the page; the other sections are still written. The
page ends with "How to choose settings", one derived sentence per section.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
import os
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from brave6d.core.atomic import atomic_write_text
from brave6d.core.errors import BraveError
from brave6d.core.layout import SceneDir
from brave6d.core.progress import StageResult, Stopwatch
from brave6d.evaluation.report.common import RenderedSection
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore, describe_machine
from brave6d.evaluation.report.protocol import MeasureInputs, Section
from brave6d.evaluation.report import sections as registry

if TYPE_CHECKING:
    from brave6d.core.run_context import RunContext

log = logging.getLogger(__name__)


def measurement_names() -> tuple[str, ...]:
    """The sections' measurement names, in the order they are measured (the registry's order)."""
    return tuple(s.name for s in registry.SECTIONS)


def figure_names() -> tuple[str, ...]:
    """The plots the sections write (removed before each rendering, so none outlives its data)."""
    return tuple(s.figure for s in registry.page_order())


@dataclass(frozen=True)
class ReportSettings:
    """Each section's settings by name (a section not named uses its full defaults);
    :meth:`for_mode` gives the quick (CI) and full variants."""

    sections: Mapping[str, Any] = field(default_factory=dict)

    def for_section(self, section: Section) -> Any:
        """The settings ``section`` measures with."""
        if section.name in self.sections:
            return self.sections[section.name]
        return section.settings(quick=False)

    @staticmethod
    def for_mode(quick: bool, device: str = "auto", benchmark_json: Path | None = None,
                 schedules_json: Path | None = None) -> ReportSettings:
        """Quick: a miniature sweep of every section (well under 2 minutes on 2 cores); full: the demo's.

        ``device``, ``benchmark_json`` and ``schedules_json`` go to every section whose settings have a
        field of that name.
        """
        common = {"device": device, "benchmark_json": benchmark_json, "schedules_json": schedules_json}
        return ReportSettings({s.name: with_common(s.settings(quick), common) for s in registry.SECTIONS})


def with_common(settings: Any, values: Mapping[str, Any]) -> Any:
    """``settings`` (a dataclass, or None) with the fields of ``values`` it has replaced."""
    if settings is None or not dataclasses.is_dataclass(settings):
        return settings
    names = {f.name for f in dataclasses.fields(settings)}
    return dataclasses.replace(settings, **{k: v for k, v in values.items() if k in names})


@dataclass
class ReportResult:
    """What :func:`build_report` did: the page, its plots and how long each measurement took."""

    markdown: Path
    figures: list[Path]
    seconds: dict[str, float]
    statuses: dict[str, str]


def report_dir(workdir: Path) -> Path:
    return Path(workdir) / "report"


@dataclass(frozen=True)
class ReportTarget:
    """What a report reads and where it writes: the work directory (sections that read the demo's
    other outputs, such as ``evaluation/baseline.json``, look there), the scene directory, and the
    folder of ``report.md``, its PNGs and ``measurements/``; ``learned_model``: the learned model's
    folder when it is not the demo's ``<workdir>/learned/model`` (a dataset's is shared by its scenes)."""

    workdir: Path
    scene: Path
    out: Path
    learned_model: Path | None = None

    @staticmethod
    def of_workdir(workdir: Path) -> ReportTarget:
        """The demo's layout: ``WORKDIR/scene`` reported into ``WORKDIR/report``."""
        return ReportTarget(Path(workdir), Path(workdir) / "scene", report_dir(workdir))

    @staticmethod
    def of_scene(scene: Path, out: Path, learned_model: Path | None = None) -> ReportTarget:
        """Any scene directory reported into ``out`` (its parent is the work directory)."""
        return ReportTarget(Path(scene).parent, Path(scene), Path(out), learned_model)


def as_target(where: Path | ReportTarget) -> ReportTarget:
    """``where`` as a :class:`ReportTarget` (a plain path is a demo work directory)."""
    return where if isinstance(where, ReportTarget) else ReportTarget.of_workdir(Path(where))


def measurement_store(workdir: Path, refresh: bool = False) -> MeasurementStore:
    return MeasurementStore(report_dir(workdir) / "measurements", refresh=refresh)


def measure_all(workdir: Path | ReportTarget, settings: ReportSettings, refresh: bool = False,
                only: tuple[str, ...] | None = None) -> tuple[dict[str, Measurement], dict[str, float]]:
    """Measure (or reuse) every section's data; a failing section is recorded, not raised."""
    target = as_target(workdir)
    inputs = MeasureInputs(target.workdir, SceneDir(target.scene),
                           MeasurementStore(target.out / "measurements", refresh=refresh), target.learned_model)
    results: dict[str, Measurement] = {}
    seconds: dict[str, float] = {}
    for section in registry.SECTIONS:
        name = section.name
        if only and name not in only:
            continue
        t0 = time.perf_counter()
        try:
            results[name] = section.measure(inputs, settings.for_section(section))
        except KeyboardInterrupt:
            raise
        except Exception as exc:  # noqa: BLE001 - one broken section must not cost the whole page
            log.warning("report: measuring %s failed: %s", name, exc, exc_info=True)
            results[name] = inputs.store.failed(name, f"{type(exc).__name__}: {exc}")
        seconds[name] = time.perf_counter() - t0
        log.info("report: %s %s in %.1f s", name, results[name].status, seconds[name])
    return results, seconds


def render_sections(measurements: Mapping[str, Measurement | None], out_dir: Path) -> list[RenderedSection]:
    """Every section, in page order, from measurements (any of them may be None).

    A measurement file that cannot be rendered (edited by hand, from an older version) gives a
    section that says so instead of stopping the page.
    """
    sections = []
    for section in registry.page_order():
        try:
            sections.append(section.render(measurements, out_dir))
        except Exception as exc:  # noqa: BLE001 - one unreadable measurement must not cost the whole page
            log.warning("report: rendering %r failed: %s", section.title, exc, exc_info=True)
            sections.append(RenderedSection(section.title, f"> **Not available.** The cached measurement could not "
                                                           f"be rendered ({type(exc).__name__}: {exc}); run "
                                                           "`brave6d report --refresh`.\n"))
    return sections


def write_report(workdir: Path | ReportTarget, seconds: dict[str, float] | None = None) -> ReportResult:
    """Render ``report/report.md`` and its PNGs from the cached measurements only (no measuring)."""
    target = as_target(workdir)
    out = target.out
    store = MeasurementStore(out / "measurements")
    measurements = {name: store.load(name) for name in measurement_names()}
    for name in figure_names():  # a section that lost its data must not keep an old plot
        (out / name).unlink(missing_ok=True)
    sections = render_sections(measurements, out)
    page = compose(target, sections, measurements, seconds or {})
    md = atomic_write_text(out / "report.md", page)
    statuses = {k: (m.status if m is not None else "absent") for k, m in measurements.items()}
    return ReportResult(md, [f for s in sections for f in s.figures], seconds or {}, statuses)


def compose(workdir: Path | ReportTarget, sections: list[RenderedSection],
            measurements: Mapping[str, Measurement | None], seconds: dict[str, float]) -> str:
    """The whole page: header (machine, scene, time spent), the sections, how to choose settings."""
    target = as_target(workdir)
    machines = {describe_machine(m.machine, with_load=False)
                for m in measurements.values() if m is not None and m.machine}
    spent = sum(m.seconds for m in measurements.values() if m is not None)
    now = _dt.datetime.now().isoformat(timespec="seconds")
    header = [
        f"# What accuracy costs in time: {target.scene.parent.name}/{target.scene.name}",
        "",
        "Every figure below is measured on the scene directory "
        f"`{target.scene}`; each plot states the machine and the settings it was measured with.",
        "",
        f"- Machine: {'; '.join(sorted(machines)) or 'not recorded'}",
        f"- Written {now}; "
        + (f"this run measured for {sum(seconds.values()):.0f} s; " if seconds else "from cached measurements; ")
        + f"the sweeps' points took {spent:.0f} s in all (cached in `{target.out.name}/measurements/`).",
        "- Sections: " + ", ".join(f"{name} {_status(measurements.get(name))}" for name in measurement_names()),
        "",
    ]
    advice = [s.advice for s in sections if s.advice]
    closing = ["## How to choose settings", ""]
    closing.append(" ".join(advice) if advice else
                   "No section has enough measurements to derive advice yet; run the missing stages first.")
    return "\n".join(header) + "\n" + "\n".join(s.markdown() for s in sections) + "\n" + "\n".join(closing) + "\n"


def _status(m: Measurement | None) -> str:
    if m is None:
        return "(not measured)"
    return f"({m.status}{'' if m.status != 'partial' else f', {len(m.points)} points'})"


def build_report(workdir: Path | ReportTarget, settings: ReportSettings, refresh: bool = False,
                 only: tuple[str, ...] | None = None, measure: bool = True) -> ReportResult:
    """Measure what is not cached (unless ``measure`` is False), then write the page; ``workdir``:
    a demo work directory, or a :class:`ReportTarget` for any scene directory and output folder."""
    seconds: dict[str, float] = {}
    if measure:
        _, seconds = measure_all(workdir, settings, refresh, only)
    return write_report(workdir, seconds)


def stage_report(ctx: RunContext) -> StageResult:
    """The demo's last stage: ``brave6d report`` on ``ctx.workdir`` (quick sweeps with ``ctx.quick``).

    It runs in a child process because the timings need OpenMP threads that sleep while they
    wait (``OMP_WAIT_POLICY=PASSIVE``, as ``brave6d serve`` sets it): the policy is read once,
    when torch loads, and the demo process loaded torch long before this stage. With spinning
    threads the rasterizer measured up to ten times slower on 2 cores than the server renders.
    """
    cmd = [sys.executable, "-m", "brave6d.cli", "report", "--workdir", str(ctx.workdir),
           "--mode", "quick" if ctx.quick else "full", "--device", ctx.device]
    env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    with Stopwatch() as watch:
        done = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, check=False)
    if done.returncode != 0:
        raise BraveError(f"the report failed (exit status {done.returncode}; see the messages above): {' '.join(cmd)}")
    store = measurement_store(ctx.workdir)
    statuses = {name: (m.status if (m := store.load(name)) is not None else "absent") for name in measurement_names()}
    plots = sum((report_dir(ctx.workdir) / name).is_file() for name in figure_names())
    missing = [k for k, v in statuses.items() if v != "complete"]
    return StageResult("report", figures={
        "report": str(report_dir(ctx.workdir) / "report.md"), "plots": plots, "seconds": round(watch.seconds, 1),
        "incomplete": "+".join(missing) or "none",
    })

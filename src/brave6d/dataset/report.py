"""``brave6d dataset report WORKDIR``: the accuracy-vs-time report of every scene, and one index.

Each scene (``WORKDIR/scenes/<name>``, or a captured scene where it lies) gets the single-scene report (:func:`brave6d.evaluation.report.build_report`)
in ``WORKDIR/report/<name>/`` (``report.md``, its PNGs, ``measurements/``: resumable per scene as
``brave6d report`` is). ``WORKDIR/report/README.md`` links them and compares the scenes in one table
read from their cached measurements: holdout PSNR, the distance study's AR and the real-vs-splat AR
gap per capture ring, each where it was measured.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from brave6d.core.atomic import atomic_write_text
from brave6d.core.errors import BraveError
from brave6d.core.progress import format_table

INDEX = "README.md"


@dataclass(frozen=True)
class SceneSummary:
    """One scene's row of the index (NaN: not measured)."""

    scene: str
    report: Path | None
    holdout_psnr: float = math.nan
    distance_ar: float = math.nan
    distance_targets: int = 0
    gap_by_ring: tuple[tuple[float, float], ...] = ()  # (distance m, AR real - AR splat)
    statuses: Mapping[str, str] = field(default_factory=dict)
    note: str = ""


@dataclass(frozen=True)
class DatasetReport:
    """What :func:`report_dataset` wrote: the index and each scene's summary."""

    index: Path
    scenes: tuple[SceneSummary, ...]


def report_root(workdir: Path) -> Path:
    return Path(workdir) / "report"


def report_dataset(workdir: Path, quick: bool, only: Sequence[str] = (), refresh: bool = False,
                   device: str = "auto") -> DatasetReport:
    """Report every scene of the work directory (module docstring), then write the index."""
    from brave6d.dataset.learn import learned_model_dir
    from brave6d.dataset.workdir import WORKDIR_DATASET, load_workdir_dataset, scene_root
    from brave6d.evaluation.report import ReportSettings, ReportTarget, build_report

    workdir = Path(workdir)
    spec_path = workdir / WORKDIR_DATASET
    if not spec_path.is_file():
        raise BraveError(f"{spec_path}: not found; is {workdir} a work directory of 'brave6d dataset run'?")
    dataset = load_workdir_dataset(workdir)
    settings = ReportSettings.for_mode(quick, device)
    unknown = sorted(set(only) - set(settings.sections))
    if unknown:
        raise BraveError(f"brave6d dataset report: --only {' '.join(unknown)}: no such section "
                         f"(choose from {', '.join(settings.sections)})")
    summaries = []
    for scene in dataset.scenes:
        root = scene_root(workdir, scene).root
        out = report_root(workdir) / scene.name
        if not root.is_dir():
            summaries.append(SceneSummary(scene.name, None, note=f"no scene directory {root}"))
            continue
        result = build_report(ReportTarget.of_scene(root, out, learned_model_dir(workdir)), settings, refresh=refresh,
                              only=tuple(only))
        summaries.append(summarize_scene(scene.name, out, result.markdown, result.statuses))
    index = write_index(workdir, f"{dataset.spec.name} {dataset.spec.version}", summaries, quick)
    return DatasetReport(index, tuple(summaries))


# ----------------------------------------------------------------------------- the cross-scene figures
def summarize_scene(name: str, out: Path, markdown: Path | None, statuses: Mapping[str, str]) -> SceneSummary:
    """The index row of one scene from its cached measurements in ``out/measurements``."""
    from brave6d.evaluation.report import MeasurementStore

    store = MeasurementStore(Path(out) / "measurements")
    training, distance, realism = (store.load(n) for n in ("training", "distance", "realism"))
    psnr = _num(training.summary.get("psnr")) if training is not None and training.usable else math.nan
    ar, n = pooled_ar(distance.points) if distance is not None and distance.usable else (math.nan, 0)
    gaps = gap_by_ring(realism.points) if realism is not None and realism.usable else ()
    return SceneSummary(name, markdown, psnr, ar, n, gaps, dict(statuses))


def pooled_ar(points: Sequence[Mapping[str, Any]]) -> tuple[float, int]:
    """Mean AR over the distance study's target views with a finite AR, and how many there are."""
    values = [v for p in points if p.get("target") and math.isfinite(v := _num(p.get("ar")))]
    return (sum(values) / len(values), len(values)) if values else (math.nan, 0)


def gap_by_ring(points: Sequence[Mapping[str, Any]]) -> tuple[tuple[float, float], ...]:
    """Per capture ring (distance, ascending): mean AR on real minus mean AR on splat images over its targets."""
    rings: dict[float, tuple[list[float], list[float]]] = defaultdict(lambda: ([], []))
    for p in points:
        real, splat = rings[round(_num(p.get("distance_m")), 4)]
        for o in p.get("objects", []):
            if math.isfinite(r := _num(o.get("real_ar"))):
                real.append(r)
            if math.isfinite(s := _num(o.get("splat_ar"))):
                splat.append(s)
    return tuple((d, sum(r) / len(r) - sum(s) / len(s)) for d, (r, s) in sorted(rings.items())
                 if r and s and math.isfinite(d))


def write_index(workdir: Path, title: str, scenes: Sequence[SceneSummary], quick: bool) -> Path:
    """``WORKDIR/report/README.md``: a link to each scene's report and the cross-scene table."""
    root = report_root(workdir)
    rows = []
    for s in scenes:
        link = f"[{s.scene}]({s.report.relative_to(root).as_posix()})" if s.report is not None else s.scene
        gaps = "; ".join(f"{d * 100:.0f} cm: {g:+.3f}" for d, g in s.gap_by_ring) or "not measured"
        done = sum(v == "complete" for v in s.statuses.values())
        rows.append((link, _fmt(s.holdout_psnr, 2), f"{_fmt(s.distance_ar, 3)} ({s.distance_targets} views)"
                     if s.distance_targets else "not measured", gaps,
                     f"{done}/{len(s.statuses)}" if s.statuses else s.note or "-"))
    text = (f"# Reports of the dataset {title}\n\n"
            f"One accuracy-vs-time report per scene (`brave6d dataset report`, {'quick' if quick else 'full'} "
            "sweeps), each measured on its own scene directory; the table compares the scenes. Holdout PSNR: "
            "the trained splat on its held-out views; distance AR: the static estimator's BOP Average Recall "
            "pooled over the distance study's views; gap: AR on the captured frames minus AR on splat renders of "
            "the same views, per capture ring.\n\n"
            + format_table(["scene", "holdout PSNR [dB]", "distance-study AR", "real - splat AR gap per ring",
                            "sections complete"], rows) + "\n")
    root.mkdir(parents=True, exist_ok=True)
    return atomic_write_text(root / INDEX, text)


def _num(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _fmt(value: float, digits: int) -> str:
    return f"{value:.{digits}f}" if math.isfinite(value) else "n/a"

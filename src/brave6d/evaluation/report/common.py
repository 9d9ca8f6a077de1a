"""What every report section shares: the :class:`RenderedSection` it renders to, number formatting,
the "diminishing returns" rule behind its advice, and the notes for missing inputs and NaN."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.core.layout import FrameRecord, SceneDir
from brave6d.evaluation.metrics.pairing import paired_standard_error  # noqa: F401 (the sections import it from here)
from brave6d.evaluation.report.measurements import Measurement, describe_machine


@dataclass
class RenderedSection:
    """One section of the page: Markdown body, the PNGs it links, one sentence of advice."""

    title: str
    body: str
    advice: str = ""
    figures: list[Path] = field(default_factory=list)

    def markdown(self) -> str:
        return f"## {self.title}\n\n{self.body.strip()}\n"


def num(value: Any) -> float:
    """``value`` as a float; None, strings and other non-numbers become NaN."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    return float(value)


def fmt(value: Any, digits: int = 2) -> str:
    """Fixed-point text of a number (``n/a`` for None/NaN), the form used in tables and advice."""
    v = num(value)
    return "n/a" if not math.isfinite(v) else f"{v:.{digits}f}"


def finite(values: Sequence[Any]) -> np.ndarray:
    """The finite values of ``values`` as a float array (None and NaN dropped)."""
    arr = np.array([num(v) for v in values], dtype=np.float64)
    return arr[np.isfinite(arr)]


def mean(values: Sequence[Any]) -> float:
    """Mean of the finite values (NaN when there are none)."""
    a = finite(values)
    return float(np.mean(a)) if a.size else math.nan


def median(values: Sequence[Any]) -> float:
    """Median of the finite values (NaN when there are none)."""
    a = finite(values)
    return float(np.median(a)) if a.size else math.nan


def quantile(values: Sequence[Any], q: float) -> float:
    """Quantile ``q`` of the finite values (NaN when there are none)."""
    a = finite(values)
    return float(np.quantile(a, q)) if a.size else math.nan


def evenly_spaced(items: Sequence[Any], k: int) -> list[Any]:
    """``k`` of ``items`` at evenly spaced positions (all of them when ``k >= len``, none when ``k <= 0``)."""
    n = len(items)
    if k >= n:
        return list(items)
    return [items[math.floor((i + 0.5) * n / k)] for i in range(max(k, 0))]


def seconds_per_frame(records: Sequence[FrameRecord], level: int | None = None) -> float | None:
    """Median time-stamp gap before each frame (of ``level`` if given), in capture order: the robot
    time one more view costs (travel + settle + exposure). None without increasing time stamps."""
    ordered = sorted(records, key=lambda r: r.index)
    gaps = [b.timestamp - a.timestamp for a, b in zip(ordered, ordered[1:])
            if b.timestamp > a.timestamp and (level is None or b.distance_level == level)]
    return median(gaps) if gaps else None


def first_reaching(ys: Sequence[Any], target: float, higher_is_better: bool = True) -> int | None:
    """Index of the first finite ``y`` at least as good as ``target`` (None if none is)."""
    for i, y in enumerate(num(v) for v in ys):
        if math.isfinite(y) and (y >= target if higher_is_better else y <= target):
            return i
    return None


def calibrated_capture(scene: SceneDir) -> list[tuple[Path, str]]:
    """The files that give every captured frame its calibrated camera pose, with their stages."""
    return [(scene.frames_path, "capture"), (scene.intrinsics_path, "calibration"),
            (scene.handeye_path, "calibration")]


def unavailable(title: str, m: Measurement | None, what: str) -> RenderedSection:
    """The section text when its measurement is missing or failed: says what and why."""
    if m is None:
        reason = "nothing measured yet (run `brave6d report` without `--no-measure`)"
    elif m.status == "missing":
        reason = m.note or "an input is missing"
    elif m.status == "failed":
        reason = f"measuring failed: {m.note}"
    else:
        reason = "no points measured yet"
    return RenderedSection(title, f"> **Not available.** {what}: {reason}.\n")


def provenance(m: Measurement) -> str:
    """The line under a section: machine, settings and whether the sweep is complete."""
    settings = ", ".join(f"{k}={_short(v)}" for k, v in m.settings.items())
    state = "" if m.status == "complete" else f" **Partial sweep ({len(m.points)} points so far).**"
    return (f"*Machine:* {describe_machine(m.machine)}. *Settings:* {settings or 'none'}. "
            f"*Measured* {m.measured_at or 'at an unknown time'}"
            + (f" in {m.seconds:.1f} s." if m.seconds else ".") + state)


def settings_line(m: Measurement, keys: Sequence[str] | None = None) -> str:
    """Compact ``k=v`` list of (some of) a measurement's settings, for plot footers."""
    items = m.settings.items() if keys is None else ((k, m.settings.get(k)) for k in keys)
    return ", ".join(f"{k}={_short(v)}" for k, v in items)


def nan_note(dropped: int, what: str) -> str:
    """A sentence for the section when ``dropped`` values were NaN/missing and are not drawn."""
    if dropped <= 0:
        return ""
    return f"\n> Note: {dropped} {what} had no finite value (NaN or missing) and are not drawn.\n"


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "/".join(_short(v) for v in value)
    return str(value)

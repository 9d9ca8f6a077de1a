"""Plot primitives of the report (matplotlib, Agg): figures that state machine and settings,
and lines that never hide a NaN (the dropped points are counted in the legend and returned)."""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import ticker  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from brave6d.core.atomic import atomic_write  # noqa: E402
from brave6d.evaluation.report.common import num  # noqa: E402

DPI = 110


def new_figure(ncols: int, nrows: int = 1, panel: tuple[float, float] = (4.3, 3.3)) -> tuple[Figure, list[Axes]]:
    """A figure of ``nrows x ncols`` panels (flat list of axes, row by row), grids on."""
    fig, axes = plt.subplots(nrows, ncols, figsize=(panel[0] * ncols, panel[1] * nrows + 0.9), squeeze=False)
    flat = [ax for row in axes for ax in row]
    for ax in flat:
        ax.grid(alpha=0.3)
    return fig, flat


def finite_pairs(xs: Sequence[Any], ys: Sequence[Any]) -> tuple[list[float], list[float], int]:
    """The ``(x, y)`` pairs where both are finite numbers, and how many pairs were dropped."""
    keep = [(num(x), num(y)) for x, y in zip(xs, ys)]
    good = [(x, y) for x, y in keep if math.isfinite(x) and math.isfinite(y)]
    return [x for x, _ in good], [y for _, y in good], len(keep) - len(good)


def plot_line(ax: Axes, xs: Sequence[Any], ys: Sequence[Any], label: str | None = None, fmt: str = "o-",
              **kwargs: Any) -> int:
    """Draw the finite points of a series; returns the number of dropped (NaN/None) points.

    Dropped points are named in the legend label (``"... (2 NaN not drawn)"``) so that a gap
    never passes silently; a series with no finite point is listed as such.
    """
    x, y, dropped = finite_pairs(xs, ys)
    if dropped and label is not None:
        label = f"{label} ({dropped} NaN not drawn)"
    if x:
        ax.plot(x, y, fmt, label=label, **kwargs)
    elif label is not None:  # keep the series visible in the legend
        ax.plot([], [], fmt, label=f"{label}: no finite values", **kwargs)
    return dropped


def plot_band(ax: Axes, xs: Sequence[Any], lo: Sequence[Any], hi: Sequence[Any], **kwargs: Any) -> None:
    """Shade between ``lo`` and ``hi`` where all three are finite (an inter-quartile band)."""
    rows = [(num(x), num(a), num(b)) for x, a, b in zip(xs, lo, hi)]
    rows = [r for r in rows if all(math.isfinite(v) for v in r)]
    if rows:
        ax.fill_between([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], alpha=0.2,
                        linewidth=0, **kwargs)


def save_figure(fig: Figure, path: Path, title: str, machine: str, settings: str) -> Path:
    """Title on top, machine and settings as a footer; written atomically as PNG, then closed."""
    fig.suptitle(title, fontsize=11)
    width = int(fig.get_figwidth() * 16)  # characters of the 7-point footer per line
    footer = textwrap.fill(f"machine: {machine}", width) + "\n" + textwrap.fill(f"settings: {settings}", width)
    fig.text(0.005, 0.005, footer, fontsize=7, color="0.3", va="bottom", ha="left")
    n_lines = footer.count("\n") + 1
    bottom = min(0.35, (0.1 + 0.13 * n_lines) / fig.get_figheight())
    fig.tight_layout(rect=(0, bottom, 1, 0.95))
    try:
        atomic_write(path, lambda handle: fig.savefig(handle, format="png", dpi=DPI))
    finally:
        plt.close(fig)
    return path


def compact(value: float, _pos: object = None) -> str:
    """Tick text: ``200``, ``0.05``, ``20k``, ``1.5M`` (no powers of ten, no crowded zeros)."""
    for limit, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= limit:
            return f"{value / limit:g}{suffix}"
    return f"{value:g}"


def compact_xticks(ax: Axes) -> None:
    """Label the x axis with :func:`compact` numbers (``100k`` instead of ``100000``)."""
    ax.xaxis.set_major_formatter(ticker.FuncFormatter(compact))


def log_axes(ax: Axes) -> None:
    """Log-log axes labelled with plain numbers (``200``, ``20k``) instead of powers of ten."""
    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(ticker.LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(ticker.FuncFormatter(compact))
        axis.set_minor_formatter(ticker.NullFormatter())


def legend(ax: Axes) -> None:
    """A small legend, only when the axes have labelled artists."""
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(fontsize=7)

"""Logging and progress conventions shared by every stage.

- Messages go through :mod:`logging` (logger per module, ``brave6d`` format, stderr).
- Long loops use :func:`progress`: a tqdm bar with rate and ETA on stderr; in a non-interactive
  run (CI, a log file) it prints a line at most every few seconds instead of redrawing.
- A stage reports what it did as a :class:`StageResult`; the demo prints them as one table.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")

LOG_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


def setup_logging(verbosity: int = 0) -> None:
    """Configure root logging once: WARNING by default, INFO with -v, DEBUG with -vv."""
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, format=LOG_FORMAT, datefmt="%H:%M:%S", stream=sys.stderr, force=True)
    for noisy in ("matplotlib", "PIL", "numba", "urllib3", "httpx", "trimesh"):
        logging.getLogger(noisy).setLevel(max(level, logging.WARNING))


def progress(
    iterable: Iterable[T],
    total: int | None = None,
    desc: str = "",
    unit: str = "it",
    initial: int = 0,
    disable: bool | None = None,
) -> Iterator[T]:
    """Wrap ``iterable`` in a progress bar with ETA (stderr).

    ``initial`` counts items already done (resumed jobs), so the ETA stays honest.
    """
    interactive = sys.stderr.isatty()
    return iter(
        tqdm(
            iterable,
            total=total,
            desc=desc,
            unit=unit,
            initial=initial,
            disable=disable,
            dynamic_ncols=True,
            mininterval=0.2 if interactive else 5.0,
            file=sys.stderr,
            leave=True,
        )
    )


def progress_bar(total: int, desc: str = "", unit: str = "it", initial: int = 0, position: int | None = None) -> tqdm:
    """A manual progress bar (call ``.update(n)``, ``.set_postfix(...)``, ``.close()``); ``position``:
    its line when several run at once."""
    interactive = sys.stderr.isatty()
    return tqdm(total=total, desc=desc, unit=unit, initial=initial, dynamic_ncols=True, position=position,
                mininterval=0.2 if interactive else 5.0, file=sys.stderr)


@dataclass
class StageResult:
    """What one pipeline stage did: its name, wall time, status and a few key figures."""

    name: str
    seconds: float = 0.0
    status: str = "ok"
    figures: dict[str, Any] = field(default_factory=dict)

    def figures_text(self) -> str:
        return ", ".join(f"{k}={_fmt(v)}" for k, v in self.figures.items())


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


class Stopwatch:
    """Context manager measuring wall time in seconds (``.seconds``)."""

    def __enter__(self) -> Stopwatch:
        self._start = time.perf_counter()
        self.seconds = 0.0
        return self

    def __exit__(self, *exc: object) -> None:
        self.seconds = time.perf_counter() - self._start


def format_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A plain-text table (also valid Markdown) with columns padded to their widest cell."""
    cells = [[_fmt(c) for c in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]
    line = "| " + " | ".join(h.ljust(w) for h, w in zip(headers, widths)) + " |"
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    body = ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |" for r in cells]
    return "\n".join([line, sep, *body])

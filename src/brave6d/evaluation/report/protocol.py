"""The :class:`Section` protocol: what one section of the report provides to the page.

A section owns one measurement (``report/measurements/<name>.json``), its settings with their
defaults, the figure it draws and its part of the page. :mod:`brave6d.evaluation.report.build` knows
sections only through this protocol and the registry in :mod:`brave6d.evaluation.report.sections`;
docs/ARCHITECTURE.md shows how to add one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from brave6d.core.layout import SceneDir
from brave6d.evaluation.report.common import RenderedSection
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore


@dataclass(frozen=True)
class MeasureInputs:
    """What a section may measure from: the work directory, its scene, the measurement cache and
    the learned model's folder (None: the demo's, ``<workdir>/learned/model``)."""

    workdir: Path
    scene: SceneDir
    store: MeasurementStore
    learned_model: Path | None = None


class Section(Protocol):
    """One section of the report (see the module docstring)."""

    #: The measurement's name: ``report/measurements/<name>.json`` and the ``--only`` choice.
    name: str
    #: Position on the page (1 = first); the title starts with it.
    page: int
    #: The page heading, ``"<page>. <what>"``.
    title: str
    #: The PNG the section writes beside ``report.md``.
    figure: str

    def settings(self, quick: bool) -> Any:
        """The section's default settings (a frozen dataclass, or None when it has none);
        ``quick``: the miniature variant of ``brave6d report --mode quick`` (CI)."""
        ...

    def measure(self, inputs: MeasureInputs, settings: Any) -> Measurement:
        """Measure (or reuse from ``inputs.store``) the section's data; a missing input gives a
        measurement that says so rather than an exception."""
        ...

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        """The section's Markdown (and figure in ``out_dir``) from the cached measurements (any may be None)."""
        ...

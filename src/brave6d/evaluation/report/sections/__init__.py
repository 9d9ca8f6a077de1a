"""The report's sections, registered once.

Each module here defines one section behind the :class:`~brave6d.evaluation.report.protocol.Section`
protocol as its ``SECTION``; :data:`SECTIONS` lists them in measuring order (cheap first),
:func:`page_order` in the order of the page. Adding a section is one module here and its name
in :data:`MODULES`; nothing else in the report changes (docs/ARCHITECTURE.md, section 6).
"""

from __future__ import annotations

from importlib import import_module

from brave6d.evaluation.report.protocol import Section

#: Section modules in measuring order; each defines ``SECTION``.
MODULES = ("handeye", "latency", "views", "training", "baseline", "synthesis", "distance", "realism", "fidelity",
           "learned")

SECTIONS: tuple[Section, ...] = tuple(import_module(f"{__name__}.{module}").SECTION for module in MODULES)


def page_order() -> list[Section]:
    """The sections in the order of the page (by their ``page`` number)."""
    return sorted(SECTIONS, key=lambda s: s.page)


def names() -> tuple[str, ...]:
    """The sections' measurement names in page order (the ``--only`` choices)."""
    return tuple(s.name for s in page_order())

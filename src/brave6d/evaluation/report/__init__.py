"""``brave6d report``: the accuracy-vs-time page, from cached measurements of the demo scene.

Public API (imported lazily, so importing the package loads neither matplotlib nor torch):
``build_report`` (measure what is not cached, then write the page), ``write_report`` (the page
from the cache alone), ``ReportSettings``, ``ReportTarget`` (any scene directory and output folder); for writing a section: the ``Section`` protocol,
``MeasureInputs``, ``RenderedSection``, ``Measurement`` and ``MeasurementStore``. The sections
themselves are registered in :mod:`brave6d.evaluation.report.sections` (see docs/ARCHITECTURE.md).
"""

from brave6d.core.lazy import lazy_exports

__all__ = ["Measurement", "MeasurementStore", "MeasureInputs", "RenderedSection", "ReportSettings", "ReportTarget", "Section",
           "build_report", "write_report"]

_LAZY = {
    "build_report": ".build",
    "write_report": ".build",
    "ReportSettings": ".build",
    "ReportTarget": ".build",
    "Section": ".protocol",
    "MeasureInputs": ".protocol",
    "RenderedSection": ".common",
    "Measurement": ".measurements",
    "MeasurementStore": ".measurements",
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

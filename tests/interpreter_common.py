"""What the Triton-interpreter case scripts (``*_interpreter_cases.py``) share: hypothesis settings
for a few derandomised draws (the interpreter is slow) and the JSON report they write."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from hypothesis import HealthCheck, settings

#: a handful of reproducible draws, no example database (each runs the kernel in NumPy)
FEW_DRAWS = settings(max_examples=5, deadline=None, derandomize=True, database=None,
                     suppress_health_check=list(HealthCheck))


def write_report(out_path: str, named: dict[str, Any], run_drawn: Callable[[], None], drawn: list[Any]) -> int:
    """Run the hypothesis-drawn cases (``run_drawn`` appends to ``drawn``), then write the report."""
    run_drawn()
    with open(out_path, "w") as f:
        json.dump({**named, "hypothesis": drawn}, f, indent=1)
    return 0

"""How a training run ended, in words: the steps it reached and planned, what stopped it, and for a run
its time budget stopped, the one line that says how to continue.

``brave6d train``'s summary and the pipeline's train stage (:mod:`brave6d.training.demo`) both word a
run's ``metrics.json`` through these, so the terminal and the demo's stage line say the same.
"""

from __future__ import annotations

import math
from pathlib import Path


def steps_text(metrics: dict) -> str:
    """``631 of 2000 planned steps (stopped by the time budget: 840 s, the whole command)``."""
    planned = metrics.get("planned_steps")
    done = metrics["steps"]
    text = f"{done} of {planned} planned steps" if planned is not None else f"{done} steps"
    stopped = metrics.get("stopped_by")
    budget = metrics.get("time_budget") or {}
    if stopped == "time budget" and budget.get("budget_s") is not None:
        return text + f" (stopped by the time budget: {budget['budget_s']:.0f} s, the whole command)"
    return text + (f" (stopped by {stopped})" if stopped and stopped != "steps" else " (all planned steps)")


def budget_stop_line(metrics: dict, scene_dir: Path | str, preset: str = "fast",
                     steps: int | None = None) -> str | None:
    """One line for a run its time budget stopped: how far short it is and the command that continues it
    (``--resume`` with enough time for the steps left at this run's pace); None when it finished."""
    if metrics.get("stopped_by") != "time budget":
        return None
    done, planned = int(metrics["steps"]), int(metrics.get("planned_steps") or metrics["steps"])
    budget = float((metrics.get("time_budget") or {}).get("budget_s") or 0.0)
    command = f"brave6d train {scene_dir} --preset {preset}{f' --steps {steps}' if steps is not None else ''} --resume"
    head = f"stopped by the time budget ({budget:.0f} s) after {done} of {planned} steps, {planned - done} short"
    if done == 0:  # no pace to go by: the initialisation took the budget (a resumed run does not redo it)
        return (f"{head} (loading and the initial points took {float(metrics.get('init_time_s', 0.0)):.0f} s of "
                f"it): continue with {command} (another {budget:.0f} s; --time-budget SECONDS for more)")
    per_step = float(metrics["train_time_s"]) / done
    # the steps left at this pace, 10 % more, and a minute to load the images again
    more = int(math.ceil(((planned - done) * per_step * 1.1 + 60.0) / 60.0) * 60)
    return (f"{head} (about {_duration((planned - done) * per_step)} more at {per_step:.2f} s per step): "
            f"continue with {command} --time-budget {more}")


def _duration(seconds: float) -> str:
    """``12 s`` under a minute and a half, else ``27 min``."""
    return f"{seconds:.0f} s" if seconds < 90.0 else f"{seconds / 60.0:.0f} min"

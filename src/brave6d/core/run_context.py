"""What the stages of one pipeline run share: the typed context every stage function receives.

A stage is a function ``stage(ctx: RunContext) -> StageResult`` in its own package; the
orchestrator (:mod:`brave6d.pipeline`) names it as ``"module:function"`` and runs it with one
:class:`RunContext`, whether the run is ``brave6d demo`` or one scene's job of ``brave6d dataset
run``. The type lives in the core so that stages can name it without importing the floor above them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from brave6d.core.layout import SceneDir
from brave6d.core.progress import StageResult
from brave6d.core.spec import SceneSpec

#: What ``--quick`` changes in a scene's capture: few views on two rings (CI's miniature runs).
QUICK_CAPTURE = {"distances_m": [0.3, 0.45], "views_per_distance": 10}


@dataclass
class RunContext:
    """One run of the pipeline on one scene directory.

    ``workdir``: where the run keeps what is not the scene's (report caches, scratch); ``quick``:
    the miniature settings every stage has (few views, steps and pixels); ``device``: ``auto``,
    ``cpu`` or ``cuda``; ``obj_ids``: object name -> BOP ``obj_id`` fixed by a dataset's library
    (None: the scene numbers its own objects); ``resume``: continue a training from its checkpoints
    (a dataset job requeued after a preemption); ``results``: the stages' results so far, in order.
    """

    workdir: Path
    scene: SceneDir
    spec: SceneSpec
    quick: bool = False
    device: str = "auto"
    obj_ids: dict[str, int] | None = None
    resume: bool = False
    results: list[StageResult] = field(default_factory=list)

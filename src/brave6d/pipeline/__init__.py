"""The pipeline: the floor above the stages that runs them in order on one scene.

Public API (importing it loads no stage):

- ``RunContext`` (what the stages of one run share and what the run chose: rig, training preset,
  device, resume, quick; built with ``RunContext.for_scene``; defined in ``brave6d.core.run_context``
  so that stages and their commands can name it), ``Rig``, ``SIM_RIG``, ``DEVICES``, ``QUICK_CAPTURE``;
- ``Stage``, ``STAGES`` (pipeline order, each stage as ``"module:function"``), ``stage_named``,
  ``run_stages``, ``summary_table``.

``brave6d demo`` (:mod:`brave6d.pipeline.demo`) is one configuration of it: the embedded demo scene
on the simulated rig. ``brave6d dataset run`` runs the same stages per scene with the same
constructor (``RunContext.for_scene``), and so do the rig's commands (``brave6d capture run``,
``brave6d calibrate``, with ``--robot`` / ``--camera``); ``brave6d train`` resolves ``--preset``
as the training stage does.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "RunContext": "brave6d.core.run_context", "QUICK_CAPTURE": "brave6d.core.run_context",
    "Rig": "brave6d.core.run_context", "SIM_RIG": "brave6d.core.run_context", "DEVICES": "brave6d.core.run_context",
    "Stage": ".stages", "STAGES": ".stages", "stage_named": ".stages", "run_stages": ".stages",
    "summary_table": ".stages",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

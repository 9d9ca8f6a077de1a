"""The learned baseline as agents: the detector + coordinate net (:mod:`brave6d.evaluation.learned`)
playing the benchmark through the same :class:`~brave6d.evaluation.agents.Agent` protocol as the
weight-free baselines.

- :class:`LearnedAgent` with ``active=False`` (``learned-static``: estimates from the start view)
  or ``active=True`` (``learned-active``: moves until its detection is confident and large
  enough, the paper's convergence criterion, then estimates); ``use_depth`` refines the RGB
  pose's translation with the served depth (the ``-depth`` variants, reported separately);
- :class:`LearnedAgentOptions`: the thresholds and moves;
- ``fusion``: what several views give that one cannot (the object's position triangulated from
  the views' rays, for the RGB-only active agent).

The registry (:data:`brave6d.evaluation.agents.POLICIES`) builds them from a trained model folder
given in :class:`brave6d.evaluation.agents.AgentSetup`.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {"LearnedAgent": ".agent", "LearnedAgentOptions": ".agent"}

__all__ = sorted(_LAZY)

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

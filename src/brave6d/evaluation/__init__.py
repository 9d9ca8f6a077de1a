"""Evaluation stage: metrics and episode scoring, agents, and the accuracy-vs-time report.

Three subpackages, each with its own public API in its ``__init__``:

- :mod:`brave6d.evaluation.metrics`: BOP19 metrics and Average Recall, BOP results files, episode-log
  scoring and the leaderboard;
- :mod:`brave6d.evaluation.agents`: the agents that play episodes through ``serve``'s client;
- :mod:`brave6d.evaluation.report`: ``brave6d report``, the accuracy-vs-time page.

Plus ``brave6d.evaluation.cli`` (``brave6d evaluate EPISODE_LOGS``) and ``brave6d.evaluation.demo`` (the demo's
evaluation stage). The names most callers need are re-exported here, lazily (importing the package
stays cheap): ``evaluate_bop19``, ``EvalConfig``, ``read_episodes``, ``score_episodes``,
``models_from_bundle``, ``write_leaderboard``, ``Leaderboard``, ``read_bop_results``,
``write_bop_results``.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {name: ".metrics" for name in (
    "evaluate_bop19", "EvalConfig", "read_episodes", "score_episodes", "models_from_bundle",
    "write_leaderboard", "Leaderboard", "read_bop_results", "write_bop_results")}

__all__ = sorted(_LAZY)

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

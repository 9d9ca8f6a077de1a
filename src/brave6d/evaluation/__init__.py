"""Evaluation stage: metrics and episode scoring, agents, and the accuracy-vs-time report.

Three subpackages, each with its own public API in its ``__init__``:

- :mod:`brave6d.evaluation.metrics`: BOP19 metrics and Average Recall, BOP results files, episode-log
  scoring and the leaderboard;
- :mod:`brave6d.evaluation.agents`: the agents that play episodes through ``serve``'s client;
- :mod:`brave6d.evaluation.report`: ``brave6d report``, the accuracy-vs-time page.

Plus ``brave6d.evaluation.cli`` (``brave6d evaluate EPISODE_LOGS``), ``brave6d.evaluation.demo`` (the demo's
evaluation stage), ``brave6d.evaluation.estimate_bop`` (the static estimator over a BOP split) and
``brave6d.evaluation.estimate_cli`` (``brave6d estimate frame|bop``). The names most callers need are
re-exported here, lazily (importing the package stays cheap): ``evaluate_bop19``, ``EvalConfig``,
``read_episodes``, ``score_episodes``, ``models_from_bundle``, ``write_leaderboard``, ``Leaderboard``,
``read_bop_results``, ``write_bop_results``; the static estimator on any RGB-D frame:
``estimate_pose``, ``prepare_model``, ``read_depth_png``, ``PixelHint``, ``BoxHint``, ``FrameOptions``,
``FramePose``, ``EstimateRefused``, ``REFUSAL_CAUSES``; over a BOP split: ``estimate_bop_split``, ``SplitRun``.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {name: ".metrics" for name in (
    "evaluate_bop19", "EvalConfig", "read_episodes", "score_episodes", "models_from_bundle",
    "write_leaderboard", "Leaderboard", "read_bop_results", "write_bop_results")}
_LAZY.update({name: ".agents" for name in (
    "estimate_pose", "prepare_model", "read_depth_png", "PixelHint", "BoxHint", "FrameOptions", "FramePose",
    "EstimateRefused", "REFUSAL_CAUSES")})
_LAZY.update({name: ".estimate_bop" for name in ("estimate_bop_split", "SplitRun")})

__all__ = sorted(_LAZY)

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

"""Metrics and episode scoring: BOP19 pose errors and Average Recall, BOP results files, the
CPU depth renderer VSD needs, and the leaderboard of the render server's episode logs.

Public API (imported lazily: ``import brave6d.evaluation.metrics`` loads neither Open3D nor trimesh):

- Average Recall: ``evaluate_bop19``, ``EvalConfig``, ``Estimate``, ``GTInstance``, ``ObjectModel``,
  ``BopScores``, ``METRICS``;
- pose errors (BOP units, mm): ``vsd``, ``mssd``, ``mspd``, ``VSD_TAUS``, ``identity_symmetries``;
- depth rendering for VSD: ``DepthRenderer``, ``render_depth``;
- BOP results CSV and scoring inputs from BOP folders: ``read_bop_results``, ``write_bop_results``,
  ``format_results_csv``, ``check_times``, ``load_scene_gt_instances``, ``load_split_gt_instances``,
  ``load_models``, ``load_ply_mesh`` (the dataset's JSON files are parsed by ``annotation``);
- episode scoring: ``read_episodes``, ``read_episode``, ``find_episode_logs``, ``score_episodes``,
  ``episode_to_bop``, ``models_from_bundle``, ``write_leaderboard``, ``EpisodeRecord``,
  ``Leaderboard``, ``AgentScore``, ``EpisodeScore``, ``GroupScore`` (an agent's AR per scene / category),
  ``rank_episodes`` and ``NotRanked`` (which episodes a scored or training leaderboard ranks, and why not);
- the agent-run summary (``<workdir>/evaluation/baseline.json``): ``AgentRuns``, ``AgentRunsRow``,
  ``AgentRunsEpisode``, ``AGENT_RUNS_FORMAT``, ``agent_runs_from_board``, ``agent_runs_path``,
  ``read_agent_runs``, ``write_agent_runs``.

Modules: ``bop_metrics`` (VSD/MSSD/MSPD, symmetries), ``recall`` (matching and AR),
``depth_renderer``, ``bop_results`` (results CSV, BOP folders as scoring inputs), ``episodes``
(episode logs -> leaderboard; the log schema is serve's), ``agent_runs`` (the agent-run summary file).
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "evaluate_bop19": ".recall", "EvalConfig": ".recall", "Estimate": ".recall", "GTInstance": ".recall",
    "ObjectModel": ".recall", "BopScores": ".recall", "METRICS": ".recall",
    "vsd": ".bop_metrics", "mssd": ".bop_metrics", "mspd": ".bop_metrics", "VSD_TAUS": ".bop_metrics",
    "identity_symmetries": ".bop_metrics",
    "DepthRenderer": ".depth_renderer", "render_depth": ".depth_renderer",
    "read_bop_results": ".bop_results", "write_bop_results": ".bop_results", "format_results_csv": ".bop_results",
    "check_times": ".bop_results", "load_scene_gt_instances": ".bop_results",
    "load_split_gt_instances": ".bop_results", "load_models": ".bop_results", "load_ply_mesh": ".bop_results",
    "read_episodes": ".episodes", "read_episode": ".episodes", "find_episode_logs": ".episodes",
    "score_episodes": ".episodes", "episode_to_bop": ".episodes", "models_from_bundle": ".episodes",
    "write_leaderboard": ".episodes", "EpisodeRecord": ".episodes", "Leaderboard": ".episodes",
    "AgentScore": ".episodes", "EpisodeScore": ".episodes", "GroupScore": ".episodes",
    "rank_episodes": ".episodes", "NotRanked": ".episodes",
    "AgentRuns": ".agent_runs", "AgentRunsRow": ".agent_runs", "AgentRunsEpisode": ".agent_runs",
    "AGENT_RUNS_FORMAT": ".agent_runs", "agent_runs_from_board": ".agent_runs", "agent_runs_path": ".agent_runs",
    "read_agent_runs": ".agent_runs", "write_agent_runs": ".agent_runs",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

"""evaluation stage: BOP19 pose metrics and Average Recall, BOP results files, depth rendering.

- :mod:`evaluation.metrics.bop_metrics`: VSD, MSSD, MSPD pose errors and symmetry sets (BOP units, mm).
- :mod:`evaluation.metrics.recall`: :func:`~evaluation.metrics.recall.evaluate_bop19` and its input/output dataclasses.
- :mod:`evaluation.metrics.bop_results`: results CSV read/write, BOP scene and model folder readers.
- :mod:`evaluation.metrics.depth_renderer`: CPU z-depth rendering of object meshes for VSD (Open3D ray casting).
- :mod:`evaluation.metrics.episodes`: score the render server's episode logs (AR, adjustments, wall time).
- :mod:`evaluation.agents.baseline`: the weight-free active and static baseline agents.
- :mod:`evaluation.cli`: ``brave6d evaluate EPISODE_LOGS`` (leaderboard table, CSV, JSON).
- :mod:`evaluation.demo`: the demo's evaluation stage (both baselines on every object).
- :mod:`evaluation.report` and ``evaluation.report_*``: ``brave6d report``, the accuracy-vs-time page.

Modules are imported explicitly (``from evaluation.metrics.recall import evaluate_bop19``) so that
importing the package stays cheap.
"""

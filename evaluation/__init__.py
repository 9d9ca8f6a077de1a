"""evaluation stage: BOP19 pose metrics and Average Recall, BOP results files, depth rendering.

- :mod:`evaluation.bop_metrics`: VSD, MSSD, MSPD pose errors and symmetry sets (BOP units, mm).
- :mod:`evaluation.recall`: :func:`~evaluation.recall.evaluate_bop19` and its input/output dataclasses.
- :mod:`evaluation.bop_results`: results CSV read/write, BOP scene and model folder readers.
- :mod:`evaluation.renderer`: CPU z-depth rendering of object meshes for VSD (Open3D ray casting).

Modules are imported explicitly (``from evaluation.recall import evaluate_bop19``) so that
importing the package stays cheap.
"""

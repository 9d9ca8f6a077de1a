"""training stage: 3DGS model, rasterizer backends, trainer, evaluation, PLY export.

Public API (imported lazily, so `import training` stays cheap: no torch / numba import):
``rasterize``, ``train_scene``, ``GaussianModel``, ``read_ply``, ``write_ply``, ``SplatData``,
``SH_C0``, ``sh_degree_for``, ``holdout_split``, ``get_preset``. Other stages (serve, evaluation)
import only these names.
"""

from importlib import import_module
from typing import Any

__all__ = ["SH_C0", "GaussianModel", "SplatData", "get_preset", "holdout_split", "rasterize", "read_ply",
           "sh_degree_for", "train_scene", "write_ply"]

_LAZY = {
    "rasterize": ".rasterizer",
    "train_scene": ".pipeline",
    "GaussianModel": ".model",
    "read_ply": ".ply",
    "write_ply": ".ply",
    "SplatData": ".ply",
    "SH_C0": ".ply",
    "sh_degree_for": ".ply",
    "holdout_split": ".dataset",
    "get_preset": ".presets",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module 'training' has no attribute {name!r}")

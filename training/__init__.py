"""training stage: 3DGS model, rasterizer backends, trainer, evaluation, PLY export.

Public API (imported lazily, so `import training` stays cheap: no torch / numba import):
``rasterize``, ``train_scene``, ``GaussianModel``, ``read_ply``, ``write_ply``, ``get_preset``.
"""

from importlib import import_module
from typing import Any

__all__ = ["GaussianModel", "get_preset", "rasterize", "read_ply", "train_scene", "write_ply"]

_LAZY = {
    "rasterize": ".rasterizer",
    "train_scene": ".pipeline",
    "GaussianModel": ".model",
    "read_ply": ".ply",
    "write_ply": ".ply",
    "get_preset": ".presets",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module 'training' has no attribute {name!r}")

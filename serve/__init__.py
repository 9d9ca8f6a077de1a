"""Serve stage: scene bundles, the render server, its Python client, a Gymnasium-style environment
and a browser viewer.

Modules (import them directly; this package imports nothing heavy):

- :mod:`serve.bundle`: ``export_bundle(scene_dir)`` -> ``<scene>/bundle`` (checksummed manifest),
  ``load_bundle(path)`` (refuses a bundle whose checksums do not match).
- :mod:`serve.limits`: the image-size cap and the bounds on poses and twists (one place for all).
- :mod:`serve.geometry`: camera collision sphere vs oriented boxes, workspace, twist integration.
- :mod:`serve.renderer`: the splat on ``cuda``/``cpu``, one view per call with ``training.rasterize``.
- :mod:`serve.splat_check`: ``check_splat`` refuses a splat with NaN/inf, no Gaussians or none
  visible (export and the renderer's loading call it).
- :mod:`serve.visibility`: visible fraction of each object (Open3D ray casting + splat depth).
- :mod:`serve.episodes`: episode state machine, refusals, adjustment counting, JSONL logs.
- :mod:`serve.app`: ``create_app(bundle)``, the FastAPI app (REST + WebSocket + viewer).
- :mod:`serve.client`: ``BraveClient`` (httpx), observations as NumPy arrays.
- :mod:`serve.gym_env`: ``BraveEnv`` (``reset``/``step`` like Gymnasium).
- :mod:`serve.runner`: uvicorn in the foreground or a background thread (``ServerThread``).
- :mod:`serve.cli`, :mod:`serve.export_cli`: ``brave6d serve BUNDLE``, ``brave6d export SCENE_DIR``.
- :mod:`serve.demo`: the demo's ``stage_export`` and ``stage_serve``.
- :mod:`serve.synthetic`: a small synthetic scene and bundle for tests and benchmarks.
- ``serve/viewer/``: the static browser viewer served at ``/viewer/``.
"""

from importlib import import_module
from typing import Any

#: The public names, imported lazily (``import serve`` stays cheap: no torch, no FastAPI).
_LAZY = {"SplatRenderer": ".renderer"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module 'serve' has no attribute {name!r}")

"""The scenes a serving command serves: a bundle folder's, or every scene of a dataset release.

The top floor may import every stage, so the choice between the two formats and their owners
meet here: :func:`brave6d.serve.is_bundle` and :func:`brave6d.serve.bundle_scene_source` for a
bundle, :func:`brave6d.dataset.release_scene_sources` for a release (the release folder that
``brave6d release build`` wrote, or the unzipped dataset).
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from brave6d.core.errors import BraveError

if TYPE_CHECKING:
    from brave6d.serve import SceneSource


def scene_sources(path: Path | str, cache_dir: Path | str | None = None) -> list[SceneSource]:
    """The scene sources of ``path``: one for a bundle folder, one per scene of a release (its bundle
    zips unpacked into ``cache_dir`` on first use; see :func:`brave6d.dataset.release_scene_sources`)."""
    from brave6d.serve import bundle_scene_source, is_bundle

    root = Path(path)
    if not root.exists():
        raise BraveError(f"{root}: no such bundle or release")
    if is_bundle(root):
        return [bundle_scene_source(root)]
    from brave6d.dataset import release_scene_sources

    return release_scene_sources(root, cache_dir=cache_dir)


def serving_run(module: str) -> Callable[[argparse.Namespace], int]:
    """The ``run(args)`` of a serving command: ``module``'s ``run(args, sources_of)`` (imported when
    the command runs) with :func:`scene_sources` handed to it."""
    def run(args: argparse.Namespace) -> int:
        return int(importlib.import_module(module).run(args, scene_sources))

    return run

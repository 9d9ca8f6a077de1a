"""Dataset releases: ``brave6d release build`` packages a dataset work directory as BOP-style zips
plus one render-server bundle per scene, checksums, a manifest and a dataset card;
``brave6d release verify`` checks a release folder completely.

Public API (imported lazily: ``import brave6d.dataset.release`` loads no torch):

- ``build_release``, ``ReleaseResult``; ``verify_release``, ``VerifyReport``; ``ReleaseError``;
- ``load_release_source``, ``ReleaseSource``, ``SceneSource``, ``LibraryObject`` (what a release is
  built from: the one reader of ``WORKDIR/dataset.yaml`` in this package);
- the release's files: ``read_sha256sums``, ``read_targets``, ``read_holdout``, ``read_manifest``;
- serving a release: ``release_scene_sources`` (one ``brave6d.serve.SceneSource`` per scene; bundle zips are
  unpacked into a cache on first use), ``default_cache_dir``.

The modules behind them, one job each: ``source`` (dataset.yaml -> scenes and library),
``collect`` (read and check each scene's BOP export, bundle, holdout and statistics), ``zips``
(the project's one zip module: streamed, reproducible writing, and the one safe reader and
unpacker with its size policy ``ZipLimits``: every member checked to stay inside its folder, sizes
checked from the headers and again while streaming), ``images`` (every PNG of a release decoded
or header-checked, through ``brave6d.core.png_check``), ``formats`` (file names, SHA256SUMS, targets,
holdout.json), ``manifest`` (manifest.json), ``card`` (the dataset card), ``train_pbr`` and ``learned``
(the synthetic split and the learned model, when the work directory has them), ``ros2_wheel`` (the
ROS 2 interfaces wheel for agents, when a ROS 2 Python can build it), ``build``, ``verify``,
``serving`` (the scenes of a release for ``brave6d serve``: the cache folder checked at start,
bundles unpacked on first use and again by ``refresh``), ``cli``.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "build_release": ".build", "ReleaseResult": ".build", "verify_release": ".verify", "VerifyReport": ".verify",
    "ReleaseError": ".source", "load_release_source": ".source", "ReleaseSource": ".source",
    "SceneSource": ".source", "LibraryObject": ".source",
    "read_sha256sums": ".formats", "read_targets": ".formats", "read_holdout": ".formats",
    "read_manifest": ".manifest", "release_scene_sources": ".serving", "default_cache_dir": ".serving",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

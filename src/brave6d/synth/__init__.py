"""Synth stage: a synthetic training split (BOP ``train_pbr``) rendered by the project's CPU renderer.

Public API (imported lazily, so ``import synth`` costs no Open3D or trimesh):

- the run: ``synthesize``, ``SynthOptions``, ``SynthResult`` (``brave6d synth``);
- its inputs: ``load_synth_source``, ``SynthSource``, ``SynthObject`` (a dataset's or scene's
  object library, camera, capture distances and effects);
- randomisation: ``Randomization``, ``sample_image_scene``, ``ImageScene``, ``LibraryAssets``,
  ``image_rng``;
- placement: ``resting_poses``, ``RestingPoses``, ``place_on_plane``, ``Placement``;
- rendering and files: ``render_image``, ``RenderedImage``, ``SPLIT``, ``image_address``,
  ``image_problem`` (is an image written before complete and whole: what a resumed run checks).

The modules behind them, one job each: ``source`` (the spec), ``placement`` (resting poses without
interpenetration), ``randomize`` (one image's random scene), ``render`` (SimCamera + ground truth),
``writer`` (the train_pbr files, resumable records, ``synth.json``; an image whose files fail their
check is rendered again on resume: :mod:`brave6d.core.png_check`),
``limits`` (the bounds of the flags and the memory/CPU check at start), ``run`` (workers, progress),
``cli``.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "synthesize": ".run", "SynthOptions": ".run", "SynthResult": ".run",
    "load_synth_source": ".source", "SynthSource": ".source", "SynthObject": ".source",
    "Randomization": ".randomize", "sample_image_scene": ".randomize", "ImageScene": ".randomize",
    "LibraryAssets": ".randomize", "image_rng": ".randomize",
    "resting_poses": ".placement", "RestingPoses": ".placement", "place_on_plane": ".placement",
    "Placement": ".placement",
    "render_image": ".render", "RenderedImage": ".render", "SPLIT": ".writer", "image_address": ".writer",
    "image_problem": ".writer",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

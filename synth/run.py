"""``brave6d synth``: render N synthetic training images in parallel, resumable, deterministic.

Image ``i`` is drawn from ``(seed, i)`` alone (:func:`synth.randomize.image_rng`, the effects'
noise from the same pair), so the bytes written do not depend on the number of workers or on
where a run was resumed. Workers are processes (``concurrent.futures``, spawned: each loads the
library once); with one worker everything runs in this process.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

from brave6d.errors import BraveError
from brave6d.progress import progress_bar
from synth.randomize import LibraryAssets, Randomization, sample_image_scene
from synth.render import render_image
from synth.source import SynthSource, load_synth_source
from synth.writer import check_settings, gather_scene_files, is_complete, write_image

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SynthOptions:
    """``images``: how many; ``seed``: the split's seed (>= 0); ``workers``: processes; ``width`` /
    ``height``: image size (default: the spec's camera); ``randomization``: how images vary."""

    images: int
    seed: int = 0
    workers: int = 1
    width: int | None = None
    height: int | None = None
    randomization: Randomization = field(default_factory=Randomization)

    def __post_init__(self) -> None:
        if self.images < 1 or self.images > 1_000_000:
            raise BraveError(f"synth: --images must be in 1..1000000, got {self.images}")
        if self.seed < 0 or self.seed >= 2 ** 63:
            raise BraveError(f"synth: --seed must be a non-negative 64-bit integer, got {self.seed}")
        if self.workers < 1:
            raise BraveError(f"synth: --workers must be at least 1, got {self.workers}")


@dataclass(frozen=True)
class SynthResult:
    """What a run did: images in the split, rendered now, skipped (already complete), wall time."""

    out: Path
    images: int
    rendered: int
    skipped: int
    seconds: float
    render_seconds: float

    @property
    def images_per_s(self) -> float:
        """Images rendered per second of wall time (0 when nothing was rendered)."""
        return self.rendered / self.render_seconds if self.rendered and self.render_seconds > 0 else 0.0


def synthesize(spec_path: Path | str, out: Path | str, options: SynthOptions) -> SynthResult:
    """Write (or complete) the synthetic split of ``spec_path`` into ``out`` (module docstring)."""
    start = time.perf_counter()
    source = load_synth_source(spec_path).with_size(options.width, options.height)
    root = Path(out)
    if root.exists() and not root.is_dir():
        raise BraveError(f"{root}: OUT is a file; give a folder")
    root.mkdir(parents=True, exist_ok=True)
    check_settings(root, _settings(source, options))
    pending = [i for i in range(options.images) if not is_complete(root, i)]
    skipped = options.images - len(pending)
    if skipped:
        log.info("%s: %d of %d images already complete, rendering %d", root, skipped, options.images, len(pending))
    job = _Job(source.path, options.width, options.height, options.randomization, options.seed, root)
    render_start = time.perf_counter()
    bar = progress_bar(options.images, desc="synth", unit="img", initial=skipped)
    try:
        if options.workers == 1 or len(pending) <= 1:
            _init_worker(job)
            for i in pending:
                _render_one(i)
                bar.update(1)
        else:
            ctx = get_context("spawn")  # a fresh process: no Open3D/OpenMP state forked from this one
            with ProcessPoolExecutor(min(options.workers, len(pending)), mp_context=ctx, initializer=_init_worker,
                                     initargs=(job,)) as pool:
                for future in as_completed([pool.submit(_render_one, i) for i in pending]):
                    future.result()
                    bar.update(1)
    finally:
        bar.close()
    render_seconds = time.perf_counter() - render_start
    gather_scene_files(root, options.images)
    return SynthResult(root, options.images, len(pending), skipped, time.perf_counter() - start, render_seconds)


def _settings(source: SynthSource, options: SynthOptions) -> dict[str, object]:
    """What ``OUT/synth.json`` records: a resumed run must match every field."""
    return {"source": str(source.path), "source_digest": source.fingerprint(), "seed": options.seed,
            "width": source.camera.width, "height": source.camera.height,
            "effects": source.effects.enabled(), "randomization": options.randomization.to_json(),
            "obj_ids": {o.name: o.obj_id for o in source.objects}}


@dataclass(frozen=True)
class _Job:
    spec: Path
    width: int | None
    height: int | None
    randomization: Randomization
    seed: int
    out: Path


_STATE: dict[str, object] = {}


def _init_worker(job: _Job) -> None:
    """Load the library once per process."""
    source = load_synth_source(job.spec).with_size(job.width, job.height)
    _STATE["job"] = job
    _STATE["assets"] = LibraryAssets(source)


def _render_one(index: int) -> int:
    job: _Job = _STATE["job"]  # type: ignore[assignment]
    assets: LibraryAssets = _STATE["assets"]  # type: ignore[assignment]
    scene = sample_image_scene(assets, job.seed, index, job.randomization)
    write_image(job.out, index, render_image(scene, assets, job.seed))
    return index

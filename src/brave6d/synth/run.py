"""``brave6d synth``: render N synthetic training images in parallel, resumable, deterministic.

Image ``i`` is drawn from ``(seed, i)`` alone (:func:`brave6d.synth.randomize.image_rng`, the effects'
noise from the same pair), so the bytes written do not depend on the number of workers or on
where a run was resumed. Workers are processes (``concurrent.futures``, spawned: each loads the
library once); with one worker everything runs in this process.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

from brave6d.core.errors import BraveError
from brave6d.core.progress import progress_bar
from brave6d.synth import limits
from brave6d.core.png_check import CHECKS, DEFAULT_CHECK
from brave6d.synth.randomize import LibraryAssets, Randomization, sample_image_scene
from brave6d.synth.render import render_image
from brave6d.synth.source import SynthSource, load_synth_source
from brave6d.synth.writer import (
    CONVENTIONS,
    check_settings,
    gather_scene_files,
    has_record,
    image_problem,
    write_image,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SynthOptions:
    """``images``: how many; ``seed``: the split's seed (>= 0); ``workers``: processes; ``width`` /
    ``height``: image size (default: the spec's camera); ``randomization``: how images vary;
    ``resume_check``: how the PNGs of images already written are checked before they count as
    complete (:mod:`brave6d.core.png_check`: ``header``, ``crc`` or ``decode``); ``mesh_dirs``: folders besides a
    dataset.yaml's own that its meshes may lie in (``--mesh-dir``); ``scene_dirs``: the same for its
    captured scene directories (``--scene-dir``); ``convention``: ``brave6d`` (PNG, depth in mm) or
    ``blenderproc`` (JPEG, depth in 0.1 mm: :mod:`brave6d.synth.writer`). Bounds: :mod:`brave6d.synth.limits`."""

    images: int
    seed: int = 0
    workers: int = 1
    width: int | None = None
    height: int | None = None
    randomization: Randomization = field(default_factory=Randomization)
    resume_check: str = DEFAULT_CHECK
    mesh_dirs: tuple[Path, ...] = ()
    scene_dirs: tuple[Path, ...] = ()
    convention: str = "brave6d"

    def __post_init__(self) -> None:
        for name in limits.BOUNDS:
            value = getattr(self, name)
            if value is not None or name not in ("width", "height"):
                object.__setattr__(self, name, limits.check_option(name, value))
        if self.resume_check not in CHECKS:
            raise BraveError(f"synth: resume_check must be one of {', '.join(CHECKS)}, got {self.resume_check!r}")
        if self.convention not in CONVENTIONS:
            raise BraveError(f"synth: convention must be one of {', '.join(CONVENTIONS)}, got {self.convention!r}")


@dataclass(frozen=True)
class SynthResult:
    """What a run did: images in the split, rendered now, skipped (already complete), wall time;
    ``repaired``: images rendered again because their files were damaged (counted in ``rendered``),
    ``repair_reason``: the first damaged file and what was wrong with it."""

    out: Path
    images: int
    rendered: int
    skipped: int
    seconds: float
    render_seconds: float
    repaired: int = 0
    repair_reason: str | None = None

    @property
    def images_per_s(self) -> float:
        """Images rendered per second of wall time (0 when nothing was rendered)."""
        return self.rendered / self.render_seconds if self.rendered and self.render_seconds > 0 else 0.0


def synthesize(spec_path: Path | str, out: Path | str, options: SynthOptions) -> SynthResult:
    """Write (or complete) the synthetic split of ``spec_path`` into ``out`` (module docstring)."""
    start = time.perf_counter()
    source = load_synth_source(spec_path, options.mesh_dirs, options.scene_dirs).with_size(options.width, options.height)
    size = (source.camera.width, source.camera.height)
    size_from = "--width/--height" if options.width and options.height else f"the camera of {source.path}"
    limits.check_machine(*size, options.workers, min(options.workers, options.images), size_from)
    root = Path(out)
    if root.exists() and not root.is_dir():
        raise BraveError(f"{root}: OUT is a file; give a folder")
    root.mkdir(parents=True, exist_ok=True)
    check_settings(root, _settings(source, options))
    recorded = [i for i in range(options.images) if has_record(root, i)]
    damaged = _damaged(root, recorded, size, options.resume_check, options.convention)
    pending = sorted(set(range(options.images)) - set(recorded) | set(damaged))
    skipped = options.images - len(pending)
    reason = damaged[min(damaged)] if damaged else None
    if damaged:
        log.warning("%s: %d image(s) written before are damaged and will be rendered again; first: %s",
                    root, len(damaged), reason)
    if skipped:
        log.info("%s: %d of %d images already complete, rendering %d", root, skipped, options.images, len(pending))
    job = _Job(source.path, options.width, options.height, options.randomization, options.seed, root,
               options.mesh_dirs, options.scene_dirs, options.convention)
    render_start = time.perf_counter()
    try:
        _render_all(job, pending, options.workers, options.images)
    except (MemoryError, BrokenProcessPool) as exc:
        what = "ran out of memory" if isinstance(exc, MemoryError) else \
            "lost a worker process (the system may have killed it for memory)"
        raise BraveError(f"synth: rendering {size[0]}x{size[1]} images with --workers {options.workers} {what}; "
                         f"estimate {limits.render_memory_bytes(*size) / limits.GIB:.1f} GiB per worker; "
                         "use fewer --workers or smaller --width/--height") from None
    render_seconds = time.perf_counter() - render_start
    gather_scene_files(root, options.images, options.convention)
    return SynthResult(root, options.images, len(pending), skipped, time.perf_counter() - start, render_seconds,
                       len(damaged), reason)


def _damaged(root: Path, indices: list[int], size: tuple[int, int], check: str,
             convention: str = "brave6d") -> dict[int, str]:
    """Image index -> its first problem, for the images of ``indices`` whose record or PNGs are
    damaged (:func:`brave6d.synth.writer.image_problem`; on a few threads: reading, CRC-32 and decoding
    release the GIL)."""
    found: dict[int, str] = {}
    if not indices:
        return found
    bar = progress_bar(len(indices), desc=f"synth: checking ({check})", unit="img")
    try:
        with ThreadPoolExecutor(min(limits.usable_cpus(), 4)) as pool:
            for i, problem in zip(indices, pool.map(lambda i: image_problem(root, i, size, check, convention),
                                                        indices)):
                if problem is not None:
                    found[i] = problem
                bar.update(1)
    finally:
        bar.close()
    return found


def _render_all(job: _Job, pending: list[int], workers: int, images: int) -> None:
    """Render ``pending`` (of ``images``) in this process (one worker) or in ``workers`` spawned processes."""
    bar = progress_bar(images, desc="synth", unit="img", initial=images - len(pending))
    try:
        if workers == 1 or len(pending) <= 1:
            _init_worker(job)
            for i in pending:
                _render_one(i)
                bar.update(1)
        else:
            ctx = get_context("spawn")  # a fresh process: no Open3D/OpenMP state forked from this one
            with ProcessPoolExecutor(min(workers, len(pending)), mp_context=ctx, initializer=_init_worker,
                                     initargs=(job,)) as pool:
                for future in as_completed([pool.submit(_render_one, i) for i in pending]):
                    future.result()
                    bar.update(1)
    finally:
        bar.close()


def _settings(source: SynthSource, options: SynthOptions) -> dict[str, object]:
    """What ``OUT/synth.json`` records: a resumed run must match every field."""
    settings = {"source": str(source.path), "source_digest": source.fingerprint(), "seed": options.seed,
                "width": source.camera.width, "height": source.camera.height,
                "effects": source.effects.enabled(), "randomization": options.randomization.to_json(),
                "obj_ids": {o.name: o.obj_id for o in source.objects}}
    if options.convention != "brave6d":  # the default leaves the file as before: older splits resume
        settings["convention"] = options.convention
    return settings


@dataclass(frozen=True)
class _Job:
    spec: Path
    width: int | None
    height: int | None
    randomization: Randomization
    seed: int
    out: Path
    mesh_dirs: tuple[Path, ...] = ()
    scene_dirs: tuple[Path, ...] = ()
    convention: str = "brave6d"


_STATE: dict[str, object] = {}


def _init_worker(job: _Job) -> None:
    """Load the library once per process."""
    source = load_synth_source(job.spec, job.mesh_dirs, job.scene_dirs).with_size(job.width, job.height)
    _STATE["job"] = job
    _STATE["assets"] = LibraryAssets(source)


def _render_one(index: int) -> int:
    job: _Job = _STATE["job"]  # type: ignore[assignment]
    assets: LibraryAssets = _STATE["assets"]  # type: ignore[assignment]
    scene = sample_image_scene(assets, job.seed, index, job.randomization)
    write_image(job.out, index, render_image(scene, assets, job.seed), job.convention)
    return index

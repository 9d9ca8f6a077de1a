"""Report section 8: synthetic-split speed: ``brave6d synth`` images per second by image size and workers.

The scene's own spec (its objects, camera effects and capture distances) is rendered by
:func:`brave6d.synth.synthesize` into a temporary folder (never into the scene) at each image size and
worker count of the sweep: one point per setting, images per second of wall time from the first
image to the last written file (worker start-up and library loading included: what a user waits
for). One untimed one-image run at the smallest size comes first, so that this process's one-time
imports and compilation do not land on the first setting. The advice derives the rate at each size, whether more workers pay on this machine and how
long 10,000 images take.

It also prices ``synth --resume-check``: on the images of the largest size's one-worker run, the
time :func:`brave6d.synth.image_problem` takes per image at each check level (``header``, ``crc``,
``decode``: what a resumed run spends on every image it finds), beside the time to render one.
"""

from __future__ import annotations

import math
import statistics
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from brave6d.core.progress import format_table
from brave6d.evaluation.report.common import RenderedSection, fmt, nan_note, num, provenance, settings_line, unavailable
from brave6d.evaluation.report.measurements import Measurement, describe_machine, file_stamp, machine_info, run_sweep
from brave6d.evaluation.report.plots import legend, new_figure, plot_line, save_figure
from brave6d.evaluation.report.protocol import MeasureInputs

NAME = "synthesis"
PAGE = 8
TITLE = f"{PAGE}. Synthetic training split: images per second by image size and workers"
FIGURE = "synthesis.png"
#: The split size the advice prices.
SPLIT_IMAGES = 10_000
#: More workers "pay" when they are at least this much faster than one.
WORKERS_PAY = 1.2


@dataclass(frozen=True)
class SynthSweep:
    """Image sizes (width, height), worker counts, images per point and the split's seed."""

    sizes: tuple[tuple[int, int], ...] = ((320, 240), (640, 480))
    workers: tuple[int, ...] = (1, 2)
    images: int = 8
    seed: int = 0


def measure_synthesis(inputs: MeasureInputs, sweep: SynthSweep) -> Measurement:
    """Run (or resume) the synth speed sweep on the scene's spec; see the module docstring."""
    scene, store = inputs.scene, inputs.store
    spec = scene.spec_path
    if (absent := store.require(NAME, [(spec, "scene init (brave6d init)")])) is not None:
        return absent
    from brave6d.synth import SynthOptions, load_synth_source, synthesize

    key = {"spec": file_stamp(spec), "sweep": asdict(sweep)}
    if (done := store.complete(NAME, key)) is not None:
        return done
    source = load_synth_source(spec)
    settings = {"sizes": [f"{w}x{h}" for w, h in sweep.sizes], "workers": list(sweep.workers),
                "images": sweep.images, "seed": sweep.seed, "objects": len(source.objects)}
    m = store.resume(NAME, key, settings, machine_info("cpu"))
    m.summary.update({"spec": str(spec), "objects": [o.name for o in source.objects],
                      "effects": source.effects.enabled()})

    largest = max(sweep.sizes, key=lambda s: s[0] * s[1])

    def run(images: int, width: int, height: int, workers: int) -> tuple[Any, dict[str, float]]:
        with tempfile.TemporaryDirectory(prefix="brave6d-report-synth-") as tmp:
            out = Path(tmp) / "train_pbr"
            result = synthesize(spec, out, SynthOptions(images=images, seed=sweep.seed, workers=workers,
                                                        width=width, height=height))
            priced = (width, height) == largest and workers == min(sweep.workers)
            return result, (resume_check_ms(out, images, (width, height)) if priced else {})

    warmed: list[bool] = []

    def measure(item: tuple[int, int, int]) -> dict[str, Any]:
        width, height, workers = item
        if not warmed:  # untimed: one-time imports and compilation (module docstring)
            run(1, *min(sweep.sizes, key=lambda s: s[0] * s[1]), 1)
            warmed.append(True)
        result, check_ms = run(sweep.images, width, height, workers)
        point = {"width": width, "height": height, "workers": workers, "images": result.rendered,
                 "render_s": result.render_seconds, "wall_s": result.seconds, "images_per_s": result.images_per_s}
        return {**point, "resume_check_ms": check_ms} if check_ms else point

    items = [(f"{w}x{h}-w{n}", (w, h, n)) for w, h in sweep.sizes for n in sweep.workers]
    return run_sweep(store, m, items, measure, desc="report: synthesis", unit="setting")


def resume_check_ms(out: Path, images: int, size: tuple[int, int], repeats: int = 3) -> dict[str, float]:
    """Milliseconds per image that a resumed run spends checking the ``images`` images in ``out``
    at each level of ``--resume-check`` (one thread, files in the page cache: median of ``repeats``)."""
    from brave6d.core.png_check import CHECKS
    from brave6d.synth import image_problem

    out_ms = {}
    for check in CHECKS:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            bad = [i for i in range(images) if image_problem(out, i, size, check) is not None]
            times.append((time.perf_counter() - t0) * 1000.0 / images)
            if bad:  # a freshly written split: a problem here is the check's, not the images'
                raise RuntimeError(f"synth check {check!r} refused image {bad[0]} of a fresh split in {out}")
        out_ms[check] = statistics.median(times)
    return out_ms


# ----------------------------------------------------------------------------- aggregation
def rate_at(points: Sequence[dict[str, Any]]) -> dict[tuple[int, int], dict[int, float]]:
    """Images per second by ``(width, height)`` and then by workers (NaN where not finite)."""
    table: dict[tuple[int, int], dict[int, float]] = {}
    for p in points:
        size = (int(p["width"]), int(p["height"]))
        table.setdefault(size, {})[int(p["workers"])] = num(p.get("images_per_s"))
    return dict(sorted(table.items(), key=lambda kv: kv[0][0] * kv[0][1]))


def best_workers(rates: Mapping[int, float]) -> tuple[int, float] | None:
    """The worker count with the highest finite rate, and that rate (None when none is finite)."""
    finite = {w: r for w, r in rates.items() if math.isfinite(r) and r > 0}
    if not finite:
        return None
    w = max(finite, key=lambda k: finite[k])
    return w, finite[w]


def hours_for(images: int, rate: float) -> float:
    """Hours to render ``images`` at ``rate`` images/s (NaN when the rate is not positive)."""
    return images / rate / 3600.0 if math.isfinite(rate) and rate > 0 else math.nan


# ----------------------------------------------------------------------------- rendering
def render_synthesis(m: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 8 from its measurement: images/s by size (one line per worker count), table, advice."""
    if m is None or not m.usable or not m.points:
        return unavailable(TITLE, m, "Synthetic-split speed")
    rates = rate_at(m.points)
    sizes = list(rates)
    workers = sorted({w for per in rates.values() for w in per})
    fig, (ax,) = new_figure(1, panel=(6.0, 3.6))
    dropped = 0
    mpx = [w * h / 1e6 for w, h in sizes]
    for k, n in enumerate(workers):
        dropped += plot_line(ax, mpx, [rates[s].get(n, math.nan) for s in sizes],
                             f"{n} worker{'s' if n > 1 else ''}", fmt="o-", color=f"C{k}")
    ax.set_xticks(mpx, [f"{w}x{h}" for w, h in sizes])
    ax.set_xlabel("image size")
    ax.set_ylabel("synthetic images per second")
    ax.set_ylim(bottom=0)
    legend(ax)
    png = save_figure(fig, out_dir / FIGURE, "brave6d synth on the scene's objects: images per second",
                      describe_machine(m.machine), settings_line(m))
    table = []
    for p in m.points:
        r = num(p.get("images_per_s"))
        table.append((f"{p['width']}x{p['height']}", p["workers"], p.get("images"), fmt(r, 2),
                      fmt(1.0 / r if r > 0 else math.nan, 2), fmt(hours_for(SPLIT_IMAGES, r), 1)))
    objects = m.summary.get("objects") or []
    body = (f"`brave6d synth` on `{m.summary.get('spec')}` ({len(objects)} objects: {', '.join(objects)}), "
            f"{m.settings.get('images')} images per setting into a temporary folder; wall time from the first "
            "image to the last written file, worker start-up and library loading included (after one untimed "
            "warm-up image).\n\n"
            f"![images per second]({png.name})\n\n"
            + format_table(["size", "workers", "images", "images/s", "s/image", f"h for {SPLIT_IMAGES:,}"], table)
            + "\n\n" + resume_check_text(m.points) + provenance(m) + "\n" + nan_note(dropped, "plotted synthesis rates"))
    advice = advice_synthesis(rates, m.machine, int(num(m.settings.get("images"))))
    return RenderedSection(TITLE, body, (advice + " " + advice_resume_check(m.points)).strip(), [png])


def _priced(points: Sequence[dict[str, Any]]) -> tuple[dict[str, Any], dict[str, float], float] | None:
    """The point whose images were checked at every ``--resume-check`` level, its ms per image by
    level and its ms to render one image (NaN when its rate is not finite); None when none was."""
    for p in points:
        ms = p.get("resume_check_ms")
        if isinstance(ms, dict) and ms:
            rate = num(p.get("images_per_s"))
            return p, {str(k): num(v) for k, v in ms.items()}, (1000.0 / rate if rate > 0 else math.nan)
    return None


def resume_check_text(points: Sequence[dict[str, Any]]) -> str:
    """A table of what each ``--resume-check`` level costs per image (empty when not measured)."""
    priced = _priced(points)
    if priced is None:
        return ""
    point, ms, render = priced
    rows = [(level, fmt(v, 2), fmt(v / render * 100.0, 2) if math.isfinite(render) else "n/a", CATCHES.get(level, ""))
            for level, v in ms.items()]
    return (f"`--resume-check`: what a resumed run spends checking each image it finds "
            f"({point['width']}x{point['height']}, {point.get('images')} images, one thread, files in the page "
            f"cache; rendering one took {fmt(render, 0)} ms):\n\n"
            + format_table(["level", "ms/image", "% of a render", "finds"], rows) + "\n\n")


#: What each ``--resume-check`` level finds (:mod:`brave6d.core.png_check`).
CATCHES = {"header": "a file cut short, not a PNG, wrong size or kind",
           "crc": "also any changed byte",
           "decode": "also compressed data that does not inflate (only a forged file with valid CRCs)"}


def advice_resume_check(points: Sequence[dict[str, Any]]) -> str:
    """Which ``--resume-check`` level to use, from its measured cost beside a render."""
    priced = _priced(points)
    if priced is None:
        return ""
    _, ms, render = priced
    crc, decode = ms.get("crc", math.nan), ms.get("decode", math.nan)
    if not (math.isfinite(render) and math.isfinite(crc)):
        return ""
    text = (f"**Resume check:** the default `crc` costs {fmt(crc, 2)} ms per image found on resume "
            f"({fmt(crc / render * 100.0, 2)} % of rendering one) and finds any changed byte: keep it")
    if math.isfinite(decode):
        text += (f"; `decode` ({fmt(decode, 1)} ms) adds only forged files with valid CRCs, worth it for a split "
                 "others could have written")
    return text + "."


def advice_synthesis(rates: Mapping[tuple[int, int], Mapping[int, float]], machine: Mapping[str, Any],
                     images: int) -> str:
    """The rate at each size, whether more workers pay here for runs of ``images`` images (their
    start-up included), and the time of a 10k-image split."""
    best = {size: b for size, per in rates.items() if (b := best_workers(per)) is not None}
    if not best:
        return ""
    one = {size: per.get(1, math.nan) for size, per in rates.items()}
    parts = [f"{w}x{h}: {fmt(one[(w, h)], 2)} images/s" for (w, h) in best if math.isfinite(one[(w, h)])]
    text = "**Synthetic split:** with 1 worker " + ("; ".join(parts) if parts else "not measured")
    multi = [(size, n, r) for size, per in rates.items() for n, r in per.items() if n > 1 and math.isfinite(r)]
    cores = machine.get("usable_cores") or machine.get("cores")
    if multi:
        gains = [(size, n, r / one[size]) for size, n, r in multi if math.isfinite(one[size]) and one[size] > 0]
        if gains:
            n = max(g[1] for g in gains)
            speedups = [g for s, k, g in gains if k == n]
            low, high = min(speedups), max(speedups)
            span = fmt(low, 2) if abs(high - low) < 0.005 else f"{fmt(low, 2)}-{fmt(high, 2)}"
            if low >= WORKERS_PAY:
                text += (f"; {n} workers render {span}x faster on this machine ({cores} cores, {images}-image "
                         f"runs): use --workers {n}")
            else:
                text += (f"; {n} workers are only {span}x as fast on this machine ({cores} cores, {images}-image "
                         "runs, start-up included): keep --workers 1 for runs this short (on a long split the "
                         "start-up amortises: time a longer run with benchmarks/synth.py before adding workers)")
    largest = max(best, key=lambda s: s[0] * s[1])
    n, r = best[largest]
    return text + (f". {SPLIT_IMAGES:,} images at {largest[0]}x{largest[1]} take about "
                   f"{fmt(hours_for(SPLIT_IMAGES, r), 1)} h here ({n} worker{'s' if n > 1 else ''}).")


class SynthesisSection:
    """Section 8 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> SynthSweep:
        """Full: 320x240 and 640x480, 1 and 2 workers, 8 images; quick: 3 tiny images, 1 worker."""
        if quick:
            return SynthSweep(sizes=((80, 60), (160, 120)), workers=(1,), images=3)
        return SynthSweep()

    def measure(self, inputs: MeasureInputs, settings: SynthSweep) -> Measurement:
        return measure_synthesis(inputs, settings)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_synthesis(measurements.get(NAME), out_dir)


SECTION = SynthesisSection()

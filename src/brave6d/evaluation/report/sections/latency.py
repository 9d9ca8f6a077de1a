"""Report section 3: render latency against image resolution and number of Gaussians.

The scene's trained splat (``splat/point_cloud.ply``, else the bundle's) is subsampled at
random to several counts; each subset is handed in memory to the render server's own
:class:`brave6d.serve.SplatRenderer` (``from_splat``: load-time pruning, per-view culling, forward
rasterization) and rendered from a few captured camera poses at several resolutions of
the calibrated (undistorted) camera. A warm-up render precedes each count; the report gives
the median ``render_ms`` (the rasterizer call, as the server reports it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.core.layout import SceneDir
from brave6d.core.progress import format_table
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore, describe_machine, file_stamp, machine_info, run_sweep
from brave6d.evaluation.report.common import RenderedSection, calibrated_capture, fmt, median, nan_note, num, provenance, quantile
from brave6d.evaluation.report.common import settings_line, unavailable
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.plots import legend, log_axes, new_figure, plot_line, save_figure

NAME = "latency"
PAGE = 3
TITLE = f"{PAGE}. Rendering: latency against resolution and number of Gaussians"
FIGURE = "latency.png"
#: Frame-time targets the advice is phrased against (interactive viewing, agent steps).
TARGETS_MS = (33.3, 100.0)


@dataclass(frozen=True)
class LatencySweep:
    """Gaussian counts as fractions of the splat, image sizes as scales of the capture camera."""

    fractions: tuple[float, ...] = (1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0)
    scales: tuple[float, ...] = (0.25, 0.5, 1.0)
    repeats: int = 5
    views: int = 3
    device: str = "auto"
    seed: int = 0


def find_splat(scene: SceneDir) -> Path | None:
    """The trained splat the server would load: ``splat/point_cloud.ply``, else ``bundle/splat.ply``."""
    from brave6d.serve import SPLAT, find_splat_ply

    try:
        return find_splat_ply(scene)
    except Exception:  # noqa: BLE001 - absent: try the bundle
        bundled = scene.bundle_dir / SPLAT
        return bundled if bundled.is_file() else None


def measure_latency(scene: SceneDir, store: MeasurementStore, sweep: LatencySweep) -> Measurement:
    """Run (or resume) the latency sweep; see the module docstring."""
    ply = find_splat(scene)
    if ply is None:
        return store.missing(NAME, f"no trained splat under `{scene.splat_dir}` or `{scene.bundle_dir}` "
                                   "(run the training stage)")
    if (absent := store.require(NAME, calibrated_capture(scene))) is not None:
        return absent
    from brave6d.core.calibration_io import camera_poses, read_intrinsics
    from brave6d.serve import SplatRenderer
    from brave6d.training import read_ply, resolve_device

    device = str(resolve_device(sweep.device))
    key = {"splat": file_stamp(ply), "frames": file_stamp(scene.frames_path),
           "intrinsics": file_stamp(scene.intrinsics_path), "handeye": file_stamp(scene.handeye_path),
           "sweep": asdict(sweep), "device": device}
    if (done := store.complete(NAME, key)) is not None:
        return done
    splat = read_ply(ply)
    n_total = splat.num_gaussians
    camera = read_intrinsics(scene).without_distortion()
    poses = [T for _, T in camera_poses(scene)]
    picks = np.linspace(0, len(poses) - 1, min(sweep.views, len(poses))).round().astype(int)
    poses = [poses[i] for i in picks]
    counts = sorted({max(1, round(f * n_total)) for f in sweep.fractions})
    sizes = sorted({(max(16, round(camera.width * s)), max(16, round(camera.height * s))) for s in sweep.scales})
    settings = {"splat": ply.name, "gaussians": counts, "sizes": [f"{w}x{h}" for w, h in sizes],
                "repeats": sweep.repeats, "views": len(poses), "device": device,
                "sh_degree": SplatRenderer.effective_sh_degree(splat.shN)}
    m = store.resume(NAME, key, settings, machine_info(device))
    m.summary.update({"splat": str(ply), "n_total": n_total, "capture_size": [camera.width, camera.height]})
    current: dict[str, Any] = {}

    def renderer_for(n: int) -> Any:
        if current.get("n") != n:
            keep = np.sort(np.random.default_rng(sweep.seed).choice(n_total, n, replace=False))
            current.update(n=n, renderer=SplatRenderer.from_splat(splat.subset(keep), device=device,
                                                                  source=f"{ply} ({n} of its Gaussians)"))
            current["renderer"].warm_up(camera, poses[0])
        return current["renderer"]

    def render(item: tuple[int, tuple[int, int]]) -> dict[str, Any]:
        n, (w, h) = item
        renderer = renderer_for(n)
        cam = camera.scaled(w, h)
        renderer.render(poses[0], cam)  # warm-up at this size (allocations, caches)
        outs = [renderer.render(T, cam) for _ in range(sweep.repeats) for T in poses]
        return {"gaussians": n, "loaded": renderer.num_gaussians, "width": w, "height": h,
                "antialiasing": renderer.antialiasing,
                "median_ms": median([o.render_ms for o in outs]), "p90_ms": quantile([o.render_ms for o in outs], 0.9),
                "drawn": median([o.gaussians_drawn for o in outs]), "samples": len(outs)}

    items = [(f"g{n}-{w}x{h}", (n, (w, h))) for n in counts for (w, h) in sizes]
    return run_sweep(store, m, items, render, desc="report: render latency", unit="cell")


# ----------------------------------------------------------------------------- rendering
def render_latency(m: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 3 from its measurement: plot, table, advice (or a note saying what is missing)."""
    if m is None or not m.usable:
        return unavailable(TITLE, m, "Render latency sweep")
    sizes = sorted({(int(p["width"]), int(p["height"])) for p in m.points}, key=lambda s: s[0] * s[1])
    counts = sorted({int(p["gaussians"]) for p in m.points})
    cell = {(int(p["gaussians"]), int(p["width"]), int(p["height"])): p for p in m.points}

    def ms(n: int, w: int, h: int) -> float:
        return num(cell.get((n, w, h), {}).get("median_ms"))

    fig, (ax_n, ax_px) = new_figure(2)
    dropped = 0
    for w, h in sizes:
        dropped += plot_line(ax_n, counts, [ms(n, w, h) for n in counts], f"{w}x{h}")
    for n in counts:
        dropped += plot_line(ax_px, [w * h / 1e6 for w, h in sizes], [ms(n, w, h) for w, h in sizes], f"{n:,} G")
    ax_n.set_xlabel("Gaussians (random subset of the splat)")
    ax_px.set_xlabel("image size [megapixels]")
    for ax in (ax_n, ax_px):
        ax.set_ylabel("median render latency [ms]")
        log_axes(ax)
        for target in TARGETS_MS:
            ax.axhline(target, color="0.5", lw=0.8, ls=":")
        legend(ax)
    png = save_figure(fig, out_dir / FIGURE, "Render latency (serve renderer, forward only) against Gaussians "
                      "and resolution; dotted: 33 ms and 100 ms", describe_machine(m.machine), settings_line(m))
    table = [(f"{n:,}", *(fmt(ms(n, w, h), 1) for w, h in sizes)) for n in counts]
    n_total = num(m.summary.get("n_total"))
    total = f"{int(n_total):,}" if math.isfinite(n_total) else "?"
    body = (f"The splat `{Path(str(m.summary.get('splat', '?'))).name}` ({total} Gaussians) is "
            "subsampled at random and rendered by the render server's renderer from captured camera poses; "
            "median milliseconds per frame (rows: Gaussians, columns: image size):\n\n"
            f"![render latency]({png.name})\n\n"
            + format_table(["Gaussians", *(f"{w}x{h}" for w, h in sizes)], table)
            + "\n\n" + provenance(m) + "\n" + nan_note(dropped, "latency cells"))
    return RenderedSection(TITLE, body, advice_latency(counts, sizes, ms, scaling_exponents(m.points)), [png])


def scaling_exponents(points: list[dict[str, Any]]) -> tuple[float, float] | None:
    """Least-squares ``(b, c)`` of ``log ms = a + b log Gaussians + c log pixels`` over the finite cells."""
    rows = [(num(p.get("gaussians")), num(p.get("width")) * num(p.get("height")), num(p.get("median_ms")))
            for p in points]
    rows = [r for r in rows if all(math.isfinite(v) and v > 0 for v in r)]
    if len({r[0] for r in rows}) < 2 or len({r[1] for r in rows}) < 2:
        return None
    A = np.array([[1.0, math.log(n), math.log(px)] for n, px, _ in rows])
    coef = np.linalg.lstsq(A, np.log([r[2] for r in rows]), rcond=None)[0]
    return float(coef[1]), float(coef[2])


def advice_latency(counts: list[int], sizes: list[tuple[int, int]], ms: Any,
                   exponents: tuple[float, float] | None) -> str:
    """Per target frame time: the largest image size at which the full splat renders in time,
    and which knob (Gaussians or pixels) buys more speed, from the fitted exponents."""
    if not counts or not sizes:
        return ""
    full = counts[-1]
    parts = []
    for target in TARGETS_MS:
        fits = [(w, h) for w, h in sizes if math.isfinite(ms(full, w, h)) and ms(full, w, h) <= target]
        if fits:
            w, h = fits[-1]
            parts.append(f"renders within {target:.0f} ms up to {w}x{h} ({fmt(ms(full, w, h), 1)} ms)")
        else:
            w, h = sizes[0]
            under = [n for n in counts if math.isfinite(ms(n, w, h)) and ms(n, w, h) <= target]
            if under:
                parts.append(f"misses {target:.0f} ms at every measured size (at {w}x{h}, {under[-1]:,} "
                             "Gaussians make it)")
    if parts:
        text = f"**Render resolution and Gaussians:** the full splat ({full:,} Gaussians) " + "; ".join(parts) + "."
    else:
        w, h = sizes[0]
        text = (f"**Render resolution and Gaussians:** no measured combination renders within {max(TARGETS_MS):.0f} ms "
                f"(fastest: {fmt(ms(counts[0], w, h), 1)} ms for {counts[0]:,} Gaussians at {w}x{h}).")
    if exponents is not None:
        b, c = exponents
        cheaper = "fewer pixels" if c > b else "fewer Gaussians"
        text += (f" Latency grows as Gaussians^{b:.2f} x pixels^{c:.2f}: halving the Gaussians saves "
                 f"{100 * (1 - 0.5 ** b):.0f} %, halving the pixels {100 * (1 - 0.5 ** c):.0f} %, so {cheaper} "
                 "is the cheaper way to a target frame time.")
    return text


class LatencySection:
    """Section 3 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> LatencySweep:
        """The demo's sweep; quick: four Gaussian counts at two small image sizes."""
        if quick:
            return LatencySweep(fractions=(1 / 8, 1 / 4, 1 / 2, 1.0), scales=(0.25, 0.5), repeats=3, views=2)
        return LatencySweep()

    def measure(self, inputs: MeasureInputs, settings: LatencySweep) -> Measurement:
        return measure_latency(inputs.scene, inputs.store, settings)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_latency(measurements.get(NAME), out_dir)


SECTION = LatencySection()

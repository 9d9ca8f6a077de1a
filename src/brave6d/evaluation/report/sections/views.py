"""Report section 4: holdout PSNR against views per distance level, with the capture time they cost.

Short trainings with one step budget on subsets of the training views of every ring (evenly
spaced in capture order), the holdout fixed (the training stage's 10 % per level). Nothing
is written into the scene: :func:`brave6d.training.train` runs without checkpoints and the model
stays in memory. Every run starts from points back-projected from its *own* depth frames (random
points without depth), so that a sparser capture does not borrow geometry from views it
would not have. The preset is the one the scene was trained with (``splat/metrics.json``),
scaled to the step budget. The holdout is scored at several steps of every run, so the run
on all views doubles as section 1's holdout curve. Capture time per view: median gap between
consecutive frame time stamps of that level (travel + settle + exposure).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from brave6d.core.layout import SceneDir
from brave6d.core.progress import format_table
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore, describe_machine, file_stamp, machine_info, run_sweep
from brave6d.evaluation.report.common import RenderedSection, calibrated_capture, evenly_spaced, fmt, nan_note, num, provenance
from brave6d.evaluation.report.common import seconds_per_frame, settings_line, unavailable
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.plots import legend, new_figure, plot_line, save_figure

if TYPE_CHECKING:
    from brave6d.training import Preset

NAME = "views"
PAGE = 4
TITLE = f"{PAGE}. Capture: holdout quality against views per distance level"
FIGURE = "views.png"
#: A gain below this many dB is "diminishing returns" in the advice.
PSNR_TOLERANCE_DB = 0.5


@dataclass(frozen=True)
class ViewsSweep:
    """Fractions of each ring's training views, the step budget, holdout evaluations per run, and
    caps on the Gaussians and the image size (``downscale``: at least this factor)."""

    fractions: tuple[float, ...] = (0.125, 0.5, 1.0)
    steps: int = 900
    evaluations: int = 6
    # Caps on top of the preset (None: the preset's): the cost of a step grows with the Gaussians
    # and the pixels, and subsets are only comparable at equal capacity.
    max_gaussians: int | None = 10_000
    downscale: int | None = 4
    device: str = "auto"


def measure_views(scene: SceneDir, store: MeasurementStore, sweep: ViewsSweep) -> Measurement:
    """Run (or resume) the subset trainings; see the module docstring."""
    if (absent := store.require(NAME, calibrated_capture(scene))) is not None:
        return absent
    from brave6d.training import load_scene, resolve_device

    preset, preset_source = scene_preset(scene, sweep)
    device = resolve_device(sweep.device)
    key = {"frames": file_stamp(scene.frames_path), "intrinsics": file_stamp(scene.intrinsics_path),
           "handeye": file_stamp(scene.handeye_path), "preset": preset.to_json(), "sweep": asdict(sweep),
           "device": str(device)}
    if (done := store.complete(NAME, key)) is not None:
        return done
    data = load_scene(scene, preset.downscale)
    per_level: dict[int, list[Any]] = defaultdict(list)
    for v in data.train:
        per_level[v.distance_level].append(v)
    levels = sorted(per_level)
    settings = {"preset": f"{preset.name} ({preset_source})", "steps": preset.steps, "fractions": list(sweep.fractions),
                "image": f"{data.camera.width}x{data.camera.height}", "init": "own depth frames",
                "max_gaussians": preset.densification.max_gaussians, "holdout_views": len(data.test),
                "device": str(device)}
    m = store.resume(NAME, key, settings, machine_info(str(device)))
    records = scene.frames()
    m.summary.update({"levels": {str(lv): {"distance_m": per_level[lv][0].distance_m, "train_views": len(per_level[lv]),
                                           "capture_s_per_view": seconds_per_frame(records, lv)}
                                 for lv in levels},
                      "holdout_views": len(data.test)})
    subsets: dict[tuple[int, ...], float] = {}
    for f in sorted(sweep.fractions):
        counts = tuple(max(1, min(len(per_level[lv]), round(f * len(per_level[lv])))) for lv in levels)
        subsets.setdefault(counts, f)

    def train(item: tuple[tuple[int, ...], float]) -> dict[str, Any]:
        counts, fraction = item
        chosen = [v for lv, k in zip(levels, counts) for v in evenly_spaced(per_level[lv], k)]
        return {"fraction": fraction, "views_per_level": list(counts), "n_train": len(chosen),
                **train_subset(dataclasses.replace(data, train=sorted(chosen, key=lambda v: v.index)), preset, device)}

    items = [("v" + "-".join(map(str, c)), (c, f)) for c, f in subsets.items()]
    return run_sweep(store, m, items, train, desc="report: trainings on view subsets", unit="run")


def scene_preset(scene: SceneDir, sweep: ViewsSweep) -> tuple[Preset, str]:
    """The preset the scene was trained with (else ``fast``), scaled to the sweep's step budget."""
    from brave6d.core.atomic import read_json
    from brave6d.core.errors import DataError
    from brave6d.training import Preset, get_preset

    preset, source = get_preset("fast"), "the fast preset: no splat/metrics.json"
    try:
        preset = Preset.from_json(read_json(scene.metrics_path).get("preset_config") or {})
        source = "as trained"
    except (DataError, TypeError, AttributeError):
        pass
    preset = preset.with_steps(sweep.steps)
    trained_cap, trained_points = preset.densification.max_gaussians, preset.initialisation.max_init_points
    cap = trained_cap if sweep.max_gaussians is None else min(trained_cap or sweep.max_gaussians, sweep.max_gaussians)
    init_points = trained_points if cap is None else min(trained_points, max(1, cap // 2))
    return preset.with_values(time_budget_s=None, max_gaussians=cap, max_init_points=init_points,
                              downscale=max(preset.downscale, sweep.downscale or 1),
                              eval_every=max(1, sweep.steps // max(sweep.evaluations, 1))), source


def train_subset(data: Any, preset: Preset, device: Any) -> dict[str, Any]:
    """Train on ``data.train`` from its own depth points; holdout curve and final scores."""
    from brave6d.training import evaluate_holdout, train

    run = train(data, preset, device, init_method="depth")
    curve = [{"step": p.step, "time_s": p.time_s, "gaussians": p.gaussians, "psnr": p.psnr, "ssim": p.ssim}
             for p in run.holdout_curve]
    eval_s = sum(p.eval_s for p in run.holdout_curve)
    if not curve or curve[-1]["step"] != run.steps:  # the schedule did not score the last step
        t = time.perf_counter()
        h = evaluate_holdout(run.model, data)
        eval_s += time.perf_counter() - t
        curve.append({"step": run.steps, "time_s": run.result.train_seconds, "gaussians": run.num_gaussians,
                      "psnr": h.psnr, "ssim": h.ssim})
    return {"steps": run.steps, "train_s": run.result.train_seconds, "init_s": run.init_seconds, "eval_s": eval_s,
            "init": {"source": run.init["source"], "points": run.init["points"]}, "gaussians": run.num_gaussians,
            "psnr": curve[-1]["psnr"], "ssim": curve[-1]["ssim"], "curve": curve}


# ----------------------------------------------------------------------------- rendering
def capture_seconds(point: dict[str, Any], levels: dict[str, Any]) -> float:
    """Robot time the point's training views cost: views x the level's seconds per view."""
    per_view = [num(levels[lv].get("capture_s_per_view")) for lv in sorted(levels, key=int)]
    return sum(k * s for k, s in zip(point.get("views_per_level", []), per_view))


def render_views(m: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 4 from its measurement: plot, table, advice (or a note saying what is missing)."""
    if m is None or not m.usable:
        return unavailable(TITLE, m, "Views-per-level sweep")
    levels = m.summary.get("levels", {})
    pts = sorted(m.points, key=lambda p: num(p.get("n_train")))
    per_ring = [float(np.mean(p["views_per_level"])) if p.get("views_per_level") else math.nan for p in pts]
    capture_min = [capture_seconds(p, levels) / 60.0 for p in pts]
    fig, (ax_v, ax_s, ax_t, ax_c) = new_figure(2, 2)
    dropped = plot_line(ax_v, per_ring, [p.get("psnr") for p in pts], "holdout PSNR")
    dropped += plot_line(ax_s, per_ring, [p.get("ssim") for p in pts], "holdout SSIM", color="tab:orange")
    dropped += plot_line(ax_t, capture_min, [p.get("psnr") for p in pts], "holdout PSNR")
    for p in pts:
        curve = p.get("curve", [])
        dropped += plot_line(ax_c, [c.get("step") for c in curve], [c.get("psnr") for c in curve],
                             f"{per_level_text(p)} views per level", fmt=".-")
    for ax in (ax_v, ax_s):
        ax.set_xlabel("training views per distance level (mean over levels)")
    ax_t.set_xlabel("robot time of those views [min]")
    ax_c.set_xlabel("training step")
    ax_s.set_ylabel("holdout SSIM")
    for ax in (ax_v, ax_t, ax_c):
        ax.set_ylabel("holdout PSNR [dB]")
    for ax in (ax_v, ax_s, ax_t, ax_c):
        legend(ax)
    png = save_figure(fig, out_dir / FIGURE, "Holdout quality against training views per distance level "
                      "(same step budget, fixed holdout)", describe_machine(m.machine), settings_line(m))
    table = [(per_level_text(p), p.get("n_train"), fmt(c * 60.0, 0), fmt(p.get("psnr")), fmt(p.get("ssim"), 4),
              p.get("gaussians"), fmt(p.get("train_s"), 1)) for p, c in zip(pts, capture_min)]
    rings = ", ".join(f"{num(v.get('distance_m')):.2f} m: {v.get('train_views')} training views, "
                      f"{fmt(v.get('capture_s_per_view'), 1)} s/view" for _, v in sorted(levels.items()))
    body = (f"Trainings of {m.settings.get('steps')} steps on subsets of each ring's training views, scored on the "
            f"same {m.summary.get('holdout_views')} holdout views. Rings: {rings}. Each run starts from its own "
            "depth frames; robot time = views x the ring's median time per view (travel + settle + exposure).\n\n"
            f"![holdout PSNR against views per ring]({png.name})\n\n"
            + format_table(["views per level", "train views", "robot s", "PSNR [dB]", "SSIM", "Gaussians",
                            "train s"], table)
            + "\n\n" + provenance(m) + "\n" + nan_note(dropped, "plotted view-sweep values"))
    return RenderedSection(TITLE, body, advice_views(pts, capture_min), [png])


def per_level_text(point: dict[str, Any]) -> str:
    """``"8/5"``: training views of each distance level, nearest first."""
    return "/".join(str(k) for k in point.get("views_per_level", [])) or "?"


def advice_views(pts: list[dict[str, Any]], capture_min: list[float]) -> str:
    """The fewest views per level within ``PSNR_TOLERANCE_DB`` of the most views, and the robot time saved."""
    scored = [(p, c) for p, c in zip(pts, capture_min) if math.isfinite(num(p.get("psnr")))]
    if len(scored) < 2:
        return ""
    best, best_c = scored[-1]
    p, c = next(s for s in scored if num(s[0]["psnr"]) >= num(best["psnr"]) - PSNR_TOLERANCE_DB)
    if p is best:
        prev = scored[-2][0]
        return (f"**Views per ring:** every subset lost more than {PSNR_TOLERANCE_DB} dB of holdout PSNR against "
                f"{per_level_text(best)} training views per level ({fmt(prev.get('psnr'))} dB with "
                f"{per_level_text(prev)} vs {fmt(best.get('psnr'))} dB): capture all of them.")
    saved = f", saving {fmt(best_c - c, 1)} min of robot time" if math.isfinite(best_c - c) else ""
    passes = num(best.get("steps")) / num(best.get("n_train"))
    caveat = (f"; at {best.get('steps')} steps the largest set was seen only {fmt(passes, 1)} times per view, so a "
              "longer training may still profit from more views" if passes < 5 else "")
    return (f"**Views per ring:** {per_level_text(p)} training views per level come within {PSNR_TOLERANCE_DB} dB "
            f"of {per_level_text(best)} ({fmt(p.get('psnr'))} vs {fmt(best.get('psnr'))} dB after "
            f"{p.get('steps', '?')} steps){saved}{caveat}.")


class ViewsSection:
    """Section 4 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> ViewsSweep:
        """The demo's sweep; quick: three subsets, 40 steps, at most 4000 Gaussians."""
        if quick:
            return ViewsSweep(fractions=(0.25, 0.5, 1.0), steps=40, evaluations=4, max_gaussians=4000)
        return ViewsSweep()

    def measure(self, inputs: MeasureInputs, settings: ViewsSweep) -> Measurement:
        return measure_views(inputs.scene, inputs.store, settings)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_views(measurements.get(NAME), out_dir)


SECTION = ViewsSection()

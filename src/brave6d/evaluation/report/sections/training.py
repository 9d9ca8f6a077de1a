"""Report section 1: holdout PSNR/SSIM against training time, steps and number of Gaussians.

Three sources, each drawn when it exists:

* the scene's own training run, ``splat/metrics.json``: its curve (train PSNR as an EMA,
  Gaussians, time per recorded step) and the final holdout scores;
* the JSON of ``benchmarks/training.py`` (default ``splat/benchmark_training.json``): holdout
  PSNR/SSIM at several steps of a full run;
* the report's own run on all training views (section 4's sweep), scored every few steps;
* the JSON of ``benchmarks/time_to_quality.py`` (default ``splat/time_to_quality.json``): two
  training schedules trained interleaved on one machine, drawn on one PSNR-against-time plot
  (``training_schedules.png``) with the time each takes to the first one's final PSNR.

Collecting reads files only (cheap); the result is cached like the measurements so that the
page can be rebuilt from ``report/measurements`` alone.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from brave6d.core.atomic import read_json
from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir
from brave6d.core.progress import format_table
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore, describe_machine, file_stamp, machine_info
from brave6d.evaluation.report.common import RenderedSection, first_reaching, fmt, nan_note, num, provenance, settings_line
from brave6d.evaluation.report.common import unavailable
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.sections.views import NAME as VIEWS
from brave6d.evaluation.report.plots import compact_xticks, legend, new_figure, plot_line, save_figure

NAME = "training"
PAGE = 1
TITLE = f"{PAGE}. Training: holdout quality against time, steps and Gaussians"
FIGURE = "training.png"
SCHEDULES_FIGURE = "training_schedules.png"
PSNR_TOLERANCE_DB = 0.5


def default_benchmark_json(scene: SceneDir) -> Path:
    """Where ``benchmarks/training.py`` writes its JSON by default."""
    return scene.benchmark_training_path


def default_schedules_json(scene: SceneDir) -> Path:
    """Where ``benchmarks/time_to_quality.py`` writes its JSON by default."""
    return scene.time_to_quality_path


def collect_training(scene: SceneDir, store: MeasurementStore, benchmark: Path | None = None,
                     schedules: Path | None = None) -> Measurement:
    """Read ``splat/metrics.json`` (and the benchmark and schedule-comparison JSONs if present)
    into the ``training`` measurement."""
    metrics_path = scene.metrics_path
    bench_path = benchmark or default_benchmark_json(scene)
    schedules_path = schedules or default_schedules_json(scene)
    if (absent := store.require(NAME, [(metrics_path, "training")])) is not None:
        return absent
    key = {"metrics": file_stamp(metrics_path), "benchmark": file_stamp(bench_path),
           "schedules": file_stamp(schedules_path)}
    metrics = read_json(metrics_path)
    # reading is cheap: always collect afresh (the cached copy serves write_report)
    m = Measurement(name=NAME, key=key, machine=machine_info(str(metrics.get("device", "cpu"))))
    hold = metrics.get("holdout") or {}
    images = metrics.get("images") or {}
    m.settings = {"preset": metrics.get("preset"), "steps": metrics.get("steps"),
                  "image": images.get("metrics_resolution"), "device": metrics.get("device"),
                  "max_gaussians": (metrics.get("preset_config") or {}).get("max_gaussians")}
    m.summary = {
        "steps": metrics.get("steps"), "train_s": metrics.get("train_time_s"), "total_s": metrics.get("total_time_s"),
        "gaussians": metrics.get("num_gaussians"), "psnr": hold.get("psnr"), "ssim": hold.get("ssim"),
        "per_level": {k: {"distance_m": v.get("distance_m"), "psnr": v.get("psnr"), "ssim": v.get("ssim")}
                      for k, v in (hold.get("per_level") or {}).items()},
        "n_train": metrics.get("n_train_views"), "n_holdout": metrics.get("n_holdout_views"),
        "stopped_by": metrics.get("stopped_by"), "planned_steps": metrics.get("planned_steps"),
        "time_budget": metrics.get("time_budget"),
        "init": (metrics.get("init") or {}).get("source"),
        "benchmark": None,
    }
    m.points = [{"source": "scene", "step": c.get("step"), "time_s": c.get("time_s"),
                 "gaussians": c.get("num_gaussians"), "train_psnr": c.get("train_psnr"),
                 "psnr": c.get("holdout_psnr")} for c in metrics.get("curve") or [] if num(c.get("step")) > 0]
    if bench_path.is_file():
        try:
            bench = read_json(bench_path)
            m.points += [{"source": "benchmark", "step": r.get("step"), "time_s": r.get("train_time_s"),
                          "gaussians": r.get("num_gaussians"), "psnr": r.get("holdout_psnr"),
                          "ssim": r.get("holdout_ssim")} for r in bench.get("points") or []]
            m.summary["benchmark"] = {"path": str(bench_path), "preset": bench.get("preset"),
                                      "device": bench.get("device"), "image_size": bench.get("image_size")}
        except (DataError, AttributeError) as exc:
            m.summary["benchmark"] = {"path": str(bench_path), "error": str(exc)}
    m.summary["schedules"] = None
    if schedules_path.is_file():
        try:
            points, m.summary["schedules"] = read_schedules(schedules_path)
            m.points += points
        except (DataError, AttributeError, KeyError, TypeError) as exc:
            m.summary["schedules"] = {"path": str(schedules_path), "error": f"{type(exc).__name__}: {exc}"}
    m.status = "complete"
    store.save(m)
    return m


def read_schedules(path: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The two holdout curves and the summary of a ``benchmarks/time_to_quality.py`` JSON."""
    data = read_json(path)
    points, runs = [], []
    for key in ("a", "b"):
        run = data[key]
        points += [{"source": "schedule", "schedule": run["name"], "step": p.get("step"), "time_s": p.get("time_s"),
                    "gaussians": p.get("gaussians"), "psnr": p.get("psnr"), "ssim": p.get("ssim")}
                   for p in run["points"]]
        preset = run.get("preset") or {}
        source = run.get("source") or {}
        runs.append({"name": run["name"], "preset": preset.get("name"), "steps": run.get("steps"),
                     # --a-source REV: the run trained with the code of that git revision
                     "revision": source.get("rev") if isinstance(source, dict) else None,
                     "train_s": run.get("train_s"), "final_psnr": run.get("final_psnr"),
                     "final_ssim": run.get("final_ssim"), "gaussians": run.get("gaussians"),
                     "gaussians_per_pixel": run.get("gaussians_per_pixel"),
                     "time_to_other_final": run.get("time_to_other_final"),
                     # the ratio's numerator: a run can reach its final PSNR before its last step
                     "time_to_own_final": run.get("time_to_own_final", run.get("train_s"))})
    return points, {"path": str(path), "device": data.get("device"), "ratio": data.get("ratio_time_to_a_final"),
                    "runs": runs}


# ----------------------------------------------------------------------------- rendering
def report_run(views: Measurement | None) -> dict[str, Any] | None:
    """Section 4's run on the most training views (its holdout curve), or None."""
    if views is None or not views.usable or not views.points:
        return None
    return max(views.points, key=lambda p: num(p.get("n_train")) if math.isfinite(num(p.get("n_train"))) else -1)


def curves(training: Measurement | None, views: Measurement | None) -> list[tuple[str, list[dict[str, Any]], str]]:
    """``(label, points with step/time_s/gaussians/psnr/ssim, marker)`` of every holdout source."""
    out = []
    if training is not None and training.usable:
        bench = [p for p in training.points if p.get("source") == "benchmark"]
        if bench:
            out.append(("benchmarks/training.py run", bench, "o-"))
        s = training.summary
        out.append((f"scene's training (final, {s.get('steps')} steps)",
                    [{"step": s.get("steps"), "time_s": s.get("train_s"), "gaussians": s.get("gaussians"),
                      "psnr": s.get("psnr"), "ssim": s.get("ssim")}], "*"))
    run = report_run(views)
    if run is not None:
        image = views.settings.get("image") if views is not None else None
        out.append((f"report run (all views, {run.get('steps')} steps, {image} images)", run.get("curve") or [], "s-"))
    return out


def render_training(training: Measurement | None, views: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 1 from the ``training`` and ``views`` measurements (either may be missing)."""
    sources = curves(training, views)
    if not sources:
        return unavailable(TITLE, training, "Training measurements")
    fig, axes = new_figure(3, 2)
    dropped = 0
    xs = (("time_s", "training time [s]"), ("step", "training step"), ("gaussians", "Gaussians"))
    scene_curve = [p for p in (training.points if training is not None else []) if p.get("source") == "scene"]
    for col, (field, xlabel) in enumerate(xs):
        ax_psnr, ax_ssim = axes[col], axes[3 + col]
        if scene_curve:  # a line over the Gaussians would zig-zag: Gaussians rise in steps
            dropped += plot_line(ax_psnr, [p.get(field) for p in scene_curve],
                                 [p.get("train_psnr") for p in scene_curve], "scene's training: train PSNR (EMA)",
                                 fmt="." if field == "gaussians" else "-",
                                 color="0.6", lw=1, ms=3)
        for label, pts, marker in sources:
            dropped += plot_line(ax_psnr, [p.get(field) for p in pts], [p.get("psnr") for p in pts], label, fmt=marker,
                                 ms=9 if marker == "*" else 4)
            dropped += plot_line(ax_ssim, [p.get(field) for p in pts], [p.get("ssim") for p in pts], label, fmt=marker,
                                 ms=9 if marker == "*" else 4)
        ax_psnr.set_ylabel("PSNR [dB]")
        ax_ssim.set_ylabel("holdout SSIM")
        for ax in (ax_psnr, ax_ssim):
            ax.set_xlabel(xlabel)
            compact_xticks(ax)
        legend(ax_psnr)
    provenance_of = training if training is not None and training.usable else views
    assert provenance_of is not None
    footer = settings_line(provenance_of) + ("" if views is None or not views.usable else
                                             f"; report run: {settings_line(views, ['preset', 'steps', 'image'])}")
    png = save_figure(fig, out_dir / FIGURE, "Holdout quality against training time, steps and Gaussians",
                      describe_machine(provenance_of.machine), footer)
    body = [f"![holdout quality against training time]({png.name})"]
    if training is not None and training.usable:
        body.append(_scene_text(training))
        if not any(label.startswith("benchmarks/") for label, _, _ in sources):
            body.append("For holdout scores along the scene's own preset, run `python benchmarks/training.py "
                        "SCENE_DIR` (it writes `splat/benchmark_training.json`, which this report reads) and "
                        "run `brave6d report` again.")
    else:
        body.append(unavailable(TITLE, training, "The scene's own training run").body)
    for label, pts, marker in sources:
        if marker == "*":
            continue
        rows = [(int(num(p.get("step"))) if math.isfinite(num(p.get("step"))) else "n/a", fmt(p.get("time_s"), 1),
                 p.get("gaussians"), fmt(p.get("psnr")), fmt(p.get("ssim"), 4)) for p in pts]
        body.append(f"**{label}:**\n\n" + format_table(["step", "train s", "Gaussians", "PSNR [dB]", "SSIM"], rows))
    figures = [png]
    schedules = (training.summary.get("schedules") if training is not None and training.usable else None) or {}
    advice = advice_training(sources, training)
    if schedules.get("runs"):
        assert training is not None
        curves_png, text, schedule_advice, n = render_schedules(training, schedules, out_dir)
        figures.append(curves_png)
        dropped += n
        body += [f"![holdout PSNR of two training schedules against time]({curves_png.name})", text]
        advice = f"{schedule_advice} {advice}".strip()
    elif schedules.get("error"):
        body.append(f"The schedule comparison {schedules.get('path')} could not be read: {schedules['error']}.")
    else:
        body.append("To compare two training schedules (e.g. the previous `fast` against today's), run "
                    "`python benchmarks/time_to_quality.py SCENE_DIR --a old=fast,... --b new=fast`; it writes "
                    "`splat/time_to_quality.json`, which this report plots.")
    body.append(provenance(provenance_of) + "\n" + nan_note(dropped, "plotted training values"))
    return RenderedSection(TITLE, "\n\n".join(body), advice, figures)


def render_schedules(training: Measurement, schedules: dict[str, Any], out_dir: Path
                     ) -> tuple[Path, str, str, int]:
    """The two schedules' holdout PSNR against time on one plot, their table and the advice that
    follows from it; returns ``(png, body text, advice, NaN values dropped)``."""
    a, b = schedules["runs"]
    target = num(a.get("final_psnr"))
    fig, axes = new_figure(1, 1, panel=(7.0, 4.0))
    ax = axes[0]
    dropped = 0
    for run in (a, b):
        pts = [p for p in training.points if p.get("source") == "schedule" and p.get("schedule") == run["name"]]
        dropped += plot_line(ax, [p.get("time_s") for p in pts], [p.get("psnr") for p in pts],
                             f"{run['name']}: {fmt(run.get('final_psnr'))} dB, {run.get('gaussians')} Gaussians, "
                             f"{fmt(run.get('train_s'), 0)} s", fmt="o-", ms=3)
    if math.isfinite(target):
        ax.axhline(target, color="0.5", lw=0.8, ls="--")
        ax.annotate(f"{a['name']}'s final {fmt(target)} dB", (0.01, target), xycoords=("axes fraction", "data"),
                    fontsize=7, va="bottom", color="0.4")
        for time_s in (a.get("time_to_own_final"), b.get("time_to_other_final")):
            if math.isfinite(num(time_s)):
                ax.axvline(num(time_s), color="0.7", lw=0.8, ls=":")
    ax.set_xlabel("training time [s] (holdout evaluation excluded)")
    ax.set_ylabel("holdout PSNR [dB]")
    legend(ax)
    png = save_figure(fig, out_dir / SCHEDULES_FIGURE, "Two training schedules, trained interleaved on one machine",
                      describe_machine(training.machine), f"device {schedules.get('device')}; {schedules.get('path')}")
    rows = [(r["name"], _preset_label(r), r.get("steps"), fmt(r.get("train_s"), 1), fmt(r.get("final_psnr")),
             fmt(r.get("final_ssim"), 4), r.get("gaussians"), fmt(r.get("gaussians_per_pixel"))) for r in (a, b)]
    text = ("**Training schedules** (`benchmarks/time_to_quality.py`, both trained in one process, alternating "
            "chunks of steps, so that both saw the same machine load):\n\n"
            + format_table(["schedule", "preset", "steps", "train s", "PSNR [dB]", "SSIM", "Gaussians",
                            "Gaussians / pixel"], rows))
    return png, text, advice_schedules(a, b, schedules.get("ratio")), dropped


def advice_schedules(a: dict[str, Any], b: dict[str, Any], ratio: Any) -> str:
    """Which schedule to choose, from the time each needs to A's final PSNR and where each ends."""
    target, b_final = num(a.get("final_psnr")), num(b.get("final_psnr"))
    b_time, a_time = num(b.get("time_to_other_final")), num(a.get("time_to_own_final"))
    name_a, name_b = _schedule_label(a), _schedule_label(b)
    if not math.isfinite(b_time):
        return (f"**Training schedule:** {name_b} ended at {fmt(b_final)} dB and never reached {name_a}'s "
                f"{fmt(target)} dB ({fmt(a_time, 0)} s): choose {name_a} when that quality is needed, "
                f"{name_b} ({fmt(b.get('train_s'), 0)} s) when {fmt(target - b_final)} dB less will do.")
    return (f"**Training schedule:** {name_b} reached {name_a}'s final {fmt(target)} dB after {fmt(b_time, 0)} s "
            f"against {fmt(a_time, 0)} s ({fmt(ratio)}x faster) and ended at {fmt(b_final)} dB with "
            f"{b.get('gaussians')} Gaussians (against {a.get('gaussians')}): choose {name_b}.")


def _preset_label(run: dict[str, Any]) -> str:
    """```preset```, with `` at REV`` when the run trained with the code of another revision."""
    preset, rev = run.get("preset"), run.get("revision")
    return f"`{preset}`" + (f" at {rev}" if rev else "") if preset else ""


def _schedule_label(run: dict[str, Any]) -> str:
    """``name (`preset` [at REV])``, or the name alone when it is the preset's (and no revision)."""
    preset = run.get("preset")
    if not preset or (preset == run["name"] and not run.get("revision")):
        return run["name"]
    return f"{run['name']} ({_preset_label(run)})"


def _scene_text(m: Measurement) -> str:
    s = m.summary
    levels = ", ".join(f"{fmt(v.get('distance_m'))} m: {fmt(v.get('psnr'))} dB"
                       for v in (s.get("per_level") or {}).values())
    return (f"The scene's training ({m.settings.get('preset')}, {m.settings.get('image')} images, "
            f"{s.get('n_train')} training / {s.get('n_holdout')} holdout views, init {s.get('init')}): "
            f"{s.get('steps')} of {s.get('planned_steps')} planned steps in {fmt(s.get('train_s'), 1)} s of training "
            f"({fmt(s.get('total_s'), 1)} s in all, stopped by {_stopped_by(s)}), {s.get('gaussians')} Gaussians, "
            f"holdout PSNR {fmt(s.get('psnr'))} dB, "
            f"SSIM {fmt(s.get('ssim'), 4)}" + (f" (per distance: {levels})" if levels else "") + ".")


def _stopped_by(summary: dict[str, Any]) -> str:
    """What stopped the run, in words: its steps, or its time budget (and what that counts)."""
    if summary.get("stopped_by") == "time budget":
        budget = summary.get("time_budget") or {}
        seconds = budget.get("budget_s")
        return ("its time budget" + (f" of {fmt(seconds, 0)} s for the whole train command, initial points included"
                                     if seconds is not None else "") + ": continue it with brave6d train --resume")
    return "reaching its planned steps" if summary.get("stopped_by") == "steps" else str(summary.get("stopped_by"))


def advice_training(sources: list[tuple[str, list[dict[str, Any]], str]], training: Measurement | None) -> str:
    """Where the longest holdout curve comes within ``PSNR_TOLERANCE_DB`` of its end, and the cost per step."""
    runs = [(label, pts) for label, pts, marker in sources if marker != "*" and len(pts) >= 2]
    text = ""
    if runs:
        label, pts = max(runs, key=lambda r: max(num(p.get("step")) for p in r[1]))
        final = pts[-1]
        i = first_reaching([p.get("psnr") for p in pts], num(final.get("psnr")) - PSNR_TOLERANCE_DB)
        if i is not None and i == len(pts) - 1:
            gain = num(final.get("psnr")) - num(pts[-2].get("psnr"))
            text = (f"**Training steps:** on the {label}, holdout PSNR was still rising at the end "
                    f"(+{fmt(gain)} dB over the last {int(num(final.get('step')) - num(pts[-2].get('step')))} steps, "
                    f"{fmt(final.get('psnr'))} dB after {int(num(final.get('step')))} steps): more steps still pay.")
        elif i is not None:
            knee = pts[i]
            text = (f"**Training steps:** on the {label}, {int(num(knee.get('step')))} steps "
                    f"({fmt(knee.get('time_s'), 1)} s, {knee.get('gaussians')} Gaussians) reach within "
                    f"{PSNR_TOLERANCE_DB} dB of the {fmt(final.get('psnr'))} dB after {int(num(final.get('step')))} "
                    f"steps ({fmt(final.get('time_s'), 1)} s).")
    if training is not None and training.usable:
        s = training.summary
        per_step = num(s.get("train_s")) / num(s.get("steps")) if num(s.get("steps")) > 0 else math.nan
        text += (f" The scene's training cost {fmt(1000.0 * per_step, 1)} s per 1000 steps here and ended at "
                 f"{fmt(s.get('psnr'))} dB with {s.get('gaussians')} Gaussians")
        planned = num(s.get("planned_steps"))
        if s.get("stopped_by") == "time budget" and planned > num(s.get("steps")):
            text += (f"; it hit its time budget after {s.get('steps')} of {int(planned)} planned steps, so the full "
                     f"schedule needs about {fmt(planned * per_step / 60.0, 1)} min of training on this machine")
        text += "."
    return text.strip()


@dataclass(frozen=True)
class TrainingSources:
    """Where the section reads from besides ``splat/metrics.json``: the benchmark JSON
    (None: :func:`default_benchmark_json`) and the schedule comparison (None:
    :func:`default_schedules_json`)."""

    benchmark_json: Path | None = None
    schedules_json: Path | None = None


class TrainingSection:
    """Section 1 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol (it also draws
    section 4's run on all views)."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> TrainingSources:
        return TrainingSources()

    def measure(self, inputs: MeasureInputs, settings: TrainingSources) -> Measurement:
        return collect_training(inputs.scene, inputs.store, settings.benchmark_json, settings.schedules_json)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_training(measurements.get(NAME), measurements.get(VIEWS), out_dir)


SECTION = TrainingSection()

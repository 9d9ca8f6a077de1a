"""The accuracy-vs-time report: rendering from measurement JSONs, cache and resume, missing inputs,
NaN handling, the baseline reader, and a miniature real measurement of every sweep."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore, run_sweep
from brave6d.evaluation.report.build import ReportSettings, build_report, compose, figure_names, measure_all, stage_report
from brave6d.evaluation.report.build import measurement_store, write_report
from brave6d.evaluation.report.sections.baseline import by_agent, collect_baseline, render_baseline
from brave6d.evaluation.report.common import RenderedSection, evenly_spaced, fmt, median, quantile
from brave6d.evaluation.report.sections.handeye import HandEyeSweep
from brave6d.evaluation.report.sections.latency import LatencySweep, render_latency
from brave6d.evaluation.report.plots import finite_pairs, new_figure, plot_line
from brave6d.evaluation.report.sections.training import collect_training, render_training
from brave6d.evaluation.report.sections.views import ViewsSweep, render_views
from brave6d.evaluation.report.sections.distance import render_distance
from brave6d.evaluation.report.sections.realism import render_realism
from brave6d.evaluation.report.sections.learned import VARIANTS as LEARNED_VARIANTS
from brave6d.evaluation.report.sections.synthesis import SynthSweep, advice_synthesis, measure_synthesis, render_synthesis
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.sections import SECTIONS, page_order

N_SECTIONS = len(SECTIONS)  # every count below follows the registry, so adding a section changes none

MACHINE = {"cpu": "Test CPU", "cores": 2, "gpu": None, "device": "cpu", "torch": "2.13.0", "torch_threads": 2}


# ----------------------------------------------------------------------------- fabricated measurements
def _save(store: MeasurementStore, name: str, points: list[dict], summary: dict, settings: dict | None = None,
          status: str = "complete") -> Measurement:
    m = Measurement(name=name, key={"test": True}, settings=settings or {"fixture": name}, machine=MACHINE,
                    status=status, points=points, summary=summary, seconds=1.0)
    store.save(m)
    return m


def fabricate(workdir: Path, nan: bool = False) -> MeasurementStore:
    """Plausible measurements for every section (``nan``: a few values missing)."""
    store = measurement_store(workdir)
    curve = [{"source": "scene", "step": s, "time_s": s * 0.1, "gaussians": 1000 + 10 * s,
              "train_psnr": 15 + s / 100, "psnr": None} for s in (30, 60, 90)]
    curve[-1]["psnr"] = 21.5
    _save(store, "training", curve, {"steps": 90, "train_s": 9.0, "total_s": 12.0, "gaussians": 1900, "psnr": 21.5,
                                     "ssim": 0.71, "per_level": {"0": {"distance_m": 0.3, "psnr": 22.0}},
                                     "n_train": 20, "n_holdout": 2, "stopped_by": "steps", "init": "colmap"},
          {"preset": "fast", "steps": 90, "image": "80x50"})
    he = []
    for n, errs in ((3, [0.9, 1.1, 3.0]), (6, [0.30, 0.35, 0.40]), (12, [0.10, 0.12, 0.14])):
        for r, mm in enumerate(errs):
            he.append({"id": f"n{n}-r{r}", "n": n, "solve_s": 0.1 * n, "accepted_by_default_limits": True,
                       "methods": {"refined": {"mm": mm, "deg": mm / 10, "time_s": 0.1 * n},
                                   "park": {"mm": 2 * mm, "deg": mm / 5, "time_s": 0.001}}})
    he.append({"id": "n3-r3", "n": 3, "error": "DegenerateGeometryError: rotation span", "solve_s": 0.01})
    _save(store, "handeye", he, {"n_frames": 12, "n_usable": 12, "truth": "simulation truth", "has_truth": True,
                                 "robot_s_per_pose": 2.0, "detect_s_per_frame": 0.02, "focal_px": 250.0,
                                 "nearest_m": 0.2})
    lat = [{"id": f"g{n}-{w}x{h}", "gaussians": n, "width": w, "height": h, "median_ms": n * w * h / 1e6,
            "p90_ms": None, "samples": 3} for n in (1000, 4000) for w, h in ((80, 50), (160, 100))]
    if nan:
        lat[0]["median_ms"] = None
    _save(store, "latency", lat, {"splat": "/x/point_cloud.ply", "n_total": 4000})
    views = []
    for k, psnr in ((2, 18.0), (5, 20.8), (10, 21.0)):
        views.append({"id": f"v{k}", "fraction": k / 10, "views_per_level": [k, k], "n_train": 2 * k, "steps": 40,
                      "psnr": None if (nan and k == 5) else psnr, "ssim": 0.5 + k / 100, "gaussians": 900,
                      "train_s": 3.0, "curve": [{"step": 20, "time_s": 1.5, "gaussians": 800, "psnr": psnr - 1,
                                                 "ssim": 0.5}, {"step": 40, "time_s": 3.0, "gaussians": 900,
                                                                "psnr": psnr, "ssim": 0.5 + k / 100}]})
    _save(store, "views", views, {"levels": {"0": {"distance_m": 0.3, "train_views": 10, "capture_s_per_view": 1.5},
                                             "1": {"distance_m": 0.45, "train_views": 10, "capture_s_per_view": 2.5}},
                                  "holdout_views": 2}, {"steps": 40, "preset": "fast"})
    base = [{"agent": "active", "ar": 0.6, "adjustments": 4, "wall_s": 10.0, "object": "a"},
            {"agent": "active", "ar": 0.8, "adjustments": 6, "wall_s": 12.0, "object": "b"},
            {"agent": "static", "ar": 0.3, "adjustments": 0, "wall_s": 2.0, "object": "a"},
            {"agent": "static", "ar": 0.5 if not nan else None, "adjustments": 0, "wall_s": 2.0, "object": "b"}]
    _save(store, "baseline", base, {"episodes": 4}, {"source": "/x/baseline.json"})
    dist = []
    for obj_id, name in ((1, "cup"), (2, "nut")):
        for d, ar in ((0.2, 0.9), (0.35, 0.6), (0.5, 0.2)):
            ar = ar if obj_id == 1 else ar / 2
            dist.append({"id": f"o{obj_id}-d{d}", "obj_id": obj_id, "object": name, "distance_m": d, "target": True,
                         "found": True, "ar": None if (nan and obj_id == 2 and d == 0.35) else ar, "ar_vsd": ar,
                         "ar_mssd": ar, "ar_mspd": ar, "px_visib": 4000 * (0.2 / d) ** 2, "bbox_diag_px": 80 * 0.2 / d,
                         "visib_fract": 1.0, "estimate_s": 1.0, "render_s": 0.05})
    dist.append({"id": "o2-hidden", "obj_id": 2, "object": "nut", "distance_m": 0.5, "target": False,
                 "visib_fract": 0.02, "render_s": 0.05})
    _save(store, "distance", dist, {"bundle": "/x/bundle"}, {"views": 1, "image": "160x100"})
    real = []
    for level, d, psnr in ((0, 0.2, 30.0), (1, 0.5, 24.0)):
        objects = [{"obj_id": 1, "object": "cup", "visib_fract": 1.0, "bbox_diag_px": 50.0, "real_ar": 0.8,
                    "splat_ar": 0.75 if level == 0 else 0.2, "real_found": True, "splat_found": True,
                    "real_estimate_s": 1.0, "splat_estimate_s": 1.0},
                   {"obj_id": 2, "object": "nut", "visib_fract": 1.0, "bbox_diag_px": 40.0, "real_ar": 0.5,
                    "splat_ar": 0.5, "real_found": True, "splat_found": True, "real_estimate_s": 1.0,
                    "splat_estimate_s": 1.0}]
        real.append({"id": f"im{level}", "im_id": level, "level": level, "distance_m": d, "holdout": True,
                     "psnr": None if (nan and level == 1) else psnr, "ssim": 0.9, "render_s": 0.1, "objects": objects})
    _save(store, "realism", real, {"bop": "/x/bop/test/000001"}, {"views": 2, "image": "160x100"})
    synth = [{"id": f"{w}x{h}-w{n}", "width": w, "height": h, "workers": n, "images": 8,
              "images_per_s": None if (nan and w == 640 and n == 2) else rate}
             for (w, h), n, rate in (((320, 240), 1, 4.0), ((320, 240), 2, 6.0), ((640, 480), 1, 1.0),
                                     ((640, 480), 2, 1.6))]
    fid = [{"id": f"o1-d{round(d * 1000)}", "obj_id": 1, "object": "cup", "distance_m": d, "psnr": 30.0 - d,
            "ssim": 0.95, "render_s": 0.1,
            "targets": [{"obj_id": 1, "object": "cup", "px": round(400 / d), "visib_fract": 1.0, "box_psnr": 26.0 + 8 * d,
                         "box_ssim": 0.9, "depth_px": round(400 / d), "depth_median_mm": None if (nan and d == 0.5) else 2.5,
                         "within_5mm": 0.7, "within_15mm": 0.85, "no_depth": 0.0, "ar_truth": 0.8,
                         "ar_splat": 0.3}]} for d in (0.1, 0.2, 0.5)]
    _save(store, "fidelity", fid, {"bundle": "/x/bundle", "mode": "simulated"}, {"views": 1, "image": "160x100"})
    _save(store, "synthesis", synth, {"spec": "/x/scene.yaml", "objects": ["cup", "nut"]},
          {"sizes": ["320x240", "640x480"], "workers": [1, 2], "images": 8})
    learned = [{"id": f"im{level}", "im_id": level, "level": level, "distance_m": d, "holdout": True, "render_s": 0.1,
                "objects": [{"obj_id": 1, "object": "cup", "visib_fract": 1.0, "bbox_diag_px": 50.0,
                             **{f"{side}_{v}_ar": 0.5 for side in ("real", "splat") for v in LEARNED_VARIANTS}}]}
               for level, d in ((0, 0.2), (1, 0.5))]
    _save(store, "learned", learned, {"cost": str(workdir / "learned" / "cost" / "learned_cost.json"), "card": {}}, {"views": 2, "image": "160x100"})
    return store


def _valid_png(path: Path) -> tuple[int, int]:
    with Image.open(path) as im:
        im.verify()
    with Image.open(path) as im:
        assert im.format == "PNG"
        return im.size


def test_report_from_fabricated_measurements(tmp_path: Path) -> None:
    fabricate(tmp_path)
    result = write_report(tmp_path)
    md = result.markdown.read_text()
    assert [p.name for p in result.figures] == [s.figure for s in page_order()]
    assert {"training.png", "handeye.png", "latency.png", "views.png", "baseline.png", "distance.png",
            "realism.png", "synthesis.png", "fidelity.png", "learned.png"} <= {p.name for p in result.figures}
    for png in result.figures:
        w, h = _valid_png(png)
        assert w > 400 and h > 250
        assert f"]({png.name})" in md
    assert md.count("\n## ") == N_SECTIONS + 1 and "## How to choose settings" in md
    # numbers on the page are those of the JSON
    he = read_json(tmp_path / "report" / "measurements" / "handeye.json")["points"]
    mm6 = [p["methods"]["refined"]["mm"] for p in he if p["n"] == 6]
    assert re.search(rf"\| 6 +\| 3/3 +\| 3 +\| {fmt(median(mm6), 3)} +\| {fmt(quantile(mm6, 0.25), 3)}-", md)
    assert re.search(r"\| 3 +\| 3/4 ", md)  # the failed trial is counted, not hidden
    assert re.search(r"\| 4,000 +\| 16\.0 +\| 64\.0 +\|", md)  # latency = Gaussians x pixels / 1e6
    assert re.search(r"\| 5/5 +\| 10 +\| 20 +\| 20\.80 +\| 0\.5500 ", md)  # views: robot s = 5 * 1.5 + 5 * 2.5
    assert re.search(r"\| active +\| n/a +\| 2 +\| 0\.700 +\| 5\.0 ", md)  # a measurement without a mode
    assert "holdout PSNR 21.50 dB" in md
    # advice derived from the numbers
    advice = md.split("## How to choose settings")[1]
    # half a pixel at 0.2 m with f = 250 px: 0.4 mm / 0.115 deg; 3 poses had a failed trial
    assert "6 poses keep the error against the truth within half a pixel" in advice
    assert "5/5 training views per level come within 0.5 dB of 10/10" in advice
    assert "0.060 AR per adjustment" in advice  # (0.7 - 0.4) / 5
    assert "Latency grows as Gaussians^1.00 x pixels^1.00" in advice
    # distance study: rows pool both objects' views (the hidden view is no target), pixel size beside AR
    assert re.search(r"\| 20 +\| 2/2 +\| 2 +\| 0\.675 +\| 0\.675 +\| 0\.675 +\| 0\.675 +\| 4000 +\| 80 +\| 1\.00 ", md)
    assert re.search(r"\| 50 +\| 2/3 +\| 2 +\| 0\.150 ", md)
    assert re.search(r"\| cup \(1\) +\| 0\.90 +\| 0\.60 +\| 0\.20 +\|", md)
    assert "scores best at 20 cm (AR 0.675, objects about 80 px across) and worst at 50 cm (AR 0.150, 32 px)" in advice
    assert "below 75% of the best at 35, 50 cm" in advice and "The weakest object is nut" in advice
    # realism: gap = real - splat per level, and where it is large
    assert re.search(r"\| 20 +\| 1 \(1 held out\) +\| 2 +\| 30\.00 +\| 0\.900 +\| 0\.650 +\| 0\.625 +\| 0\.025 ", md)
    assert re.search(r"\| 50 +\| 1 \(1 held out\) +\| 2 +\| 24\.00 +\| 0\.900 +\| 0\.650 +\| 0\.350 +\| 0\.300 ", md)
    assert "Large gaps (|gap| >= 0.10): cup at 50 cm (0.80 real vs 0.20 splat over 1 targets)." in md
    assert "What \"real\" means here:** in the demo the captured frames come from the simulated camera" in md
    assert "differs between captured frames and splat renders by at most 0.300 (at 50 cm" in advice
    assert "trust splat scores least at 50 cm (largest: cup)" in advice
    # synthesis: images/s per size and workers, hours for 10k images = 10000 / rate / 3600
    assert re.search(r"\| 320x240 +\| 1 +\| 8 +\| 4\.00 +\| 0\.25 +\| 0\.7 +\|", md)
    assert re.search(r"\| 640x480 +\| 2 +\| 8 +\| 1\.60 +\| 0\.62 +\| 1\.7 +\|", md)
    assert "with 1 worker 320x240: 4.00 images/s; 640x480: 1.00 images/s" in advice
    assert "2 workers render 1.50-1.60x faster on this machine (2 cores, 8-image runs): use --workers 2" in advice
    assert "10,000 images at 640x480 take about 1.7 h here (2 workers)" in advice
    assert "NaN" not in md


def test_nan_values_are_named_not_plotted_silently(tmp_path: Path) -> None:
    store = fabricate(tmp_path, nan=True)
    out = tmp_path / "report"
    latency = render_latency(store.load("latency"), out).body
    assert "2 latency cells had no finite value" in latency  # one cell, drawn in both panels
    assert re.search(r"\| 1,000 +\| n/a +\|", latency)  # the table shows the gap as n/a
    views = render_views(store.load("views"), out).body
    assert "2 plotted view-sweep values had no finite value" in views and re.search(r"\| 5/5 .*\| n/a +\|", views)
    baseline = render_baseline(store.load("baseline"), out).body
    assert "1 plotted episode values had no finite" in baseline
    distance = render_distance(store.load("distance"), out).body
    assert re.search(r"\| nut \(2\) +\| 0\.45 +\| n/a +\| 0\.10 +\|", distance)
    realism = render_realism(store.load("realism"), out).body
    assert "plotted real-vs-splat values had no finite value" in realism and re.search(r"\| 50 .*\| n/a +\|", realism)
    synthesis = render_synthesis(store.load("synthesis"), out)
    assert "1 plotted synthesis rates had no finite value" in synthesis.body
    assert re.search(r"\| 640x480 +\| 2 +\| 8 +\| n/a +\| n/a +\| n/a +\|", synthesis.body)
    assert "10,000 images at 640x480 take about 2.8 h here (1 worker)" in synthesis.advice  # the finite rate
    fig, (ax,) = new_figure(1)
    dropped = plot_line(ax, [1, 2, 3, 4], [1.0, float("nan"), None, 2.0], "series")
    assert dropped == 2 and ax.get_legend_handles_labels()[1] == ["series (2 NaN not drawn)"]
    assert finite_pairs([1, None, 3], [float("inf"), 2, 3]) == ([3.0], [3.0], 2)
    assert plot_line(ax, [1, 2], [None, None], "empty") == 2
    assert ax.get_legend_handles_labels()[1][-1] == "empty (2 NaN not drawn): no finite values"


def test_missing_inputs_give_section_notes(tmp_path: Path) -> None:
    (tmp_path / "scene").mkdir()
    stage = stage_report(SimpleNamespace(workdir=tmp_path, quick=True, device="cpu"))  # the demo's last stage
    assert stage.status == "ok" and stage.figures["plots"] == 0
    assert stage.figures["incomplete"] == "+".join(s.name for s in SECTIONS)  # measuring order
    md = (tmp_path / "report" / "report.md").read_text()
    assert md.count("**Not available.**") == N_SECTIONS
    assert "board_capture/frames.jsonl` (run the calibration stage)" in md
    assert "evaluation/baseline.json` (run the evaluation stage)" in md
    assert "splat/metrics.json` (run the training stage)" in md
    assert not any((tmp_path / "report" / f).exists() for f in figure_names())
    assert "No section has enough measurements" in md


def test_page_renders_from_nothing_from_a_broken_file_and_from_a_partial_sweep(tmp_path: Path) -> None:
    md = write_report(tmp_path).markdown.read_text()
    assert md.count("nothing measured yet") == N_SECTIONS
    store = measurement_store(tmp_path)
    _save(store, "latency", [{"id": "x", "median_ms": 3.0}], {})  # hand-edited: no gaussians/width/height
    md = write_report(tmp_path).markdown.read_text()
    assert "could not be rendered (KeyError: 'width'); run `brave6d report --refresh`" in md
    store = fabricate(tmp_path)
    views = store.load("views")
    assert views is not None
    views.status, views.points = "partial", views.points[:2]
    assert "**Partial sweep (2 points so far).**" in render_views(views, tmp_path / "report").body
    assert "views (partial, 2 points)" in compose(tmp_path, [], {"views": views}, {})


def test_training_section_reads_metrics_and_the_benchmark_json(tmp_path: Path) -> None:
    from brave6d.core.layout import SceneDir

    scene = SceneDir(tmp_path / "scene")
    curve = [{"step": 0.0, "time_s": 0.0, "train_psnr": None, "num_gaussians": 100.0},
             {"step": 50.0, "time_s": 5.0, "train_psnr": 20.0, "num_gaussians": 400.0},
             {"step": 100.0, "time_s": 10.0, "train_psnr": 24.0, "num_gaussians": 800.0, "holdout_psnr": 22.0}]
    atomic_write_json(scene.splat_dir / "metrics.json", {
        "preset": "fast", "device": "cpu", "steps": 100, "planned_steps": 200, "stopped_by": "time budget",
        "train_time_s": 10.0, "total_time_s": 15.0, "num_gaussians": 800, "n_train_views": 9, "n_holdout_views": 1,
        "holdout": {"psnr": 22.0, "ssim": 0.8, "per_level": {"0": {"distance_m": 0.3, "psnr": 22.0, "ssim": 0.8}}},
        "images": {"metrics_resolution": "80x50"}, "init": {"source": "colmap"}, "preset_config": {}, "curve": curve})
    atomic_write_json(scene.splat_dir / "benchmark_training.json", {"preset": "fast", "points": [
        {"step": s, "train_time_s": s / 10, "holdout_psnr": p, "holdout_ssim": 0.7, "num_gaussians": 500}
        for s, p in ((0, 10.0), (50, 21.0), (100, 21.4), (150, 21.6))]})
    store = MeasurementStore(tmp_path / "m")
    m = collect_training(scene, store)
    assert [p["source"] for p in m.points] == ["scene", "scene"] + ["benchmark"] * 4  # step 0 has no EMA yet
    section = render_training(m, None, tmp_path / "out")
    assert "holdout PSNR 22.00 dB" in section.body and re.search(r"\| 150 +\| 15\.0 +\| 500 +\| 21\.60 ", section.body)
    assert "run `python benchmarks/training.py" not in section.body
    assert ("on the benchmarks/training.py run, 100 steps (10.0 s, 500 Gaussians) reach within 0.5 dB of the "
            "21.60 dB after 150 steps") in section.advice  # 21.4 >= 21.6 - 0.5 > 21.0
    assert "hit its time budget after 100 of 200 planned steps, so the full schedule needs about 0.3 min" \
        in section.advice
    _valid_png(tmp_path / "out" / "training.png")


# ----------------------------------------------------------------------------- the section registry
class ExtraSection:
    """One more section, known to the report only through the registry (on the next free page)."""

    name, page, figure = "extra", N_SECTIONS + 1, "extra.png"
    title = f"{N_SECTIONS + 1}. Extra: a registered section"

    def settings(self, quick: bool) -> dict:
        return {"quick": quick}

    def measure(self, inputs: MeasureInputs, settings: dict) -> Measurement:
        m = Measurement(name=self.name, settings=dict(settings), machine=MACHINE, status="complete",
                        points=[{"answer": 42}], summary={"scene": inputs.scene.root.name})
        inputs.store.save(m)
        return m

    def render(self, measurements: dict, out_dir: Path) -> RenderedSection:
        m = measurements.get(self.name)
        answer = m.points[0]["answer"] if m is not None else "none"
        return RenderedSection(self.title, f"The answer is {answer}.", advice="**Extra:** registered once.")


@pytest.mark.slow
def test_a_section_added_to_the_registry_is_measured_and_on_the_page(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    from brave6d.evaluation.report import sections

    monkeypatch.setattr(sections, "SECTIONS", (*sections.SECTIONS, ExtraSection()))
    fabricate(tmp_path)
    measured, _ = measure_all(tmp_path, ReportSettings.for_mode(quick=True), only=("extra",))
    assert list(measured) == ["extra"] and measured["extra"].settings == {"quick": True}
    md = write_report(tmp_path).markdown.read_text()
    last = max(SECTIONS, key=lambda s: s.page).title  # the registry before the patch
    assert md.count("\n## ") == N_SECTIONS + 2
    assert md.index(f"## {last}") < md.index(f"## {ExtraSection.title}") < md.index("## How to")
    assert "The answer is 42." in md and "**Extra:** registered once." in md
    assert "extra (complete)" in md.splitlines()[6]  # the header's list of sections


def test_report_settings_reach_every_section_generically() -> None:
    from brave6d.evaluation.report import sections

    quick = ReportSettings.for_mode(True, "cpu", Path("bench.json"))
    full = ReportSettings.for_mode(False)
    by_name = {s.name: s for s in sections.SECTIONS}
    assert quick.for_section(by_name["latency"]).device == "cpu" and quick.for_section(by_name["views"]).device == "cpu"
    assert full.for_section(by_name["views"]).device == "auto"
    assert quick.for_section(by_name["training"]).benchmark_json == Path("bench.json")
    assert quick.for_section(by_name["handeye"]) == HandEyeSweep(sizes=(3, 5, 8, 12), repeats=3)
    assert full.for_section(by_name["handeye"]) == HandEyeSweep()
    assert quick.for_section(by_name["views"]).steps < full.for_section(by_name["views"]).steps
    assert ReportSettings().for_section(by_name["latency"]) == LatencySweep()  # not named: the full defaults
    assert [s.page for s in sections.page_order()] == list(range(1, N_SECTIONS + 1))
    assert all(s.title.startswith(f"{s.page}. ") for s in sections.SECTIONS)


# ----------------------------------------------------------------------------- cache and resume
def test_sweep_resumes_after_an_interruption_and_refresh_remeasures(tmp_path: Path) -> None:
    calls: list[int] = []
    interrupt = {"at": 2}

    def measure(x: int) -> dict:
        calls.append(x)
        if x == interrupt["at"]:
            raise KeyboardInterrupt
        return {"x": x, "y": x * x}

    items = [(f"p{x}", x) for x in range(5)]
    store = MeasurementStore(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(store, store.resume("sq", {"k": 1}, {}, {}), items, measure, "test")
    saved = store.load("sq")
    assert saved is not None and saved.status == "partial" and [p["x"] for p in saved.points] == [0, 1]
    interrupt["at"] = -1
    m = run_sweep(store, store.resume("sq", {"k": 1}, {}, {}), items, measure, "test")
    assert calls == [0, 1, 2, 2, 3, 4] and m.status == "complete" and [p["y"] for p in m.points] == [0, 1, 4, 9, 16]
    assert run_sweep(store, store.resume("sq", {"k": 1}, {}, {}), items, measure, "test").points == m.points
    assert len(calls) == 6  # complete with the same key: nothing is measured again
    run_sweep(store, store.resume("sq", {"k": 2}, {}, {}), items, measure, "test")  # the inputs changed
    assert len(calls) == 11
    fresh = MeasurementStore(tmp_path, refresh=True)
    run_sweep(fresh, fresh.resume("sq", {"k": 2}, {}, {}), items, measure, "test")
    assert len(calls) == 16
    assert json.loads((tmp_path / "sq.json").read_text())["points"][4]["y"] == 16


def test_nan_in_a_point_is_stored_as_null(tmp_path: Path) -> None:
    store = MeasurementStore(tmp_path)
    m = run_sweep(store, store.resume("n", {}, {}, {}), [("a", 1)], lambda _: {"v": float("nan")}, "t")
    assert m.points[0]["v"] is None and read_json(tmp_path / "n.json")["points"][0]["v"] is None


# ----------------------------------------------------------------------------- baseline reader
def _agent_runs_file(workdir: Path) -> Path:
    """An agent-run summary whose leaderboard AR (pooled) differs from the mean of the episodes' ARs."""
    from brave6d.evaluation.metrics import AgentRuns, agent_runs_path, write_agent_runs

    def episode(agent: str, obj: str, ar: float, adjustments: int, wall: float | None) -> dict:
        return {"agent": agent, "variant": agent, "object": obj, "gt_id": 0, "obj_id": 1, "seed": 0,
                "episode_id": f"{agent}-{obj}", "ar": ar, "ar_vsd": ar, "ar_mssd": ar, "ar_mspd": ar,
                "adjustments": adjustments, "wall_time_s": wall, "target_distance_m": 0.3, "found": True,
                "registration_method": "resting", "registration_score": 0.7}

    def agent(name: str, ar: float, adjustments: float, wall: float | None) -> dict:
        return {"agent": name, "mode": "scored", "episodes": 2, "submitted": 2, "n_targets": 2, "ar": ar, "ar_vsd": ar,
                "ar_mssd": ar, "ar_mspd": ar, "mean_adjustments": adjustments, "mean_wall_time_s": wall}

    runs = AgentRuns.model_validate({
        "mode": "scored", "bundle": "b", "image_size": [320, 200], "metrics": ["vsd", "mssd", "mspd"],
        "agents": [agent("active", 0.7, 5.0, 4.0), agent("static", 0.25, 0.0, None)],
        "episodes": [episode("active", "nut", 0.5, 4, 3.0), episode("active", "cup", 1.0, 6, 5.0),
                     episode("static", "nut", 0.2, 0, 1.0), episode("static", "cup", 0.4, 0, None)]})
    return write_agent_runs(agent_runs_path(workdir), runs)


def test_baseline_section_shows_the_files_agent_rows(tmp_path: Path) -> None:
    _agent_runs_file(tmp_path)
    m = collect_baseline(tmp_path, MeasurementStore(tmp_path / "m"))
    assert m.status == "complete" and m.summary["episodes"] == 4
    assert [(p["agent"], p["object"], p["ar"], p["adjustments"]) for p in m.points] == [
        ("active", "nut", 0.5, 4.0), ("active", "cup", 1.0, 6.0),
        ("static", "nut", 0.2, 0.0), ("static", "cup", 0.4, 0.0)]
    rows = {r["agent"]: r for r in by_agent(m.points, m.summary["agents"])}
    assert rows["active"]["ar"] == 0.7 and rows["active"]["adjustments"] == 5.0  # pooled AR, not the 0.75 mean
    assert rows["static"]["ar"] == 0.25 and rows["static"]["wall_s"] == 1.0  # no mean wall time in the file: episodes'
    section = render_baseline(m, tmp_path / "report")
    assert re.search(r"\| active +\| scored +\| 2 +\| 0\.700 +\| 5\.0 +\| 4\.0 +\|", section.body)
    assert re.search(r"\| static +\| scored +\| 2 +\| 0\.250 +\| 0\.0 +\| 1\.0 +\|", section.body)
    assert "ran in **scored** mode" in section.body and m.summary["mode"] == "scored"
    assert "AR is the leaderboard's" in section.body and "1 plotted episode values had no finite" not in section.body
    assert "0.450 more AR (0.250 -> 0.700: 0.090 AR per adjustment)" in section.advice


def test_baseline_section_gives_active_minus_static_paired_by_start(tmp_path: Path) -> None:
    from brave6d.evaluation.metrics import AgentRuns, agent_runs_path, write_agent_runs

    def episode(agent: str, seed: int, ar: float) -> dict:
        return {"agent": agent, "variant": "active" if "active" in agent else "static", "object": "nut", "gt_id": 0,
                "obj_id": 1, "seed": seed, "episode_id": f"{agent}-{seed}", "ar": ar, "ar_vsd": ar, "ar_mssd": ar,
                "ar_mspd": ar, "adjustments": 3 if "active" in agent else 0, "wall_time_s": 1.0,
                "target_distance_m": 0.3, "found": True, "registration_method": None, "registration_score": None}

    def agent(name: str, ar: float) -> dict:
        return {"agent": name, "mode": "scored", "episodes": 6, "submitted": 6, "n_targets": 6, "ar": ar, "ar_vsd": ar,
                "ar_mssd": ar, "ar_mspd": ar, "mean_adjustments": 3.0 if "active" in name else 0.0,
                "mean_wall_time_s": 1.0}

    static = [0.2, 0.8, 0.4, 0.6, 0.1, 0.9]  # starts of very different difficulty, the active agent +0.1 on each
    write_agent_runs(agent_runs_path(tmp_path), AgentRuns.model_validate({
        "mode": "scored", "bundle": "b", "image_size": [320, 200], "metrics": ["vsd", "mssd", "mspd"],
        "agents": [agent("x-active", 0.6), agent("x-static", 0.5)],
        "episodes": [episode("x-static", i, a) for i, a in enumerate(static)]
        + [episode("x-active", i, a + 0.1) for i, a in enumerate(static)]}))
    m = collect_baseline(tmp_path, MeasurementStore(tmp_path / "m"))
    [paired] = m.summary["paired"]
    assert paired["pairs"] == 6 and abs(paired["mean"] - 0.1) < 1e-9 and paired["se"] < 1e-9
    section = render_baseline(m, tmp_path / "report")
    assert re.search(r"\| x-active +\| x-static +\| 6 +\| \+0\.100 +\| 0\.000 +\| resolved", section.body)
    assert "Paired by start, x-active - x-static = +0.100 ± 0.000 over 6 starts (resolved (no spread))" in section.advice


def test_a_version_one_summary_reads_as_training_mode(tmp_path: Path) -> None:
    """Version 1 predates the modes: its server served the ground truth, and section 5 says so."""
    path = _agent_runs_file(tmp_path)
    raw = json.loads(path.read_text())
    raw["format"] = "brave6d-baseline/1"
    del raw["mode"]
    for a in raw["agents"]:
        del a["mode"]
    path.write_text(json.dumps(raw))
    m = collect_baseline(tmp_path, MeasurementStore(tmp_path / "m"))
    assert m.status == "complete" and m.summary["mode"] == "training"
    body = render_baseline(m, tmp_path / "report").body
    assert "ran in **training** mode" in body and re.search(r"\| active +\| training +\|", body)


def test_agent_motion_advice_pairs_each_active_agent_with_its_own_static_one() -> None:
    from brave6d.evaluation.report.sections.baseline import advice_baseline

    def row(agent: str, ar: float, adjustments: float) -> dict:
        return {"agent": agent, "ar": ar, "adjustments": adjustments}

    rows = [row("baseline-active", 0.949, 3.8), row("baseline-static", 0.936, 0.0), row("learned-active", 0.515, 4.0),
            row("learned-static", 0.262, 0.0), row("learned-active-depth", 0.5, 3.5),
            row("learned-static-depth", 0.62, 0.0)]
    advice = advice_baseline(rows)
    assert "baseline-active spends 3.8 more adjustments per episode than baseline-static for 0.013 more AR" in advice
    assert "learned-active spends 4.0 more adjustments per episode than learned-static for 0.253 more AR" in advice
    assert "learned-active-depth spends 3.5 more adjustments per episode than learned-static-depth and scores " \
           "0.120 less AR" in advice
    assert "than baseline-static and scores" not in advice  # never an active agent against another estimator
    # without pairs: the most-moving agent against the least, as before; one agent: nothing to compare
    assert "b spends 2.0 more adjustments per episode than a for 0.100 more AR" in advice_baseline(
        [row("a", 0.5, 1.0), row("b", 0.6, 3.0)])
    assert advice_baseline([row("baseline-active", 0.9, 3.0)]) == ""


@pytest.mark.parametrize(("change", "field"), [
    (lambda raw: raw.update(format="brave6d-baseline/3"), "format"),
    (lambda raw: raw["episodes"][2].pop("adjustments"), "episodes[2].adjustments"),
    (lambda raw: raw["agents"][0].update(ar="n/a"), "agents[0].ar"),
])
def test_baseline_section_notes_a_malformed_file(tmp_path: Path, change: object, field: str) -> None:
    path = _agent_runs_file(tmp_path)
    raw = json.loads(path.read_text())
    change(raw)  # type: ignore[operator]
    path.write_text(json.dumps(raw))
    m = collect_baseline(tmp_path, MeasurementStore(tmp_path / "m"))
    assert m.status == "failed" and m.note.startswith(f"{path}: field '{field}'")
    body = render_baseline(m, tmp_path / "report").body
    assert body.startswith("> **Not available.** Baseline episodes: measuring failed: ") and f"'{field}'" in body


def test_baseline_file_not_json(tmp_path: Path) -> None:
    path = tmp_path / "evaluation" / "baseline.json"
    path.parent.mkdir()
    path.write_text("{not json")
    m = collect_baseline(tmp_path, MeasurementStore(tmp_path / "m"))
    assert m.status == "failed" and m.note.startswith(f"{path}: not valid JSON")


# ----------------------------------------------------------------------------- real, miniature sweeps
def _board_capture(scene_root: Path, n_views: int = 8) -> None:
    """A rendered ChArUco board capture of the demo spec's board with exact robot poses."""
    from brave6d.core.atomic import write_png
    from brave6d.core.calibration_io import write_intrinsics
    from brave6d.core.camera import PinholeCamera
    from brave6d.core.layout import FrameLog, FrameRecord, SceneDir
    from brave6d.core.transforms import invert
    from brave6d.calibration import plan_for_board
    from brave6d.calibration.known_truth import render_board_view

    scene = SceneDir(scene_root)
    spec = scene.load_spec()
    X = spec.simulation.true_tcp_T_camera.matrix()
    camera = PinholeCamera.from_hfov(640, 480, 60.0)
    W = spec.board.pose.matrix()
    frames = FrameLog(scene.board_capture.frames_path)
    for i, p in enumerate(plan_for_board(spec.board, 0.3, X, n_views, K=camera.K, image_size=(640, 480))):
        grey = render_board_view(spec.board, camera.K, invert(p.base_T_tcp @ X) @ W, (640, 480), supersample=2)
        write_png(scene.board_capture.root / f"rgb/{i:06d}.png", np.repeat(grey[:, :, None], 3, axis=2))
        frames.append(FrameRecord(index=i, view_id=p.name, distance_level=0, distance_m=0.3, rgb=f"rgb/{i:06d}.png",
                                  base_T_tcp=p.base_T_tcp.tolist(), joints=[0.0] * 6, timestamp=2.5 * i))
    write_intrinsics(scene, camera, method="synthetic")


def _plane_scene(root: Path) -> None:
    """A captured, calibrated plane scene with a small random splat in ``splat/``."""
    from brave6d.core.camera import PinholeCamera
    from brave6d.training.ply import SplatData, write_ply
    from brave6d.training.toy_scenes import plane_views, random_gaussians, write_scene

    camera = PinholeCamera.from_hfov(64, 48, 60.0)
    write_scene(root, camera, plane_views(camera, [0.3, 0.45], per_ring=5))
    g = {k: v.numpy() for k, v in random_gaussians(400, extent=0.1).items()}
    write_ply(root / "splat" / "point_cloud.ply", SplatData(g["means"], g["sh0"], g["shN"], g["opacities"],
                                                            g["scales"], g["quats"],  # trained with mip
                                                            filter_3d=np.full(400, 1e-3, np.float32)))


@pytest.mark.slow
def test_miniature_sweeps_measure_real_numbers(tmp_path: Path, demo_spec_path: Path) -> None:
    from brave6d.core.layout import init_scene_dir

    init_scene_dir(tmp_path / "hand" / "scene", demo_spec_path)
    _board_capture(tmp_path / "hand" / "scene")
    settings = ReportSettings({
        "handeye": HandEyeSweep(sizes=(3, 5), repeats=2),
        "latency": LatencySweep(fractions=(0.5, 1.0), scales=(0.5, 1.0), repeats=1, views=1, device="cpu"),
        "views": ViewsSweep(fractions=(0.5, 1.0), steps=4, evaluations=2, max_gaussians=500, downscale=None,
                            device="cpu"),
    })
    measured, _ = measure_all(tmp_path / "hand", settings, only=("handeye",))
    he = measured["handeye"]
    assert he.status == "complete" and he.summary["n_usable"] == 8 and he.summary["robot_s_per_pose"] == 2.5
    assert [p["n"] for p in he.points] == [3, 3, 5, 5, 8]
    full = he.points[-1]["methods"]["refined"]
    assert full["mm"] < 1.0 and full["deg"] < 0.1  # exact poses, noise-free board: close to the truth

    _plane_scene(tmp_path / "plane" / "scene")
    result = build_report(tmp_path / "plane", settings, only=("latency", "views", "training"))
    assert result.statuses["latency"] == "complete" and result.statuses["views"] == "complete"
    assert result.statuses["training"] == "missing"  # no metrics.json: the section says so
    store = measurement_store(tmp_path / "plane")
    lat, views = store.load("latency"), store.load("views")
    assert lat is not None and views is not None
    assert len(lat.points) == 4 and all(p["median_ms"] > 0 for p in lat.points)
    assert {p["gaussians"] for p in lat.points} == {200, 400}
    assert {p["antialiasing"] for p in lat.points} == {"mip"}  # timed as served: with its 3D filter
    assert [p["views_per_level"] for p in views.points] == [[2, 2], [4, 4]]
    assert all(math.isfinite(p["psnr"]) and p["steps"] == 4 for p in views.points)
    assert views.summary["levels"]["0"]["capture_s_per_view"] == 1.0  # time stamps 0, 1, 2, ...
    md = result.markdown.read_text()
    assert "report run (all views, 4 steps, 32x24 images)" in md and "## 4. Capture" in md
    for name in ("training.png", "latency.png", "views.png"):
        _valid_png(tmp_path / "plane" / "report" / name)

    # measured again, a measurement file would be replaced (atomic write: a new file, a new time stamp)
    def identities(workdir: Path) -> dict[str, tuple[int, int]]:
        folder = workdir / "report" / "measurements"
        return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in folder.glob("*.json")}

    before = identities(tmp_path / "plane"), identities(tmp_path / "hand")
    again, _ = measure_all(tmp_path / "plane", settings, only=("latency", "views"))
    assert again["latency"].points == lat.points and again["views"].points == views.points
    assert measure_all(tmp_path / "hand", settings, only=("handeye",))[0]["handeye"].points == he.points
    assert (identities(tmp_path / "plane"), identities(tmp_path / "hand")) == before


def test_synthesis_section_prices_the_resume_check() -> None:
    """``--resume-check``'s levels beside a render: a table and the advice (from a fabricated point)."""
    from brave6d.evaluation.report.sections.synthesis import advice_resume_check, resume_check_text

    points = [{"id": "640x480-w1", "width": 640, "height": 480, "workers": 1, "images": 8, "images_per_s": 2.0,
               "resume_check_ms": {"header": 0.5, "crc": 1.5, "decode": 25.0}}]
    table = resume_check_text(points)
    assert "rendering one took 500 ms" in table
    assert re.search(r"\| crc +\| 1\.50 +\| 0\.30 +\| also any changed byte +\|", table)  # 1.5 / 500 ms
    assert re.search(r"\| decode +\| 25\.00 +\| 5\.00 +\|", table)
    advice = advice_resume_check(points)
    assert "the default `crc` costs 1.50 ms per image found on resume (0.30 % of rendering one)" in advice
    assert "`decode` (25.0 ms) adds only forged files" in advice
    unpriced = [{k: v for k, v in points[0].items() if k != "resume_check_ms"}]
    assert resume_check_text(unpriced) == "" and advice_resume_check(unpriced) == ""
    assert advice_resume_check([{**points[0], "images_per_s": None}]) == ""  # no render time: no advice


def test_synthesis_advice_keeps_one_worker_when_more_do_not_pay() -> None:
    rates = {(320, 240): {1: 4.0, 2: 4.2}, (640, 480): {1: 1.0, 2: 1.1}}
    advice = advice_synthesis(rates, {"usable_cores": 2}, images=8)
    assert ("2 workers are only 1.05-1.10x as fast on this machine (2 cores, 8-image runs, start-up included): "
            "keep --workers 1 for runs this short") in advice
    assert "10,000 images at 640x480 take about 2.5 h here (2 workers)" in advice  # 10000 / 1.1 / 3600
    assert advice_synthesis({(320, 240): {1: math.nan}}, {}, images=8) == ""


@pytest.mark.slow
def test_synthesis_section_measures_the_scenes_objects_outside_the_scene(tmp_path: Path,
                                                                         demo_spec_path: Path) -> None:
    from brave6d.core.layout import init_scene_dir

    scene = init_scene_dir(tmp_path / "scene", demo_spec_path)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    store = measurement_store(tmp_path)
    sweep = SynthSweep(sizes=((48, 36), (96, 72)), workers=(1,), images=2)
    m = measure_synthesis(MeasureInputs(tmp_path, scene, store), sweep)
    assert m.status == "complete" and [p["id"] for p in m.points] == ["48x36-w1", "96x72-w1"]
    assert all(p["images"] == 2 and p["images_per_s"] > 0 for p in m.points)
    assert m.summary["objects"] and m.settings["objects"] == len(m.summary["objects"])
    checks = m.points[1]["resume_check_ms"]  # the largest size's one-worker run prices --resume-check
    assert set(checks) == {"header", "crc", "decode"} and all(v > 0 for v in checks.values())
    assert "resume_check_ms" not in m.points[0]
    after = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if "report" not in p.parts)
    assert after == before  # the images went to a temporary folder, not into the scene
    again = measure_synthesis(MeasureInputs(tmp_path, scene, store), sweep)  # cached: not measured again
    assert again.points == m.points
    section = render_synthesis(again, tmp_path / "report")
    assert _valid_png(tmp_path / "report" / "synthesis.png")[0] > 400 and "**Synthetic split:**" in section.advice


def _schedule_run(name: str, steps: int, psnrs: list[float], seconds_per_step: float, gaussians: int,
                  time_to_other_final: float | None) -> dict:
    every = steps // (len(psnrs) - 1)
    points = [{"step": i * every, "time_s": i * every * seconds_per_step, "cpu_s": 0.0, "psnr": p, "ssim": 0.9,
               "gaussians": gaussians} for i, p in enumerate(psnrs)]
    return {"name": name, "preset": {"name": "fast"}, "steps": steps, "final_psnr": psnrs[-1], "final_ssim": 0.95,
            "gaussians": gaussians, "gaussians_per_pixel": gaussians / 64000, "train_s": steps * seconds_per_step,
            "time_to_other_final": time_to_other_final, "points": points}


def test_training_section_plots_two_schedules_and_advises_from_them(tmp_path: Path) -> None:
    from brave6d.core.layout import SceneDir

    scene = SceneDir(tmp_path / "scene")
    atomic_write_json(scene.splat_dir / "metrics.json", {
        "preset": "fast", "device": "cpu", "steps": 100, "train_time_s": 10.0, "num_gaussians": 800,
        "holdout": {"psnr": 22.0, "ssim": 0.8}, "curve": []})
    old = _schedule_run("old", 3000, [14.0, 28.0, 30.0, 31.0, 31.9], 0.1, 113000, 300.0)
    new = _schedule_run("new", 1000, [14.0, 29.0, 31.0, 31.95, 32.1], 0.08, 40000, 60.0)
    atomic_write_json(scene.splat_dir / "time_to_quality.json", {"device": "cpu", "a": old, "b": new,
                                                                 "ratio_time_to_a_final": 5.0})
    m = collect_training(scene, MeasurementStore(tmp_path / "m"))
    assert sum(p["source"] == "schedule" for p in m.points) == 10
    section = render_training(m, None, tmp_path / "out")
    assert [f.name for f in section.figures] == ["training.png", "training_schedules.png"]
    _valid_png(tmp_path / "out" / "training_schedules.png")
    assert re.search(r"\| new +\| `fast` +\| 1000 +\| 80\.0 +\| 32\.10 ", section.body)
    assert ("new (`fast`) reached old (`fast`)'s final 31.90 dB after 60 s against 300 s (5.00x faster) and ended "
            "at 32.10 dB with 40000 Gaussians (against 113000): choose new (`fast`)") in section.advice
    # A reached its final PSNR before its last step: the advice compares the times behind the ratio
    old["time_to_own_final"] = 240.0
    atomic_write_json(scene.splat_dir / "time_to_quality.json", {"device": "cpu", "a": old, "b": new,
                                                                 "ratio_time_to_a_final": 4.0})
    section = render_training(collect_training(scene, MeasurementStore(tmp_path / "m1")), None, tmp_path / "out")
    assert "after 60 s against 240 s (4.00x faster)" in section.advice
    # A trained with the code of another revision (--a-source): the table and the advice say which
    old["source"] = {"rev": "a83a1a6", "commit": "a83a1a60fad2d0995566092e083d8fc920caee9a"}
    atomic_write_json(scene.splat_dir / "time_to_quality.json", {"device": "cpu", "a": old, "b": new,
                                                                 "ratio_time_to_a_final": 4.0})
    section = render_training(collect_training(scene, MeasurementStore(tmp_path / "m4")), None, tmp_path / "out")
    assert re.search(r"\| old +\| `fast` at a83a1a6 +\| 3000 ", section.body)
    assert "reached old (`fast` at a83a1a6)'s final 31.90 dB after 60 s" in section.advice
    del old["source"]
    # a schedule that never gets there: the advice names the quality it gives up
    new["time_to_other_final"], new["final_psnr"] = None, 31.5
    atomic_write_json(scene.splat_dir / "time_to_quality.json", {"device": "cpu", "a": old, "b": new,
                                                                 "ratio_time_to_a_final": None})
    section = render_training(collect_training(scene, MeasurementStore(tmp_path / "m2")), None, tmp_path / "out")
    assert "new (`fast`) ended at 31.50 dB and never reached old (`fast`)'s 31.90 dB (240 s)" in section.advice
    assert "0.40 dB less will do" in section.advice
    # an unreadable comparison is named, not fatal
    (scene.splat_dir / "time_to_quality.json").write_text('{"a": 1}')
    section = render_training(collect_training(scene, MeasurementStore(tmp_path / "m3")), None, tmp_path / "out")
    assert "time_to_quality.json could not be read" in section.body


@settings(max_examples=100, deadline=None)
@given(n=st.integers(0, 200), k=st.integers(-3, 250))
def test_evenly_spaced_picks_k_distinct_items_across_the_whole_list(n: int, k: int) -> None:
    items = list(range(n))
    chosen = evenly_spaced(items, k)
    assert chosen == sorted(set(chosen)) and set(chosen) <= set(items)
    assert len(chosen) == (n if k >= n else max(k, 0))
    if 0 < k < n:  # one from each of k equal stretches
        assert all(math.floor(i * n / k) <= c < math.floor((i + 1) * n / k) + 1 for i, c in enumerate(chosen))

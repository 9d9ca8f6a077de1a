"""Report section 9: fidelity where agents look: the splat against the truth from 10 to 50 cm.

The measurement is :mod:`brave6d.evaluation.report.fidelity` (what ``benchmarks/fidelity.py`` runs, for
two trainings side by side) on the scene's bundle: for a simulated scene the splat against the
simulator's truth without camera effects at seeded viewpoints per object, for a captured scene
against the held-out frames and their sensor depth; per distance the image and target-box
PSNR/SSIM, the depth error on the target's pixels and the static estimator's AR on both sides.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

from brave6d.core.progress import format_table
from brave6d.evaluation.report.common import RenderedSection, fmt, nan_note, provenance, settings_line, unavailable
from brave6d.evaluation.report.fidelity import (DISTANCES_M, FidelityProbe, FidelitySweep, fidelity_rows,
                                                fidelity_table, plot_fidelity)
from brave6d.evaluation.report.measurements import Measurement, describe_machine, file_stamp, machine_info, run_sweep
from brave6d.evaluation.report.protocol import MeasureInputs

NAME = "fidelity"
PAGE = 9
TITLE = f"{PAGE}. Fidelity where agents look: the splat against the truth from 10 to 50 cm"
FIGURE = "fidelity.png"
#: The issue's acceptance: depth on the target within 5 mm for this share of its pixels.
GOOD_WITHIN_5MM = 0.9
#: What closing the sampling gap costs (training at full resolution or from nearer rings): the lead's measured figure.
CLOSE_RANGE_COST = ("about 1.5x the training time on the demo (`fast` at the capture's 640x400 instead of 320x200: "
                    "385 s vs 264 s interleaved, box PSNR 29.4-31.8 dB instead of 26.8-31.6 at 10-50 cm; "
                    "docs/BENCHMARKS.md)")
#: What each fidelity lever cost and bought on the demo (interleaved runs; commands in docs/BENCHMARKS.md).
LEVER_PRICES = ("Levers measured on the demo (docs/BENCHMARKS.md, interleaved runs): the captured depth in training "
                "(`depth_lambda`) +11 % training time, target pixels within 5 mm 0.64 -> 0.93 at the worst "
                "distance; the median depth when serving (`render.depth_mode`) computed in the same pass, within "
                "15 mm 0.85-0.93 -> 0.99-1.00 on the same splat; Mip-Splatting's filters (`antialiasing: mip`) "
                "+8 % training time, +1.0-1.7 dB image PSNR at 10-50 cm; full capture resolution "
                "(`downscale` 1) 1.5x training time, target-box PSNR 26.8 -> 29.4 dB at 10 cm.")
#: What the ceiling rows mean (the section's text).
CEILING_NOTE = ("The ceiling rows: r is the training images' pixel footprint on the target (nearest capture ring / "
                "training focal length) over this view's (distance / bundle focal length), and the ceiling the box "
                "PSNR of the truth area-averaged to 1/r of its size and back against the truth itself (n/a where "
                "r <= 1): an estimate of what the training images could hold (many slightly shifted views can "
                "recover a little more), so close-range colour needs "
                f"training at full resolution or nearer rings, which costs {CLOSE_RANGE_COST}.")


def measure_fidelity(inputs: MeasureInputs, sweep: FidelitySweep) -> Measurement:
    """Run (or resume) the fidelity sweep on the scene's bundle; see the module docstring."""
    scene, store = inputs.scene, inputs.store
    from brave6d.serve import MANIFEST

    manifest = scene.bundle_dir / MANIFEST
    if (absent := store.require(NAME, [(manifest, "serve export (brave6d export)"),
                                       (scene.spec_path, "scene set-up (brave6d init)")])) is not None:
        return absent
    if scene.load_spec().simulation is None:  # a captured scene: compared with its held-out frames
        from brave6d.annotation import BopLayout

        if (absent := store.require(NAME, [(BopLayout(scene.bop_dir).info_path, "annotation (BOP export)"),
                                           (scene.frames_path, "capture")])) is not None:
            return absent
    from brave6d.serve import load_bundle
    from brave6d.training import resolve_device

    device = str(resolve_device(sweep.device))
    sweep = FidelitySweep(**{**asdict(sweep), "device": device})
    probe = FidelityProbe(scene, load_bundle(scene.bundle_dir), sweep)
    key = {"bundle": file_stamp(manifest), "spec": file_stamp(scene.spec_path), "sweep": asdict(sweep),
           "views": [i for i, _ in probe.items()]}
    if not probe.simulated:
        from brave6d.annotation import BopLayout

        key.update(scene_gt=file_stamp(BopLayout(probe.scene.bop_dir).info_path))
    if (done := store.complete(NAME, key)) is not None:
        return done
    m = store.resume(NAME, key, probe.settings(), machine_info(device))
    m.summary.update({"bundle": str(scene.bundle_dir), "mode": probe.mode})
    return run_sweep(store, m, probe.items(), probe.measure, desc="report: fidelity", unit="view")


def render_fidelity(m: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 9 from its measurement: the table (metrics x distances), the figure and advice."""
    if m is None or not m.usable or not m.points:
        return unavailable(TITLE, m, "Fidelity study")
    rows = fidelity_rows(m.points)
    png, dropped = plot_fidelity(out_dir / FIGURE, [("bundle", rows)], "Splat against truth where agents look",
                                 describe_machine(m.machine), settings_line(m))
    headers, lines = fidelity_table(rows)
    simulated = m.summary.get("mode") == "simulated"
    against = ("the simulator's truth at the same poses without camera effects (exact depth, the object-id "
               "buffer as the target's pixels), from seeded viewpoints per object looking at its centre"
               if simulated else "the held-out captured frames of each ring and their sensor depth (0 = no "
               "data, left out), the BOP export's visible masks as the targets' pixels")
    body = (f"The served splat of `{m.summary.get('bundle')}` against {against}. Medians per distance; depth "
            "shares are of the target's pixels with truth depth (a pixel the splat gives no depth is not within); "
            "AR: the static estimator on each side's depth, both scored against the ground truth with the "
            "truth's depth as VSD's test depth, mean over targets at least 10 % visible in the truth. "
            "`benchmarks/fidelity.py` runs the same for two trainings side by side. " + CEILING_NOTE + " "
            + LEVER_PRICES + "\n\n"
            f"![fidelity against distance]({png.name})\n\n" + format_table(headers, lines)
            + "\n\n" + provenance(m) + "\n" + nan_note(dropped, "plotted fidelity values"))
    return RenderedSection(TITLE, body, advice_fidelity(rows), [png])


def advice_fidelity(rows: list[dict[str, Any]]) -> str:
    """Where depth on the targets is furthest from the acceptance, and the largest AR gap."""
    good = [r for r in rows if math.isfinite(r["within_5mm"])]
    if not good:
        return ""
    worst = min(good, key=lambda r: r["within_5mm"])
    text = (f"**Fidelity:** depth on the target is within 5 mm for {fmt(worst['within_5mm'] * 100, 0)} % of its "
            f"pixels at {fmt(worst['distance_m'] * 100, 1)} cm (the worst distance; median error "
            f"{fmt(worst['depth_median_mm'], 1)} mm)")
    text += (f", so every distance reaches the acceptance's {GOOD_WITHIN_5MM:.0%}" if worst["within_5mm"] >= GOOD_WITHIN_5MM
             else f", below the {GOOD_WITHIN_5MM:.0%} the acceptance asks at every distance")
    capped = [r for r in rows if math.isfinite(r.get("box_psnr_ceiling", math.nan)) and math.isfinite(r["box_psnr"])]
    if capped:
        c = min(capped, key=lambda r: r["box_psnr_ceiling"])
        text += (f". At {fmt(c['distance_m'] * 100, 1)} cm the training images sampled the target {fmt(c['sampling_ratio'], 1)}x "
                 f"coarser than the view: the box PSNR is {fmt(c['box_psnr'], 1)} dB under a ceiling of "
                 f"{fmt(c['box_psnr_ceiling'], 1)} dB")
    gaps = [r for r in rows if math.isfinite(r["ar_gap"])]
    if gaps:
        g = max(gaps, key=lambda r: abs(r["ar_gap"]))
        text += (f". The estimator's AR differs most at {fmt(g['distance_m'] * 100, 1)} cm: "
                 f"{fmt(g['ar_truth'], 2)} on the truth, {fmt(g['ar_splat'], 2)} on the splat (gap "
                 f"{fmt(g['ar_gap'], 2)} ± {fmt(g.get('ar_gap_se'), 2)}, one standard error over {g['scored']} targets)")
    return text + "."


class FidelitySection:
    """Section 9 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> FidelitySweep:
        """Full: the 7 distances x 1 view per object at the bundle's size (3 held-out frames per ring
        of a captured scene); quick: 3 distances x 1 view at a quarter of the size (1 frame per ring)."""
        if quick:
            return FidelitySweep(distances_m=(0.1, 0.2, 0.5), views=1, holdout_per_level=1, scale=0.25)
        return FidelitySweep(distances_m=DISTANCES_M, views=1)

    def measure(self, inputs: MeasureInputs, settings: FidelitySweep) -> Measurement:
        return measure_fidelity(inputs, settings)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_fidelity(measurements.get(NAME), out_dir)


SECTION = FidelitySection()

"""Report section 7: how real are the splats? The static estimator on captured frames and on the
splat's renders of exactly those camera poses.

The captured views are the annotation stage's BOP export of the scene (undistorted RGB and depth,
``scene_camera`` poses and ``scene_gt`` / ``scene_gt_info`` ground truth, read through
:mod:`annotation`'s readers): per distance level the held-out views (never trained on) and a few
training views, evenly spaced in capture order. Each is rendered from the splat of the scene's
bundle by the server's renderer (:class:`brave6d.serve.SplatRenderer`) with the same ``K`` and pose, its
depth stored as the capture's is (uint16 mm), so that both sides reach the estimator in one form.
In every view each object at least 10 % visible is estimated by the static estimator
(:mod:`brave6d.evaluation.report.single_view`, told where in the image the object is) on both images and
scored against the export's ground truth with VSD/MSSD/MSPD. Both sides are scored on the same
test depth, the captured frame's (BOP's test depth of a captured image; the visible fractions are
the export's), so the gap measures only what the estimator is given, never a change of the
surface it is scored on. The gap is AR(real) - AR(splat);
PSNR and SSIM compare the render with the captured image on the pixels the raw image covers (as
the training stage scores its holdout).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.progress import format_table
from brave6d.evaluation.report.common import RenderedSection, fmt, mean, median, nan_note, num, paired_standard_error, provenance
from brave6d.evaluation.report.common import settings_line, unavailable
from brave6d.evaluation.report.measurements import Measurement, describe_machine, machine_info, run_sweep
from brave6d.evaluation.report.plots import legend, new_figure, plot_line, save_figure
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.real_vs_splat import choose_views as choose_level_views
from brave6d.evaluation.report.real_vs_splat import open_views
from brave6d.evaluation.report.single_view import MIN_VISIB_FRACT, StaticEstimator, ViewScorer, bbox_diagonal
from brave6d.evaluation.report.single_view import model_centre_m, project

NAME = "realism"
PAGE = 7
TITLE = f"{PAGE}. How real are the splats: the estimator on captured frames and on the splat's renders"
FIGURE = "realism.png"
#: An AR gap (real - splat) at least this large is named in the section and the advice.
LARGE_GAP = 0.1


@dataclass(frozen=True)
class RealismSweep:
    """Views per distance level (held-out first, then training views), an integer image stride
    (1: the captured size; ``s``: every ``s``-th pixel of the captured frame and of the render,
    which is made at the captured size), the render device and the estimator's colour weight
    (None: the agents' default; 0: depth alone; ``benchmarks/flip_colour.py`` compares weights)."""

    holdout_per_level: int = 3  # with train_per_level: 16 views on the demo's 4 rings (about 1 minute)
    train_per_level: int = 1
    stride: int = 1
    device: str = "auto"
    color_weight: float | None = None


def choose_views(levels: Mapping[int, int], holdout: set[int], exported: set[int], sweep: RealismSweep
                 ) -> list[tuple[int, bool]]:
    """``(im_id, held_out)`` per distance level as the sweep asks (:func:`real_vs_splat.choose_views`)."""
    return choose_level_views(levels, holdout, exported, sweep.holdout_per_level, sweep.train_per_level)


def measure_realism(inputs: MeasureInputs, sweep: RealismSweep) -> Measurement:
    """Run (or resume) the real-vs-splat sweep; see the module docstring."""
    scene, store = inputs.scene, inputs.store
    if sweep.stride < 1:
        raise ValueError(f"realism: stride must be a positive integer, got {sweep.stride}")
    from brave6d.training import resolve_device

    device = str(resolve_device(sweep.device))
    views = open_views(store, NAME, scene, sweep.holdout_per_level, sweep.train_per_level, sweep.stride, device)
    if isinstance(views, Measurement):
        return views
    from brave6d.annotation import read_models_info
    from brave6d.evaluation.metrics import load_models
    from brave6d.evaluation.report.image_quality import psnr, ssim

    layout, gts, infos = views.layout, views.gts, views.infos
    key = {**views.key(), "sweep": asdict(sweep), "test_depth": "captured", "estimator": StaticEstimator.SIGNALS}
    if (done := store.complete(NAME, key)) is not None:
        return done
    w, h = views.image_size
    settings = {"views": len(views.views), "holdout_per_level": sweep.holdout_per_level,
                "train_per_level": sweep.train_per_level, "image": f"{w}x{h}", "device": device}
    m = store.resume(NAME, key, settings, machine_info(device))
    views.describe(m)
    state: dict[str, Any] = {}

    def prepared() -> dict[str, Any]:  # models and estimator only when a point is missing
        if not state:
            info = read_models_info(layout.models_info_path)
            ids = sorted({g.obj_id for i, _ in views.views for g in gts[i]})
            models = load_models(layout.models_dir, ids, info)
            state.update(scorer=ViewScorer(models), centres={k: model_centre_m(v.points) for k, v in models.items()},
                         estimator=StaticEstimator({k: (layout.model_path(k), float(info[k]["diameter"])) for k in ids},
                                                   sweep.color_weight))
        return state

    def estimate_all(s: dict[str, Any], im_id: int, depth_m: NDArray[np.float32], rgb: NDArray[np.uint8],
                     K: NDArray[np.float64], world_T_cam: NDArray[np.float64],
                     test_depth: NDArray[np.float32]) -> list[dict[str, Any]]:
        out = []
        for gt_id, (g, gi) in enumerate(zip(gts[im_id], infos[im_id])):
            if gi.visib_fract < MIN_VISIB_FRACT:
                continue
            cam_T_obj = g.cam_T_model()
            centre = cam_T_obj[:3, :3] @ s["centres"][g.obj_id] + cam_T_obj[:3, 3]
            est = s["estimator"].estimate(depth_m, K, world_T_cam, g.obj_id, project(centre, K), rgb)
            score = s["scorer"].score(est, g.obj_id, cam_T_obj, K, (depth_m.shape[1], depth_m.shape[0]), test_depth,
                                      gi.visib_fract)
            out.append({"gt_id": gt_id, "obj_id": g.obj_id, "visib_fract": gi.visib_fract,
                        "found": est.cam_T_obj is not None, "estimate_s": est.seconds, **score.to_json()})
        return out

    def measure(item: tuple[int, bool]) -> dict[str, Any]:
        point, pair = views.measured_pair(*item)
        if pair is None or pair.depth_real is None:
            return point
        s, im_id = prepared(), item[0]
        K, world_T_cam, step = pair.K, pair.world_T_cam, sweep.stride
        real = estimate_all(s, im_id, pair.depth_real, pair.rgb_real, K, world_T_cam, pair.depth_real)
        splat = {o["gt_id"]: o for o in estimate_all(s, im_id, pair.depth_splat, pair.rgb_splat, K, world_T_cam,
                                                      pair.depth_real)}
        info = infos[im_id]
        objects = []
        for r in real:
            sp = splat[r["gt_id"]]
            objects.append({"obj_id": r["obj_id"], "object": views.names.get(r["obj_id"], str(r["obj_id"])),
                            "visib_fract": r["visib_fract"],
                            "bbox_diag_px": (bbox_diagonal(info[r["gt_id"]].bbox_obj) or math.nan) / step,
                            **{f"real_{k}": v for k, v in r.items() if k not in ("gt_id", "obj_id", "visib_fract")},
                            **{f"splat_{k}": v for k, v in sp.items() if k not in ("gt_id", "obj_id", "visib_fract")}})
        valid = views.valid_pixels()
        return {**point, "psnr": psnr(pair.rgb_splat, pair.rgb_real, valid),
                "ssim": ssim(pair.rgb_splat, pair.rgb_real, valid), "render_s": pair.render_s, "objects": objects}

    items = [(f"im{i}", (i, held)) for i, held in views.views]
    return run_sweep(store, m, items, measure, desc="report: real vs splat", unit="view")


# ----------------------------------------------------------------------------- aggregation
def targets(points: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every (view, object) target with its view's level, distance and held-out flag."""
    return [{**o, "level": p.get("level"), "distance_m": p.get("distance_m"), "holdout": p.get("holdout")}
            for p in points for o in p.get("objects", [])]


def mean_of(rows: Sequence[dict[str, Any]], key: str) -> float:
    """Mean of the finite ``key`` values of ``rows``."""
    return mean([r.get(key) for r in rows])


def unresolved(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Levels whose gap lies within two standard errors of ``LARGE_GAP`` (their targets cannot tell
    which side of the limit the gap is on)."""
    out = []
    for r in rows:
        gap, se = abs(num(r.get("gap"))), num(r.get("gap_se"))
        if math.isfinite(gap) and math.isfinite(se) and abs(gap - LARGE_GAP) < 2.0 * se:
            out.append(r)
    return out


def resolution_note(rows: Sequence[dict[str, Any]]) -> str:
    """One sentence naming the levels :func:`unresolved` returns ('' when every level is resolved)."""
    open_rows = unresolved(rows)
    if not open_rows:
        return ""
    levels = ", ".join(f"{fmt(num(r.get('distance_m')) * 100, 0)} cm" for r in open_rows)
    def span(values: list[float], digits: int) -> str:
        low, high = fmt(min(values), digits), fmt(max(values), digits)
        return low if low == high else f"{low}-{high}"

    counts = [float(r.get("targets", 0)) for r in open_rows]
    spans = [2.0 * num(r.get("gap_se")) for r in open_rows]
    return (f"the sweep's {span(counts, 0)} targets per level resolve a gap only to ±{span(spans, 3)} (two standard errors), "
            f"so they cannot tell which side of {fmt(LARGE_GAP, 2)} the gap is on at {levels} "
            "(`benchmarks/realism.py` with more views per level can)")


def gap_rows(points: Sequence[dict[str, Any]], obj_id: int | None = None) -> list[dict[str, Any]]:
    """Per distance level: views, PSNR/SSIM, AR on real and splat images, the gap, times."""
    views: dict[int, list[dict[str, Any]]] = defaultdict(list)
    for p in points:
        views[int(p.get("level", -1))].append(p)
    rows = []
    for level, pts in sorted(views.items()):
        tg = [t for t in targets(pts) if obj_id is None or t.get("obj_id") == obj_id]
        row = {"level": level, "distance_m": num(pts[0].get("distance_m")), "views": len(pts),
               "holdout_views": sum(bool(p.get("holdout")) for p in pts), "targets": len(tg),
               "psnr": mean_of(pts, "psnr"), "ssim": mean_of(pts, "ssim"),
               "psnr_holdout": mean_of([p for p in pts if p.get("holdout")], "psnr"),
               "ar_real": mean_of(tg, "real_ar"), "ar_splat": mean_of(tg, "splat_ar"),
               "found_real": sum(bool(t.get("real_found")) for t in tg),
               "found_splat": sum(bool(t.get("splat_found")) for t in tg),
               "estimate_s": median([t.get("real_estimate_s") for t in tg] + [t.get("splat_estimate_s") for t in tg]),
               "render_s": median([p.get("render_s") for p in pts])}
        for k in ("ar_vsd", "ar_mssd", "ar_mspd"):
            row[f"{k}_real"], row[f"{k}_splat"] = mean_of(tg, f"real_{k}"), mean_of(tg, f"splat_{k}")
        row["gap"] = row["ar_real"] - row["ar_splat"]
        row["gap_se"] = paired_standard_error([num(t.get("real_ar")) - num(t.get("splat_ar")) for t in tg])
        rows.append(row)
    return rows


def large_gaps(points: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """(level, object) cells whose |AR gap| is at least ``LARGE_GAP``, largest first."""
    cells = []
    for oid in sorted({int(t["obj_id"]) for t in targets(points)}):
        name = next((str(t.get("object")) for t in targets(points) if t["obj_id"] == oid), str(oid))
        for r in gap_rows(points, oid):
            if r["targets"] and math.isfinite(r["gap"]) and abs(r["gap"]) >= LARGE_GAP:
                cells.append({**r, "obj_id": oid, "object": name})
    return sorted(cells, key=lambda c: -abs(c["gap"]))


# ----------------------------------------------------------------------------- rendering
def render_realism(m: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 7 from its measurement: AR real/splat and the gap next to PSNR/SSIM per level."""
    if m is None or not m.usable or not m.points:
        return unavailable(TITLE, m, "Real-vs-splat comparison")
    rows = gap_rows(m.points)
    objects = sorted({(int(t["obj_id"]), str(t.get("object"))) for t in targets(m.points)})
    fig, (ax_ar, ax_gap) = new_figure(2, panel=(5.2, 3.8))
    cm = [r["distance_m"] * 100.0 for r in rows]
    dropped = plot_line(ax_ar, cm, [r["ar_real"] for r in rows], "AR on captured frames", fmt="ko-", lw=2)
    dropped += plot_line(ax_ar, cm, [r["ar_splat"] for r in rows], "AR on splat renders", fmt="s--", color="tab:red")
    ax_q = ax_ar.twinx()
    dropped += plot_line(ax_q, cm, [r["psnr"] for r in rows], None, fmt=":", color="tab:blue")
    ax_q.set_ylabel("splat PSNR [dB] (dotted)", color="tab:blue")
    dropped += plot_line(ax_gap, cm, [r["gap"] for r in rows], "all objects", fmt="ko-", lw=2)
    for i, (oid, name) in enumerate(objects):
        dropped += plot_line(ax_gap, cm_of(gap_rows(m.points, oid)), [r["gap"] for r in gap_rows(m.points, oid)],
                             f"{name} (obj {oid})", fmt="o--", color=f"C{i}", alpha=0.8)
    ax_gap.axhline(0.0, color="0.3", lw=0.8)
    for ax in (ax_ar, ax_gap):
        ax.set_xlabel("capture distance level [cm]")
    ax_ar.set_ylabel("BOP Average Recall")
    ax_ar.set_ylim(-0.03, 1.03)
    ax_gap.set_ylabel("AR gap: real - splat")
    legend(ax_ar)
    legend(ax_gap)
    png = save_figure(fig, out_dir / FIGURE, "Static estimator on captured frames vs the splat's renders of the same poses",
                      describe_machine(m.machine), settings_line(m))
    table = [(fmt(r["distance_m"] * 100, 0), f"{r['views']} ({r['holdout_views']} held out)", r["targets"],
              fmt(r["psnr"], 2), fmt(r["ssim"], 3), fmt(r["ar_real"], 3), fmt(r["ar_splat"], 3), f"{fmt(r['gap'], 3)} ± {fmt(r['gap_se'], 3)}",
              f"{r['found_real']}/{r['found_splat']}", fmt(r["estimate_s"], 2), fmt(r["render_s"], 3)) for r in rows]
    obj_table = []
    for oid, name in objects:
        at = {r["level"]: r for r in gap_rows(m.points, oid)}
        obj_table.append((f"{name} ({oid})", *(fmt(at[r["level"]]["gap"], 2) if r["level"] in at and at[r["level"]]["targets"]
                                               else "-" for r in rows)))
    gaps = large_gaps(m.points)
    where = ("Large gaps (|gap| >= " + fmt(LARGE_GAP, 2) + "): " + "; ".join(
        f"{c['object']} at {fmt(c['distance_m'] * 100, 0)} cm ({fmt(c['ar_real'], 2)} real vs {fmt(c['ar_splat'], 2)} "
        f"splat over {c['targets']} targets)" for c in gaps[:6]) + "." if gaps
             else f"No distance level or object has a gap of {fmt(LARGE_GAP, 2)} AR or more.")
    body = ("The same static estimator, told where each object is in the image, runs on captured frames (the "
            f"annotation's BOP export, `{m.summary.get('bop')}`: undistorted RGB-D, poses and ground truth) and on the "
            "splat's renders of exactly those camera poses (the served bundle, depth stored as the capture's, in mm); "
            "both are scored against the export's ground truth. Gap = AR(real) - AR(splat): positive where the splat "
            "makes the estimator worse than the camera does. **What \"real\" means here:** in the demo the captured "
            "frames come from the simulated camera (the project's CPU renderer of the scene's meshes with its camera "
            "effects), so the gap measures how far the splat is from that simulator; on a real capture the same code "
            "measures the gap to real images. SE: the standard error of the mean of the per-target differences (one "
            "target moves a level's AR by about 1 / targets).\n\n"
            f"![AR real vs splat]({png.name})\n\n"
            + format_table(["cm", "views", "targets", "PSNR [dB]", "SSIM", "AR real", "AR splat", "gap ± SE",
                            "found real/splat", "estimator s/view", "render s/view"], table)
            + "\n\nAR gap per object and distance level (cm):\n\n"
            + format_table(["object", *(fmt(r["distance_m"] * 100, 0) for r in rows)], obj_table)
            + f"\n\n{where}\n\n" + provenance(m) + "\n" + nan_note(dropped, "plotted real-vs-splat values"))
    return RenderedSection(TITLE, body, advice_realism(rows, gaps), [png])


def cm_of(rows: Sequence[dict[str, Any]]) -> list[float]:
    return [num(r["distance_m"]) * 100.0 for r in rows]


def advice_realism(rows: list[dict[str, Any]], gaps: list[dict[str, Any]]) -> str:
    """Whether splat AR stands in for real AR, where it does not, and whether PSNR tells it."""
    ok = [r for r in rows if math.isfinite(r["gap"])]
    if not ok:
        return ""
    worst = max(ok, key=lambda r: abs(r["gap"]))
    text = (f"**Splat realism:** over all levels the estimator's AR differs between captured frames and splat renders "
            f"by at most {fmt(abs(worst['gap']), 3)} (at {fmt(worst['distance_m'] * 100, 0)} cm, PSNR "
            f"{fmt(worst['psnr'], 1)} dB)")
    note = resolution_note(ok)
    if abs(worst["gap"]) < LARGE_GAP:
        text += (f", under {fmt(LARGE_GAP, 2)} in this sweep; but " + note if note else
                 f", under {fmt(LARGE_GAP, 2)}: scores on the splat stand in for scores on the capture at every distance")
    else:
        text += (f"; trust splat scores least at {', '.join(sorted({fmt(c['distance_m'] * 100, 0) + ' cm' for c in gaps}))}"
                 + (f" (largest: {gaps[0]['object']})" if gaps else "") + ("; " + note if note else ""))
    psnrs = [r["psnr"] for r in ok if math.isfinite(r["psnr"])]
    if len(ok) > 2 and len(psnrs) == len(ok) and np.std(psnrs) > 0 and np.std([r["gap"] for r in ok]) > 0:
        corr = float(np.corrcoef(psnrs, [abs(r["gap"]) for r in ok])[0, 1])
        text += f"; across levels PSNR and |gap| correlate at {fmt(corr, 2)}" + (
            " (higher PSNR, smaller gap)" if corr <= -0.5 else
            ": higher PSNR came with a larger gap, so PSNR does not say where splat scores can be trusted"
            if corr >= 0.5 else ", so PSNR alone does not predict the gap")
    est = median([r["estimate_s"] for r in ok])
    return text + f". One estimate costs {fmt(est, 2)} s, one render {fmt(median([r['render_s'] for r in ok]), 3)} s."


class RealismSection:
    """Section 7 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> RealismSweep:
        """Full: up to 3 held-out and 1 training view per level at the captured size; quick: one
        held-out view per level at a quarter of the size."""
        if quick:
            return RealismSweep(holdout_per_level=1, train_per_level=0, stride=4)
        return RealismSweep()

    def measure(self, inputs: MeasureInputs, settings: RealismSweep) -> Measurement:
        return measure_realism(inputs, settings)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_realism(measurements.get(NAME), out_dir)


SECTION = RealismSection()

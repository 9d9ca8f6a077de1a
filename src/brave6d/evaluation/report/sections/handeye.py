"""Report section 2: hand-eye error against the number of calibration poses, and solve time.

The calibration's board frames (``calibration/board_capture``) are detected once; random
subsets of ``n`` poses are then solved with :func:`calibration.calibrate_handeye` (joint
refinement; the closed-form starts come with it). The conditioning check is relaxed and the
uncertainty limit off, so that few poses are *measured* rather than refused; each trial
records whether the default limits would have accepted its uncertainty. The error is against
the spec's ``simulation.true_tcp_T_camera`` for a simulated scene, else against the solution
from all poses (then the full set itself is not a point). Robot time per pose comes from
the board frames' time stamps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.core.layout import SceneDir
from brave6d.core.progress import format_table
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore, describe_machine, file_stamp, machine_info, run_sweep
from brave6d.evaluation.report.common import RenderedSection, fmt, median, nan_note, num, provenance, quantile, seconds_per_frame
from brave6d.evaluation.report.common import settings_line, unavailable
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.plots import legend, new_figure, plot_band, plot_line, save_figure

NAME = "handeye"
PAGE = 2
TITLE = f"{PAGE}. Hand-eye calibration: error against poses and solve time"
FIGURE = "handeye.png"
#: Closed-form method drawn beside the refinement (the cheapest answer the calibration computes).
CLOSED_FORM = "park"
#: The advice asks for a hand-eye error that moves image points by at most this many pixels.
HALF_PIXEL = 0.5


@dataclass(frozen=True)
class HandEyeSweep:
    """Subset sizes (the full set is always added), random subsets per size, seed."""

    sizes: tuple[int, ...] = (3, 4, 6, 8, 12, 16, 24)
    repeats: int = 8
    seed: int = 0


def measure_handeye(scene: SceneDir, store: MeasurementStore, sweep: HandEyeSweep) -> Measurement:
    """Run (or resume) the sweep on the scene's board capture; see the module docstring."""
    layout = scene.board_capture
    absent = store.require(NAME, [(layout.frames_path, "calibration"), (scene.intrinsics_path, "calibration")])
    if absent is not None:
        return absent
    from brave6d.core.calibration_io import read_intrinsics
    from brave6d.calibration import ConditioningThresholds, HandEyeOptions, board_corner_points, calibrate_handeye

    spec = scene.load_spec()
    truth = spec.simulation.true_tcp_T_camera.matrix() if spec.simulation is not None else None
    key = {"frames": file_stamp(layout.frames_path), "intrinsics": file_stamp(scene.intrinsics_path),
           "board": spec.board.model_dump(mode="json"), "truth": None if truth is None else truth.tolist(),
           "sweep": asdict(sweep)}
    settings = {"sizes": list(sweep.sizes), "repeats": sweep.repeats, "seed": sweep.seed,
                "solver": "refined (closed-form start)", "conditioning": "relaxed", "sigma limit": "off"}
    if (done := store.complete(NAME, key)) is not None:
        return done
    m = store.resume(NAME, key, settings, machine_info("cpu"))
    camera = read_intrinsics(scene)
    records = layout.frames()
    t0 = time.perf_counter()
    views = [_detect(layout.file(r.rgb), r.base_T_tcp_matrix, r.view_id, spec.board) for r in records]
    detect_s = time.perf_counter() - t0
    defaults = HandEyeOptions()
    usable = [v for v in views if len(v.corner_ids) >= defaults.min_corners]
    options = HandEyeOptions(conditioning=ConditioningThresholds.relaxed(), max_sigma_mm=None, max_sigma_deg=None)
    obj = board_corner_points(spec.board)
    n_all = len(usable)
    if n_all < 3:
        return store.failed(NAME, f"only {n_all} of {len(views)} board frames show the board (>= 3 needed)")
    reference, truth_kind = truth, "simulation truth (scene spec `simulation.true_tcp_T_camera`)"
    if truth is None:
        reference = calibrate_handeye(usable, obj, camera.K, camera.dist_array, options).tcp_T_cam
        truth_kind = f"the solution from all {n_all} poses (no ground truth: a real rig)"
    m.summary.update({"n_frames": len(views), "n_usable": n_all, "detect_s_per_frame": detect_s / max(len(views), 1),
                      "truth": truth_kind, "has_truth": truth is not None,
                      "robot_s_per_pose": seconds_per_frame(records), "focal_px": camera.fx,
                      "nearest_m": min(spec.capture.distances_m),
                      "default_sigma_limits": [defaults.max_sigma_mm, defaults.max_sigma_deg]})

    def solve(item: tuple[int, list[int]]) -> dict[str, Any]:
        n, idx = item
        t = time.perf_counter()
        try:
            result = calibrate_handeye([usable[i] for i in idx], obj, camera.K, camera.dist_array, options)
        except Exception as exc:  # noqa: BLE001 - a failed trial is a data point (degenerate subset)
            return {"n": n, "error": f"{type(exc).__name__}: {exc}", "solve_s": time.perf_counter() - t}
        solve_s = time.perf_counter() - t
        errors = result.errors_against(reference)
        times = {r.method: r.time_s for r in result.methods}
        unc = result.uncertainty
        accepted = unc is not None and (unc.translation_sigma_norm_mm <= (defaults.max_sigma_mm or math.inf)
                                        and unc.rotation_sigma_norm_deg <= (defaults.max_sigma_deg or math.inf))
        return {"n": n, "solve_s": solve_s, "accepted_by_default_limits": bool(accepted),
                "methods": {k: {"mm": mm, "deg": deg, "time_s": times.get(k)} for k, (mm, deg) in errors.items()}}

    sizes = sorted({n for n in sweep.sizes if 3 <= n < n_all} | ({n_all} if truth is not None else set()))
    items = []
    for n in sizes:
        for r in range(sweep.repeats if n < n_all else 1):
            rng = np.random.default_rng([sweep.seed, n, r])
            items.append((f"n{n}-r{r}", (n, sorted(rng.choice(n_all, n, replace=False).tolist()))))
    return run_sweep(store, m, items, solve, desc="report: hand-eye subsets", unit="solve")


def _detect(path: Path, base_T_tcp: np.ndarray, name: str, board: Any) -> Any:
    from brave6d.core.atomic import read_png
    from brave6d.calibration import HandEyeView, detect_charuco

    return HandEyeView.from_detection(base_T_tcp, detect_charuco(read_png(path, "rgb"), board), name)


# ----------------------------------------------------------------------------- rendering
def by_size(m: Measurement) -> list[dict[str, Any]]:
    """One row per subset size: trials, failures, error quartiles (refined and closed form), times."""
    rows = []
    for n in sorted({int(p["n"]) for p in m.points}):
        pts = [p for p in m.points if int(p["n"]) == n]
        ok = [p for p in pts if "methods" in p]
        ref = [p["methods"].get("refined", {}) for p in ok]
        cf = [p["methods"].get(CLOSED_FORM, {}) for p in ok]
        rows.append({
            "n": n, "trials": len(pts), "failed": len(pts) - len(ok),
            "accepted": sum(bool(p.get("accepted_by_default_limits")) for p in ok),
            "mm": [median([e.get("mm") for e in ref]), quantile([e.get("mm") for e in ref], 0.25),
                   quantile([e.get("mm") for e in ref], 0.75)],
            "deg": [median([e.get("deg") for e in ref]), quantile([e.get("deg") for e in ref], 0.25),
                    quantile([e.get("deg") for e in ref], 0.75)],
            "cf_mm": median([e.get("mm") for e in cf]), "cf_deg": median([e.get("deg") for e in cf]),
            "cf_s": median([e.get("time_s") for e in cf]),
            "solve_s": median([p.get("solve_s") for p in ok]),
        })
    return rows


def render_handeye(m: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 2 from its measurement: plot, table, advice (or a note saying what is missing)."""
    if m is None or not m.usable:
        return unavailable(TITLE, m, "Hand-eye sweep")
    rows = by_size(m)
    s = m.summary
    per_pose = num(s.get("robot_s_per_pose"))
    fig, (ax_mm, ax_deg, ax_t) = new_figure(3)
    ns = [r["n"] for r in rows]
    dropped = plot_line(ax_mm, ns, [r["mm"][0] for r in rows], "refined (median)")
    plot_band(ax_mm, ns, [r["mm"][1] for r in rows], [r["mm"][2] for r in rows])
    dropped += plot_line(ax_mm, ns, [r["cf_mm"] for r in rows], f"{CLOSED_FORM} closed form", fmt="s--")
    dropped += plot_line(ax_deg, ns, [r["deg"][0] for r in rows], "refined (median)")
    plot_band(ax_deg, ns, [r["deg"][1] for r in rows], [r["deg"][2] for r in rows])
    dropped += plot_line(ax_deg, ns, [r["cf_deg"] for r in rows], f"{CLOSED_FORM} closed form", fmt="s--")
    dropped += plot_line(ax_t, ns, [r["solve_s"] for r in rows], "full solve (median)")
    dropped += plot_line(ax_t, ns, [r["cf_s"] for r in rows], f"{CLOSED_FORM} alone", fmt="s--")
    for ax, limit in zip((ax_mm, ax_deg), pixel_budget(s)):
        if math.isfinite(limit):
            ax.axhline(limit, color="0.4", lw=0.8, ls=":", label="half a pixel at the nearest ring")
    for ax, label in ((ax_mm, "translation error [mm]"), (ax_deg, "rotation error [deg]"), (ax_t, "solve time [s]")):
        ax.set_xlabel("calibration poses")
        ax.set_ylabel(label)
        legend(ax)
    ax_t.set_yscale("log")
    png = save_figure(fig, out_dir / FIGURE, "Hand-eye error and solve time against the number of poses "
                      f"(error vs {'truth' if s.get('has_truth') else 'all-pose solution'}; band: inter-quartile)",
                      describe_machine(m.machine), settings_line(m) + f"; truth: {s.get('truth')}")
    table = [(r["n"], f"{r['trials'] - r['failed']}/{r['trials']}", r["accepted"], fmt(r["mm"][0], 3),
              f"{fmt(r['mm'][1], 3)}-{fmt(r['mm'][2], 3)}", fmt(r["deg"][0], 4), fmt(r["cf_mm"], 3),
              fmt(r["solve_s"], 3), fmt(r["n"] * per_pose, 0)) for r in rows]
    body = (f"Random subsets of the {s.get('n_usable')} usable board poses (of {s.get('n_frames')} frames) are "
            f"solved again; the error is against {s.get('truth')}. Each pose costs about {fmt(per_pose, 1)} s "
            f"of robot time (median gap between frames) and {fmt(num(s.get('detect_s_per_frame')) * 1000, 0)} ms "
            "of ChArUco detection. Half a pixel at the nearest ring corresponds to "
            f"{fmt(pixel_budget(s)[0], 3)} mm / {fmt(pixel_budget(s)[1], 4)} deg.\n\n"
            f"![hand-eye error against poses]({png.name})\n\n"
            + format_table(["poses", "solved", "within default sigma limits", "median mm", "IQR mm", "median deg",
                            f"{CLOSED_FORM} mm", "solve s", "robot s"], table)
            + "\n\n" + provenance(m) + "\n" + nan_note(dropped, "plotted hand-eye values"))
    return RenderedSection(TITLE, body, advice_handeye(rows, s), [png])


def pixel_budget(summary: dict[str, Any], px: float = HALF_PIXEL) -> tuple[float, float]:
    """Hand-eye error (mm, deg) that moves image points by ``px`` pixels at the nearest capture distance.

    A rotation error of d rad shifts the image by ``f * d`` px; a translation error of t m shifts a
    point at depth z by ``f * t / z`` px. NaN when the focal length or distance is unknown.
    """
    f, z = num(summary.get("focal_px")), num(summary.get("nearest_m"))
    if not (f > 0 and z > 0):
        return math.nan, math.nan
    return 1000.0 * px * z / f, math.degrees(px / f)


def advice_handeye(rows: list[dict[str, Any]], summary: dict[str, Any]) -> str:
    """The fewest poses whose error stays within half a pixel at the nearest capture distance in at
    least three of four random subsets (upper quartile within the budget, rotation and translation)."""
    solved = [r for r in rows if math.isfinite(num(r["mm"][0])) and math.isfinite(num(r["deg"][0]))]
    if not solved:
        return ""
    mm_max, deg_max = pixel_budget(summary)
    if not (math.isfinite(mm_max) and math.isfinite(deg_max)):
        return ""
    per_pose = num(summary.get("robot_s_per_pose"))
    versus = "the truth" if summary.get("has_truth") else "the all-pose solution"
    budget = (f"half a pixel at the nearest ring ({fmt(mm_max, 3)} mm / {fmt(deg_max, 4)} deg for "
              f"f = {fmt(summary.get('focal_px'), 0)} px at {fmt(summary.get('nearest_m'))} m)")
    largest = solved[-1]
    tail = f"; {largest['n']} poses: median {fmt(largest['mm'][0], 3)} mm / {fmt(largest['deg'][0], 4)} deg"
    enough = next((r for r in solved if not r["failed"] and num(r["mm"][2]) <= mm_max
                   and num(r["deg"][2]) <= deg_max), None)
    if enough is None:
        return (f"**Calibration poses:** no measured pose count keeps the error against {versus} within "
                f"{budget}{tail}: add poses with larger rotations about different axes, or check the detections.")
    robot = f", about {fmt(enough['n'] * per_pose, 0)} s of robot time" if math.isfinite(per_pose) else ""
    text = (f"**Calibration poses:** {enough['n']} poses keep the error against {versus} within {budget} in 3 of 4 "
            f"random draws (upper quartile {fmt(enough['mm'][2], 3)} mm / {fmt(enough['deg'][2], 4)} deg; median "
            f"{fmt(enough['mm'][0], 3)} mm / {fmt(enough['deg'][0], 4)} deg), solved in "
            f"{fmt(enough['solve_s'], 2)} s{robot}")
    if largest is enough:
        return text + "; fewer poses did not."
    extra = largest["n"] - enough["n"]
    cost = f"{fmt(extra * per_pose, 0)} s more robot time" if math.isfinite(per_pose) else f"{extra} more poses"
    return (text + f"{tail}, i.e. {fmt(enough['mm'][0] / largest['mm'][0], 1)}x less translation error for {cost}.")


class HandEyeSection:
    """Section 2 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> HandEyeSweep:
        """The demo's sweep; quick: four subset sizes, three draws each."""
        return HandEyeSweep(sizes=(3, 5, 8, 12), repeats=3) if quick else HandEyeSweep()

    def measure(self, inputs: MeasureInputs, settings: HandEyeSweep) -> Measurement:
        return measure_handeye(inputs.scene, inputs.store, settings)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_handeye(measurements.get(NAME), out_dir)


SECTION = HandEyeSection()

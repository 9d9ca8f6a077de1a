"""Report section 6: the distance study: the static estimator's BOP AR against the sensor's distance.

The served splat (the scene's bundle, rendered by :class:`brave6d.serve.SceneServer`, the server's own
renderer with its visible fractions) is viewed from seeded viewpoints on rings around every object:
at each distance, several azimuths and elevations drawn in the bundle's start ranges, the camera
looking at the object's model centre (as an episode's start view does), poses in collision
redrawn. In each view the static estimator (:mod:`brave6d.evaluation.report.single_view`: the baseline's
perception + registration, one view, no moves) estimates the object, and the estimate is scored
with BOP's VSD/MSSD/MSPD against the bundle's ground truth, as an episode is: the estimator sees
the splat's depth, VSD's test depth and the visible fractions come from the bundle's reference
geometry (the splat's depth for a bundle without one; each point records which). A view where the object is less than
10 % visible is no BOP19 target and is left out of the AR. The object's pixel size (visible mask
area, box diagonal) is recorded with each view; so are the render and estimator times.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.core.progress import format_table
from brave6d.evaluation.report.common import RenderedSection, fmt, median, nan_note, num, provenance, settings_line, unavailable
from brave6d.evaluation.report.measurements import Measurement, describe_machine, file_stamp, machine_info, run_sweep
from brave6d.evaluation.report.plots import legend, new_figure, plot_line, save_figure
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.single_view import MIN_VISIB_FRACT, StaticEstimator, ViewScorer, bbox_diagonal

NAME = "distance"
PAGE = 6
TITLE = f"{PAGE}. Distance study: static-estimator Average Recall against sensor distance"
FIGURE = "distance.png"
METRIC_KEYS = ("ar", "ar_vsd", "ar_mssd", "ar_mspd")
#: AR below this fraction of the best distance's counts as "falls off" in the advice.
FALL_OFF = 0.75


@dataclass(frozen=True)
class DistanceSweep:
    """Ring distances (m), viewpoints per object and distance, the image size as a fraction of the
    bundle's, the seed of the viewpoints and the render device."""

    distances_m: tuple[float, ...] = (0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50)
    views: int = 2  # per object and distance (the demo's report: 56 views, about 2 minutes on 2 cores)
    scale: float = 1.0
    seed: int = 0
    device: str = "auto"


def viewpoint(centre: np.ndarray, distance: float, start: Mapping[str, Any], rng: np.random.Generator,
              check: Any, tries: int = 200) -> tuple[np.ndarray, float, float] | None:
    """A free ``world_T_cam`` at ``distance`` from ``centre`` looking at it (azimuth and elevation
    drawn from the bundle's start ranges), with the angles in degrees; None when ``tries`` all collide."""
    from brave6d.core.transforms import look_at

    el_lo, el_hi = float(start.get("min_elevation_deg", 30.0)), float(start.get("max_elevation_deg", 80.0))
    az_lo, az_hi = (float(a) for a in start.get("azimuth_range_deg", (-180.0, 180.0)))
    for _ in range(tries):
        el, az = rng.uniform(el_lo, el_hi), rng.uniform(az_lo, az_hi)
        e, a = math.radians(el), math.radians(az)
        eye = centre + distance * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        T = look_at(eye, centre)
        if check(T) is None:
            return T, az, el
    return None


def measure_distance(inputs: MeasureInputs, sweep: DistanceSweep) -> Measurement:
    """Run (or resume) the distance sweep on the scene's bundle; see the module docstring."""
    scene, store = inputs.scene, inputs.store
    from brave6d.serve import MANIFEST

    manifest = scene.bundle_dir / MANIFEST
    if (absent := store.require(NAME, [(manifest, "serve export (brave6d export)")])) is not None:
        return absent
    from brave6d.evaluation.metrics import models_from_bundle
    from brave6d.serve import SceneServer, load_bundle
    from brave6d.training import resolve_device

    device = str(resolve_device(sweep.device))
    bundle = load_bundle(scene.bundle_dir)
    key = {"bundle": file_stamp(manifest), "sweep": asdict(sweep), "device": device,
           "test_depth": "reference" if bundle.reference_path is not None else "splat",
           "estimator": StaticEstimator.SIGNALS}
    if (done := store.complete(NAME, key)) is not None:
        return done
    camera = bundle.camera
    if sweep.scale != 1.0:
        camera = camera.scaled(max(16, round(camera.width * sweep.scale)), max(16, round(camera.height * sweep.scale)))
    settings = {"distances_m": list(sweep.distances_m), "views": sweep.views, "image": f"{camera.width}x{camera.height}",
                "seed": sweep.seed, "device": device, "objects": len(bundle.objects)}
    m = store.resume(NAME, key, settings, machine_info(device))
    m.summary.update({"bundle": str(scene.bundle_dir), "objects": {str(o.obj_id): o.name for o in bundle.objects}})
    state: dict[str, Any] = {}

    def prepared() -> dict[str, Any]:  # the server and the estimator only when a point is missing
        if not state:
            server = SceneServer(bundle, device)
            server.renderer.warm_up(camera, bundle.holdout[0].world_T_cam if bundle.holdout else np.eye(4))
            state.update(server=server, scorer=ViewScorer(models_from_bundle(bundle)),
                         estimator=StaticEstimator({o.obj_id: (bundle.model_path(o), o.diameter_mm)
                                                    for o in bundle.objects}))
        return state

    def measure(item: tuple[int, float, int]) -> dict[str, Any]:
        gt_id, distance, k = item
        obj = bundle.objects[gt_id]
        s = prepared()
        server = s["server"]
        rng = np.random.default_rng([sweep.seed, gt_id, round(distance * 1000), k])
        found_pose = viewpoint(server.centres_world[gt_id], distance, bundle.start, rng, bundle.world.check)
        point: dict[str, Any] = {"obj_id": obj.obj_id, "object": obj.name, "distance_m": distance}
        if found_pose is None:
            return {**point, "target": False, "note": "every drawn viewpoint collides"}
        T, az, el = found_pose
        view = server.observe(T, camera, gt_id)
        truth = view.target()
        visib = num(truth.visib_fract) if truth is not None else math.nan
        point.update(azimuth_deg=az, elevation_deg=el, render_s=view.timings_ms["render"] / 1000.0,
                     visib_fract=visib, px_visib=truth.px_count_visib if truth is not None else None,
                     bbox_diag_px=bbox_diagonal(truth.bbox_obj) if truth is not None else None)
        if truth is None or not visib >= MIN_VISIB_FRACT:
            return {**point, "target": False}
        est = s["estimator"].estimate(view.depth, camera.K, T, obj.obj_id, (camera.cx, camera.cy), view.rgb)
        # the estimator sees the splat's depth (as an agent); VSD is scored as an episode's: on the
        # test depth of the scene's reference geometry (the splat's only for a bundle without one)
        score = s["scorer"].score(est, obj.obj_id, truth.cam_T_obj, camera.K, (camera.width, camera.height),
                                  view.test_depth, visib)
        return {**point, "target": True, "found": est.cam_T_obj is not None, "method": est.method,
                "test_depth": view.geometry,
                "estimate_s": est.seconds, **score.to_json()}

    items = [(f"o{o.obj_id}-g{o.gt_id}-d{round(d * 1000)}-v{k}", (o.gt_id, float(d), k))
             for o in bundle.objects for d in sweep.distances_m for k in range(sweep.views)]
    return run_sweep(store, m, items, measure, desc="report: distance study", unit="view")


# ----------------------------------------------------------------------------- aggregation
def by_distance(points: Sequence[dict[str, Any]], obj_id: int | None = None) -> list[dict[str, Any]]:
    """Per distance (ascending): targets, mean AR and parts, pixel size and times (one object or all)."""
    groups: dict[float, list[dict[str, Any]]] = defaultdict(list)
    for p in points:
        if obj_id is None or p.get("obj_id") == obj_id:
            groups[round(num(p.get("distance_m")), 4)].append(p)
    rows = []
    for d, pts in sorted(groups.items()):
        targets = [p for p in pts if p.get("target")]
        row: dict[str, Any] = {"distance_m": d, "views": len(pts), "targets": len(targets),
                               "found": sum(bool(p.get("found")) for p in targets)}
        for k in METRIC_KEYS:
            values = [num(p.get(k)) for p in targets]
            values = [v for v in values if math.isfinite(v)]
            row[k] = float(np.mean(values)) if values else math.nan
        row["px_visib"] = median([p.get("px_visib") for p in targets])
        row["bbox_diag_px"] = median([p.get("bbox_diag_px") for p in targets])
        row["estimate_s"] = median([p.get("estimate_s") for p in targets])
        row["render_s"] = median([p.get("render_s") for p in pts])
        rows.append(row)
    return rows


def object_ids(points: Sequence[dict[str, Any]]) -> list[tuple[int, str]]:
    """The objects of the points, ``(obj_id, name)`` by id."""
    seen = {int(p["obj_id"]): str(p.get("object", p["obj_id"])) for p in points if p.get("obj_id") is not None}
    return sorted(seen.items())


# ----------------------------------------------------------------------------- rendering
def render_distance(m: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 6 from its measurement: AR (and parts) and pixel size against distance, tables, advice."""
    if m is None or not m.usable or not m.points:
        return unavailable(TITLE, m, "Distance study")
    overall = by_distance(m.points)
    objects = object_ids(m.points)
    per_object = {oid: by_distance(m.points, oid) for oid, _ in objects}
    fig, (ax_all, ax_obj) = new_figure(2, panel=(5.2, 3.8))
    cm = [r["distance_m"] * 100.0 for r in overall]
    dropped = plot_line(ax_all, cm, [r["ar"] for r in overall], "AR", fmt="ko-", lw=2)
    for k, style in (("ar_vsd", "s--"), ("ar_mssd", "^--"), ("ar_mspd", "v--")):
        dropped += plot_line(ax_all, cm, [r[k] for r in overall], f"AR_{k[3:].upper()}", fmt=style, alpha=0.8)
    px_all = ax_all.twinx()
    dropped += plot_line(px_all, cm, [r["bbox_diag_px"] for r in overall], None, fmt=":", color="0.45")
    px_all.set_ylabel("object box diagonal [px] (dotted, median)", color="0.35")
    colours = [f"C{i}" for i in range(len(objects))]
    px_obj = ax_obj.twinx()
    for (oid, name), colour in zip(objects, colours):
        rows = per_object[oid]
        x = [r["distance_m"] * 100.0 for r in rows]
        dropped += plot_line(ax_obj, x, [r["ar"] for r in rows], f"{name} (obj {oid})", fmt="o-", color=colour)
        dropped += plot_line(px_obj, x, [r["bbox_diag_px"] for r in rows], None, fmt=":", color=colour, alpha=0.7)
    px_obj.set_ylabel("box diagonal [px] (dotted)", color="0.35")
    for ax, what in ((ax_all, "all objects"), (ax_obj, "per object")):
        ax.set_xlabel("camera distance to the object's centre [cm]")
        ax.set_ylabel(f"BOP Average Recall ({what})")
        ax.set_ylim(-0.03, 1.03)
        legend(ax)
    for ax in (px_all, px_obj):
        ax.set_ylim(bottom=0)
    png = save_figure(fig, out_dir / FIGURE, "Static estimator on the served splat: AR against distance "
                      "(dotted: the object's pixel size)", describe_machine(m.machine), settings_line(m))
    table = [(fmt(r["distance_m"] * 100, 0), f"{r['targets']}/{r['views']}", f"{r['found']}", fmt(r["ar"], 3),
              fmt(r["ar_vsd"], 3), fmt(r["ar_mssd"], 3), fmt(r["ar_mspd"], 3), fmt(r["px_visib"], 0),
              fmt(r["bbox_diag_px"], 0), fmt(r["estimate_s"], 2), fmt(r["render_s"], 3)) for r in overall]
    distances = [r["distance_m"] for r in overall]
    obj_table = []
    for oid, name in objects:
        at = {r["distance_m"]: r for r in per_object[oid]}
        obj_table.append((f"{name} ({oid})", *(fmt(at[d]["ar"], 2) if d in at else "-" for d in distances)))
    skipped = sum(1 for p in m.points if not p.get("target"))
    body = (f"The static estimator (the baseline's perception + registration, one view, no camera move) on "
            f"`{m.summary.get('bundle')}`'s splat, rendered by the server's renderer from {m.settings.get('views')} "
            f"seeded viewpoints per object and distance (azimuth and elevation in the bundle's start ranges, looking "
            f"at the object's centre), scored against the bundle's ground truth. AR per view = fraction of the "
            f"BOP19 thresholds of VSD/MSSD/MSPD passed; rows pool the objects' views. Pixel size: median visible "
            f"mask area and box diagonal of the object."
            + (f" {skipped} views where the object was under {MIN_VISIB_FRACT:.0%} visible are no BOP19 target "
               "and are left out." if skipped else "")
            + f"\n\n![AR against distance]({png.name})\n\n"
            + format_table(["cm", "targets/views", "found", "AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "visible px",
                            "box diag px", "estimator s/view", "render s/view"], table)
            + "\n\nAR per object and distance (cm):\n\n"
            + format_table(["object", *(fmt(d * 100, 0) for d in distances)], obj_table)
            + "\n\n" + provenance(m) + "\n" + nan_note(dropped, "plotted distance values"))
    return RenderedSection(TITLE, body, advice_distance(overall, per_object, dict(objects)), [png])


def advice_distance(overall: list[dict[str, Any]], per_object: Mapping[int, list[dict[str, Any]]],
                    names: Mapping[int, str]) -> str:
    """Where AR peaks, where it falls below ``FALL_OFF`` of the peak (and the pixel size there), the
    weakest object, and what a view costs."""
    scored = [r for r in overall if math.isfinite(num(r["ar"]))]
    if len(scored) < 2:
        return ""
    best = max(scored, key=lambda r: r["ar"])
    worst = min(scored, key=lambda r: r["ar"])
    text = (f"**Sensor distance:** the static estimator scores best at {fmt(best['distance_m'] * 100, 0)} cm "
            f"(AR {fmt(best['ar'], 3)}, objects about {fmt(best['bbox_diag_px'], 0)} px across) and worst at "
            f"{fmt(worst['distance_m'] * 100, 0)} cm (AR {fmt(worst['ar'], 3)}, {fmt(worst['bbox_diag_px'], 0)} px)")
    weak = [r for r in scored if r["ar"] < FALL_OFF * best["ar"]]
    if weak:
        text += (f"; below {FALL_OFF:.0%} of the best at {', '.join(fmt(r['distance_m'] * 100, 0) for r in weak)} cm, "
                 "so start episodes (and plan captures for evaluation) in the remaining range")
    else:
        text += f"; every distance stays within {FALL_OFF:.0%} of the best, so the start distance is free to choose"
    obj_ar = {oid: float(np.nanmean([num(r["ar"]) for r in rows])) for oid, rows in per_object.items()
              if any(math.isfinite(num(r["ar"])) for r in rows)}
    if len(obj_ar) > 1:
        low = min(obj_ar, key=lambda k: obj_ar[k])
        text += f". The weakest object is {names.get(low, low)} (mean AR {fmt(obj_ar[low], 3)} over distances)"
    est = median([r["estimate_s"] for r in scored])
    ren = median([r["render_s"] for r in scored])
    return text + f"; one view costs {fmt(est, 2)} s of estimator and {fmt(ren, 3)} s of rendering (medians)."


class DistanceSection:
    """Section 6 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> DistanceSweep:
        """Full: 7 distances x 2 views per object at the bundle's size; quick: 3 x 1 at a quarter size."""
        if quick:
            return DistanceSweep(distances_m=(0.2, 0.35, 0.5), views=1, scale=0.25)
        return DistanceSweep()

    def measure(self, inputs: MeasureInputs, settings: DistanceSweep) -> Measurement:
        return measure_distance(inputs, settings)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_distance(measurements.get(NAME), out_dir)


SECTION = DistanceSection()

"""Report section 10: the learned estimator (detector + coordinate network trained on the scene's
own synthetic train_pbr) on held-out synthetic images, on captured frames and on the splat's
renders of the same poses, against distance, and what its accuracy costs in time.

- Held-out train_pbr: the model card's figures (``<workdir>/learned/model/card.json``, written when
  the model was trained; never an image it trained on): detection recall and AP at IoU 0.5 per
  object, pose AR given the true box and the detected box, RGB only and with depth.
- Captured vs splat: the views of the realism study (:mod:`brave6d.evaluation.report.real_vs_splat`:
  the BOP export's captured frames per distance level, each rendered from the bundle's splat with
  the same ``K`` and pose). In each view every object at least 10 % visible is estimated on both
  images four ways (the true box from ``scene_gt_info`` or the detector's best box of the object;
  RGB alone or with the image's depth) and scored with VSD/MSSD/MSPD against the export's ground
  truth on the captured frame's test depth. Gap = AR(captured) - AR(splat) per ring: the learned
  estimator's realism gap.
- Cost: ``<workdir>/learned/cost/learned_cost.json`` when ``benchmarks/learned_cost.py`` has
  written it (held-out AR and the learned agents' AR against training time and train_pbr images),
  ``detect_scale.json`` beside it when ``benchmarks/learned_detect_scale.py`` has (detection
  recall, AP and milliseconds against the detector's input width) and ``detector_patch.json`` when
  ``benchmarks/learned_detector_patch.py`` has (recall, AP and AR against the detector's training
  patch and steps, with their seconds) and ``precision.json`` when ``benchmarks/learned_precision.py``
  has (recall and AR against the training precision and steps, with their seconds).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from brave6d.core.progress import format_table
from brave6d.evaluation.report.common import RenderedSection, fmt, mean, nan_note, num, paired_standard_error, provenance
from brave6d.evaluation.report.common import settings_line, unavailable
from brave6d.evaluation.report.measurements import Measurement, describe_machine, file_stamp, machine_info, run_sweep
from brave6d.evaluation.report.plots import legend, new_figure, plot_line, save_figure
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.real_vs_splat import open_views
from brave6d.evaluation.report.single_view import MIN_VISIB_FRACT, ViewEstimate, ViewScorer, bbox_diagonal

NAME = "learned"
PAGE = 10
TITLE = f"{PAGE}. The learned estimator: held-out synthetic images, captured frames vs splat renders, distance, cost"
FIGURE = "learned.png"
#: The four ways a target is estimated: box (true / detected) x input (RGB / RGB + depth).
VARIANTS = ("true_box_rgb", "true_box_depth", "detected_rgb", "detected_depth")
LABELS = {"true_box_rgb": "true box, RGB", "true_box_depth": "true box, + depth", "detected_rgb": "detected, RGB",
          "detected_depth": "detected, + depth"}
#: The BOP19 metrics each target's AR averages (recorded per target and per ring).
METRICS = ("vsd", "mssd", "mspd")
#: A per-ring gap (captured - splat) at least this large is named (the issue's realism limit).
LARGE_GAP = 0.1
#: Where ``benchmarks/learned_cost.py`` writes for the report (beside the demo's ``learned/model``).
COST_FILE = Path("learned") / "cost" / "learned_cost.json"
#: Where ``benchmarks/learned_detect_scale.py`` writes for the report (beside ``COST_FILE``).
DETECT_SCALE_FILE = "detect_scale.json"
#: Where ``benchmarks/learned_detector_patch.py`` writes for the report (beside ``COST_FILE``).
DETECTOR_PATCH_FILE = "detector_patch.json"
#: Where ``benchmarks/learned_precision.py`` writes for the report (beside ``COST_FILE``).
PRECISION_FILE = "precision.json"
#: Where ``benchmarks/learned_rgb_distance.py`` writes for the report (beside ``COST_FILE``).
RGB_DISTANCE_FILE = "rgb_distance.json"


@dataclass(frozen=True)
class LearnedSweep:
    """Views per distance level (held-out first, then training views), the image stride and the
    device of the renderer and the networks."""

    holdout_per_level: int = 12  # the demo's 6-9 held-out views per ring, all of them: 36-48 targets per
    train_per_level: int = 3  # ring resolve a gap to about +-0.08 (two SE); 42 views, about 70 s on 2 cores
    stride: int = 1
    device: str = "auto"


def xywh_to_box(bbox: Sequence[float], stride: int) -> tuple[float, float, float, float] | None:
    """A BOP ``[x, y, w, h]`` box as pixel edges ``(x0, y0, x1, y1)`` of the decimated image (None when
    empty, not finite, or too thin to have an area in floating point)."""
    if bbox is None or len(bbox) != 4:
        return None
    x, y, w, h = (float(v) / stride for v in bbox)
    box = (x, y, x + w, y + h)
    if not all(math.isfinite(b) for b in box) or box[2] <= box[0] or box[3] <= box[1]:
        return None
    return box


def best_detections(estimator: Any, rgb: Any, K: Any, obj_ids: Sequence[int]) -> dict[int, Any]:
    """Per object of ``obj_ids``: its best detection in ``rgb``, box refined as the agents' is, or the
    refusal's cause; one detector pass for all of them."""
    from brave6d.evaluation.learned import LearnedRefused

    try:
        found = estimator.detect(rgb, K)
    except LearnedRefused as exc:
        return {o: exc.cause for o in obj_ids}
    out: dict[int, Any] = {}
    for obj_id in obj_ids:
        best = next((d for d in found if d.obj_id == obj_id), None)
        out[obj_id] = estimator.refine_box(rgb, K, best) if best is not None else "no-detection"
    return out


def estimate_target(estimator: Any, rgb: Any, depth_m: Any, K: Any, obj_id: int,
                    true_box: tuple[float, float, float, float] | None,
                    detected: Any) -> dict[str, tuple[ViewEstimate, str | None]]:
    """The four :data:`VARIANTS` of one target (``detected``: its detection, or why there is none):
    each an estimate (``cam_T_obj`` None when refused) and the refusal's cause. A box's RGB-only and
    depth variants share one pass of the pose network (each records that pass's seconds)."""
    import time

    from brave6d.evaluation.learned import LearnedRefused

    boxes: dict[str, tuple[tuple[float, float, float, float], float] | str] = {
        "true_box": (true_box, 1.0) if true_box is not None else "no-box",
        "detected": detected if isinstance(detected, str) else (detected.box, detected.score)}
    out: dict[str, tuple[ViewEstimate, str | None]] = {}
    for kind, given in boxes.items():
        if isinstance(given, str):
            for mode in ("rgb", "depth"):
                out[f"{kind}_{mode}"] = (ViewEstimate(None, 0.0, 0.0, "learned"), given)
            continue
        t0 = time.perf_counter()
        try:
            rgb_pose, depth_pose = estimator.estimate_both(rgb, K, obj_id, given[0], depth_m, given[1])
        except LearnedRefused as exc:
            for mode in ("rgb", "depth"):
                out[f"{kind}_{mode}"] = (ViewEstimate(None, 0.0, time.perf_counter() - t0, "learned"), exc.cause)
            continue
        seconds = time.perf_counter() - t0
        for mode, pose in (("rgb", rgb_pose), ("depth", depth_pose if depth_pose is not None else rgb_pose)):
            out[f"{kind}_{mode}"] = (ViewEstimate(pose.cam_T_obj, pose.score, seconds, "learned"), None)
    return {v: out[v] for v in VARIANTS}


def measure_learned(inputs: MeasureInputs, sweep: LearnedSweep) -> Measurement:
    """Run (or resume) the learned estimator's captured-vs-splat sweep; see the module docstring."""
    from brave6d.training import resolve_device

    workdir, scene, store = inputs.workdir, inputs.scene, inputs.store
    from brave6d.evaluation.learned.demo import demo_model_dir

    model_dir = Path(inputs.learned_model) if inputs.learned_model is not None else demo_model_dir(workdir)
    model_path, card_path = model_dir / "model.pt", model_dir / "card.json"
    if (absent := store.require(NAME, [(model_path, "learn (brave6d learn train / the demo's learn stage)"),
                                       (card_path, "learn (the model's card)")])) is not None:
        return absent
    device = str(resolve_device(sweep.device))
    views = open_views(store, NAME, scene, sweep.holdout_per_level, sweep.train_per_level, sweep.stride, device)
    if isinstance(views, Measurement):
        return views
    from brave6d.annotation import read_models_info
    from brave6d.evaluation.learned import LearnedEstimator, read_card
    from brave6d.evaluation.metrics import load_models

    layout, gts, infos = views.layout, views.gts, views.infos
    key = {**views.key(), "model": file_stamp(model_path), "card": file_stamp(card_path), "sweep": asdict(sweep),
           "test_depth": "captured", "detected_boxes": "refined by the pose network's mask",
           "detect_widths": LearnedEstimator.load(model_dir).detect_widths}
    if (done := store.complete(NAME, key)) is not None:
        return done
    w, h = views.image_size
    settings = {"views": len(views.views), "holdout_per_level": sweep.holdout_per_level,
                "train_per_level": sweep.train_per_level, "image": f"{w}x{h}", "device": device}
    m = store.resume(NAME, key, settings, machine_info(device))
    views.describe(m)
    card = read_card(model_dir)
    m.summary.update({"cost": str(cost_path(model_dir)), "model": str(model_dir), "detect_widths": key["detect_widths"],
                      "evaluation": str(Path(workdir) / "evaluation"),
                      "card": {k: card.get(k) for k in ("images", "heldout_images", "train_seconds", "device",
                                                        "heldout", "preset", "objects", "model_sha256")}})
    state: dict[str, Any] = {}

    def prepared() -> dict[str, Any]:  # the networks and models only when a point is missing
        if not state:
            ids = sorted({g.obj_id for i, _ in views.views for g in gts[i]})
            models = load_models(layout.models_dir, ids, read_models_info(layout.models_info_path))
            state.update(scorer=ViewScorer(models),
                         estimator=LearnedEstimator.load(model_dir, device, models_dir=layout.models_dir))
        return state

    def measure(item: tuple[int, bool]) -> dict[str, Any]:
        point, pair = views.measured_pair(*item)
        if pair is None or pair.depth_real is None:
            return point
        s, im_id = prepared(), item[0]
        size = (pair.depth_real.shape[1], pair.depth_real.shape[0])
        sides = (("real", pair.rgb_real, pair.depth_real), ("splat", pair.rgb_splat, pair.depth_splat))
        known = sorted({g.obj_id for g in gts[im_id]} & set(s["estimator"].obj_ids))
        found = {side: best_detections(s["estimator"], rgb, pair.K, known) for side, rgb, _ in sides}
        objects = []
        for g, gi in zip(gts[im_id], infos[im_id]):
            if gi.visib_fract < MIN_VISIB_FRACT:
                continue
            row: dict[str, Any] = {"obj_id": g.obj_id, "object": views.names.get(g.obj_id, str(g.obj_id)),
                                   "visib_fract": gi.visib_fract,
                                   "bbox_diag_px": (bbox_diagonal(gi.bbox_obj) or math.nan) / sweep.stride}
            if g.obj_id not in s["estimator"].obj_ids:
                row["note"] = f"object {g.obj_id} was not in the model's training split"
                objects.append(row)
                continue
            box = xywh_to_box(gi.bbox_obj, sweep.stride)
            for side, rgb, depth in sides:
                detected = found[side][g.obj_id]
                for variant, (est, cause) in estimate_target(s["estimator"], rgb, depth, pair.K, g.obj_id, box,
                                                             detected).items():
                    score = s["scorer"].score(est, g.obj_id, g.cam_T_model(), pair.K, size, pair.depth_real,
                                              gi.visib_fract)
                    row[f"{side}_{variant}_ar"] = score.ar
                    for metric in METRICS:
                        row[f"{side}_{variant}_{metric}"] = getattr(score, f"ar_{metric}")
                    row[f"{side}_{variant}_cause"] = cause
                    row[f"{side}_{variant}_s"] = est.seconds
            objects.append(row)
        return {**point, "render_s": pair.render_s, "objects": objects}

    items = [(f"im{i}", (i, held)) for i, held in views.views]
    return run_sweep(store, m, items, measure, desc="report: learned estimator", unit="view")


# ----------------------------------------------------------------------------- aggregation
def ring_rows(points: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per distance level: targets, and per variant AR on captured frames, on splat renders, the gap ± SE."""
    by_level: dict[int, list[dict[str, Any]]] = defaultdict(list)
    for p in points:
        by_level[int(p.get("level", -1))].append(p)
    rows = []
    for level, pts in sorted(by_level.items()):
        tg = [o for p in pts for o in p.get("objects", []) if f"real_{VARIANTS[0]}_ar" in o]
        row: dict[str, Any] = {"level": level, "distance_m": num(pts[0].get("distance_m")), "views": len(pts),
                               "targets": len(tg), "bbox_diag_px": mean([o.get("bbox_diag_px") for o in tg])}
        for v in VARIANTS:
            real, splat = [num(o.get(f"real_{v}_ar")) for o in tg], [num(o.get(f"splat_{v}_ar")) for o in tg]
            row[f"real_{v}"], row[f"splat_{v}"] = mean(real), mean(splat)
            row[f"gap_{v}"] = row[f"real_{v}"] - row[f"splat_{v}"]
            row[f"gap_se_{v}"] = paired_standard_error([a - b for a, b in zip(real, splat)])
            for side, values in (("real", real), ("splat", splat)):
                row[f"se_{side}_{v}"] = standard_error(values)
                for metric in METRICS:
                    row[f"{side}_{v}_{metric}"] = mean([o.get(f"{side}_{v}_{metric}") for o in tg])
        rows.append(row)
    return rows


def near_far(rows: Sequence[Mapping[str, Any]], variant: str = "true_box_rgb", side: str = "splat"
             ) -> tuple[float, float, float, float] | None:
    """AR at the nearest ring, at the farthest, their difference and its standard error (the rings'
    targets are different ones: the two SEs combined); None with fewer than two rings."""
    ok = [r for r in rows if r.get("targets")]
    if len(ok) < 2:
        return None
    near, far = ok[0], ok[-1]
    a, b = num(near.get(f"{side}_{variant}")), num(far.get(f"{side}_{variant}"))
    se = math.hypot(num(near.get(f"se_{side}_{variant}")), num(far.get(f"se_{side}_{variant}")))
    return a, b, a - b, se


def standard_error(values: Sequence[Any]) -> float:
    """Standard error of the mean of the finite ``values`` (NaN with fewer than two)."""
    return paired_standard_error([num(v) for v in values])


#: The active agents and the gain over their static twin the benchmark claims for each (issue #62).
CLAIMED_GAIN = {"learned-active": 0.10, "learned-active-depth": 0.05}
#: The parts of the active agent that the ablation plays alone (``agents.learned.ablation``).
ABLATION_PARTS = ("closeness", "selection", "fusion")


def ablation_rows(played: Sequence[Any]) -> list[dict[str, Any]]:
    """Per learned active agent: its gain over its static twin, paired by start, and each part's alone
    (:data:`ABLATION_PARTS`), from the evaluation's episodes (``played``: :data:`pairing.Played`)."""
    from brave6d.evaluation.metrics.pairing import paired_difference

    rows = []
    for active, claimed in CLAIMED_GAIN.items():
        static = active.replace("active", "static")
        for part in (None, *ABLATION_PARTS):
            name = active if part is None else f"{active}-{part}"
            d = paired_difference(played, name, static)
            if d is not None:
                rows.append({"agent": name, "part": part or "all (the agent)", "static": static, **d.to_json(),
                             "verdict": d.verdict(claimed if part is None else None)})
    return rows


def read_played(evaluation: Path) -> list[Any]:
    """The scored episodes of the evaluation stage's leaderboards (``evaluation/leaderboard.json`` and the
    ablation's, ``evaluation/ablation/leaderboard.json``) as pairing reads them; [] when there are none."""
    from brave6d.evaluation.demo import ABLATION_DIR
    from brave6d.evaluation.metrics.pairing import played_of_rows

    played: list[Any] = []
    for path in (evaluation / "leaderboard.json", evaluation / ABLATION_DIR / "leaderboard.json"):
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        rows = data.get("episodes") if isinstance(data, dict) else None
        if isinstance(rows, list):
            played += played_of_rows([r for r in rows if isinstance(r, dict)])
    return played


def cost_path(model_dir: Path) -> Path:
    """Where ``benchmarks/learned_cost.py`` writes for the report: ``learned/cost/`` beside ``learned/model``."""
    return Path(model_dir).parent / COST_FILE.parent.name / COST_FILE.name


def read_cost(path: Path) -> dict[str, Any] | None:
    """``benchmarks/learned_cost.py``'s result ``path`` (None when absent or unreadable)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("points"), list) else None


def read_benchmark_rows(path: Path) -> list[dict[str, Any]] | None:
    """The rows of ``benchmarks/learned_detect_scale.py``'s, ``learned_detector_patch.py``'s,
    ``learned_precision.py``'s or ``learned_rgb_distance.py``'s JSON ``path`` (None when absent or
    unreadable)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    rows = data.get("rows") if isinstance(data, dict) else None
    return rows if isinstance(rows, list) and all(isinstance(r, dict) for r in rows) else None


def _detection_cells(r: Mapping[str, Any]) -> tuple[str, ...]:
    """A detection benchmark row's recall per object, worst recall, AP per object and AR given the
    detected boxes (RGB, + depth): the columns both detector tables share."""
    ar = r.get("detected_ar") or {}
    return (" / ".join(fmt(v, 2) for v in (r.get("recall") or {}).values()), fmt(r.get("recall_min"), 2),
            " / ".join(fmt(v, 2) for v in (r.get("ap") or {}).values()), fmt(ar.get("detected_rgb"), 3),
            fmt(ar.get("detected_depth"), 3))


def _detect_scale_part(rows: list[dict[str, Any]] | None, current: Any) -> tuple[str, str]:
    """The table and advice of the detector's input widths (what each set buys in recall and AP, and costs in ms)."""
    if not rows:
        return "", ""

    def widths(r: Mapping[str, Any]) -> str:
        return " + ".join(str(w) for w in (r.get("detect_widths") or ["?"]))

    table_rows = [(" + ".join(fmt(x, 3) for x in (r.get("scales") or [])), widths(r), *_detection_cells(r),
                   fmt(r.get("detect_ms"), 1)) for r in rows]
    now = " + ".join(str(w) for w in current) if isinstance(current, list) and current else "?"
    table = ("The detector's input widths (`benchmarks/learned_detect_scale.py`; the estimator detects at "
             f"{now} px):\n\n"
             + format_table(["scales", "widths px", "recall per object", "recall min", "AP per object", "AR det RGB",
                             "AR det +D", "ms per image"], table_rows) + "\n")
    best = max(rows, key=lambda r: num(r.get("recall_min")))
    cheapest = min(rows, key=lambda r: num(r.get("detect_ms")))
    advice = (f" Detector widths: {widths(best)} px give the best worst-object recall "
              f"({fmt(best.get('recall_min'), 2)}) for {fmt(best.get('detect_ms'), 1)} ms per image; the cheapest, "
              f"{widths(cheapest)} px, {fmt(cheapest.get('recall_min'), 2)} for {fmt(cheapest.get('detect_ms'), 1)} ms.")
    return table, advice


def _detector_patch_part(rows: list[dict[str, Any]] | None, card: Mapping[str, Any]) -> tuple[str, str]:
    """The table and advice of the detector's training patches (what each patch and step count buys in
    recall and AR, and costs in training seconds)."""
    if not rows:
        return "", ""

    def point(r: Mapping[str, Any]) -> str:
        return f"{r.get('patch')} px x {r.get('steps')} steps"

    table_rows = [(r.get("patch"), r.get("steps"), fmt(r.get("detector_s"), 0), fmt(r.get("steps_per_s"), 2),
                   *_detection_cells(r), _agents_cell(r.get("agents"))) for r in rows]
    preset = card.get("preset") or {}
    now = f"{preset.get('detector_patch', '?')} px x {preset.get('detector_steps', '?')} steps"
    table = ("The detector's training patches (`benchmarks/learned_detector_patch.py`, the same coordinate net for "
             f"every row; this model trained {now}):\n\n"
             + format_table(["patch px", "steps", "detector s", "steps/s", "recall per object", "recall min",
                             "AP per object", "AR det RGB", "AR det +D", "agents static / active (+D)"],
                            table_rows) + "\n")
    best = max(rows, key=lambda r: num(r.get("recall_min")))
    cheapest = min(rows, key=lambda r: num(r.get("detector_s")))
    advice = (f" Detector patches: {point(best)} give the best worst-object recall ({fmt(best.get('recall_min'), 2)}) "
              f"in {fmt(best.get('detector_s'), 0)} s of training; the quickest, {point(cheapest)}, "
              f"{fmt(cheapest.get('recall_min'), 2)} in {fmt(cheapest.get('detector_s'), 0)} s.")
    played = [r for r in rows if isinstance(r.get("agents"), dict)]
    if played:
        agent = max(played, key=lambda r: num(r["agents"].get("learned-active-depth")))
        advice += (f" As agents, {point(agent)} give learned-active-depth the best AR "
                   f"({fmt(agent['agents'].get('learned-active-depth'), 3)}): choose the patch by this, not by recall alone.")
    return table, advice


def _precision_part(rows: list[dict[str, Any]] | None, card: Mapping[str, Any]) -> tuple[str, str]:
    """The table and advice of the training precision and steps (what each buys in recall and AR, and
    costs in training seconds)."""
    if not rows:
        return "", ""

    def point(r: Mapping[str, Any]) -> str:
        return f"{r.get('precision')} x {r.get('detector_steps')} + {r.get('pose_steps')} steps"

    def ar(r: Mapping[str, Any], variant: str) -> float:
        return num((r.get("pose_ar") or {}).get(variant))

    table_rows = [(r.get("precision"), f"{r.get('detector_steps')} + {r.get('pose_steps')}", fmt(r.get("train_s"), 0),
                   fmt(ar(r, "true_box_rgb"), 3), fmt(ar(r, "true_box_depth"), 3), *_detection_cells(r),
                   _agents_cell(r.get("agents"))) for r in rows]
    preset = card.get("preset") or {}
    now = (f"{preset.get('precision', 'fp32')} x {preset.get('detector_steps', '?')} + "
           f"{preset.get('pose_steps', '?')} steps")
    table = ("Training precision and steps (`benchmarks/learned_precision.py`, both networks trained per row; this "
             f"model trained {now}):\n\n"
             + format_table(["precision", "steps det + pose", "train s", "AR true RGB", "AR true +D",
                             "recall per object", "recall min", "AP per object", "AR det RGB", "AR det +D",
                             "agents static / active (+D)"], table_rows) + "\n")
    best = max(rows, key=lambda r: ar(r, "detected_depth"))
    cheapest = min(rows, key=lambda r: num(r.get("train_s")))
    advice = (f" Training: {point(best)} gives the best AR given detected boxes with depth "
              f"({fmt(ar(best, 'detected_depth'), 3)}, worst-object recall {fmt(best.get('recall_min'), 2)}) in "
              f"{fmt(best.get('train_s'), 0)} s; the quickest, {point(cheapest)}, "
              f"{fmt(ar(cheapest, 'detected_depth'), 3)} ({fmt(cheapest.get('recall_min'), 2)}) in "
              f"{fmt(cheapest.get('train_s'), 0)} s.")
    same = {(r.get("detector_steps"), r.get("pose_steps")): r for r in rows if r.get("precision") == "fp32"}
    pairs = [(same[(r.get("detector_steps"), r.get("pose_steps"))], r) for r in rows
             if r.get("precision") == "bf16" and (r.get("detector_steps"), r.get("pose_steps")) in same]
    if pairs:
        fp32, bf16 = pairs[0]
        advice += (f" At the same steps bf16 trains in {fmt(num(bf16.get('train_s')) / num(fp32.get('train_s')), 2)}x "
                   f"fp32's time (AR detected + depth {fmt(ar(bf16, 'detected_depth'), 3)} vs "
                   f"{fmt(ar(fp32, 'detected_depth'), 3)}): where the CPU has bfloat16, spend the time it saves on steps.")
    return table, advice


def _rgb_distance_part(rows: list[dict[str, Any]] | None) -> tuple[str, str]:
    """The table and advice of the RGB-only pose's settings (PnP's own distance, the mask's area,
    that with crops at several zooms): what each gives given true and detected boxes and as agents,
    and costs per estimate; the ceilings say how good a distance the RGB-only pose would need."""
    if not rows:
        return "", ""

    def ar(r: Mapping[str, Any], variant: str) -> float:
        return num((r.get("pose_ar") or {}).get(variant))

    table_rows = []
    for r in rows:
        m = r.get("true_box_rgb") or {}
        table_rows.append((r.get("setting"), f"{fmt(ar(r, 'true_box_rgb'), 3)} ({fmt(m.get('vsd'), 3)} / "
                           f"{fmt(m.get('mssd'), 3)} / {fmt(m.get('mspd'), 3)})", fmt(ar(r, "detected_rgb"), 3),
                           fmt(r.get("ms_per_estimate"), 1), _agents_cell(r.get("agents"))))
    ceilings = (rows[-1].get("true_box_rgb") or {}).get("ceilings") or {}
    table = ("The RGB-only pose (`benchmarks/learned_rgb_distance.py`: PnP's own distance, or the distance from "
             "the mask's area against the model's silhouette, from one crop or three zooms of it):\n\n"
             + format_table(["setting", "AR true box RGB (VSD / MSSD / MSPD)", "AR detected RGB", "ms per estimate",
                             "agents static / active (+D)"], table_rows) + "\n"
             + ("\nThe same RGB-only poses given true boxes with the true distance: "
                + ", ".join(f"{k} {fmt(v, 3)}" for k, v in ceilings.items()) + ".\n" if ceilings else ""))
    by_name = {r.get("setting"): r for r in rows}
    pnp, area = by_name.get("pnp"), by_name.get("mask-area")
    if pnp is None or area is None:
        return table, ""
    gain = ar(area, "true_box_rgb") - ar(pnp, "true_box_rgb")
    cost = num(area.get("ms_per_estimate")) - num(pnp.get("ms_per_estimate"))
    verdict = "keep it on (`LearnedEstimator.mask_area_distance`)" if gain > 0 else "it does not pay here: turn it off"
    advice = (f" RGB-only, the distance from the mask's area changes AR given true boxes by {_signed(gain, 3)} "
              f"({fmt(ar(pnp, 'true_box_rgb'), 3)} -> {fmt(ar(area, 'true_box_rgb'), 3)}) for "
              f"{_signed(cost, 1)} ms per estimate: {verdict}.")
    zooms = by_name.get("mask-area, 3 zooms")
    if zooms is not None:
        gain = ar(zooms, "true_box_rgb") - ar(area, "true_box_rgb")
        cost = num(zooms.get("ms_per_estimate")) - num(area.get("ms_per_estimate"))
        verdict = ("keep them (`LearnedEstimator.crop_zooms`)" if gain > 0
                   else "they do not pay here: set `LearnedEstimator.crop_zooms = (1.0,)`")
        advice += (f" Three zooms of each box under one PnP change it by {_signed(gain, 3)} "
                   f"(given detected boxes {_signed(ar(zooms, 'detected_rgb') - ar(area, 'detected_rgb'), 3)}, "
                   f"with depth {_signed(ar(zooms, 'detected_depth') - ar(area, 'detected_depth'), 3)}) for "
                   f"{_signed(cost, 1)} ms per estimate: {verdict}.")
    if ceilings:
        advice += (f" With the true distance the same poses would score {fmt(ceilings.get('true distance'), 3)}, "
                   f"with it 1 % off {fmt(ceilings.get('distance 1% off'), 3)}: what is left between that and AR is "
                   "the RGB-only distance; below it, the rotation.")
    return table, advice


def _signed(value: float, digits: int) -> str:
    """``+0.063`` / ``-1.2`` (``n/a`` when not finite)."""
    return f"{value:+.{digits}f}" if math.isfinite(value) else "n/a"


def _agents_cell(agents: Any) -> str:
    """``learned-static / learned-active (static-depth / active-depth)`` AR, or "-" when not played."""
    if not isinstance(agents, dict):
        return "-"
    a = [fmt(agents.get(k), 3) for k in ("learned-static", "learned-active", "learned-static-depth", "learned-active-depth")]
    return f"{a[0]} / {a[1]} ({a[2]} / {a[3]})"


# ----------------------------------------------------------------------------- rendering
def _heldout_table(card: Mapping[str, Any]) -> str:
    held = card.get("heldout") or {}
    if not held:
        return "The model's card has no held-out figures.\n"
    recall, ap = held.get("detection_recall_iou50", {}), held.get("detection_ap_iou50", {})
    per_obj = held.get("pose_ar_per_object", {})
    rows = [(oid, fmt(recall.get(oid), 2), fmt(ap.get(oid), 2),
             *(fmt(per_obj.get(v, {}).get(oid), 3) for v in VARIANTS)) for oid in sorted(recall, key=int)]
    ar = held.get("pose_ar", {})
    rows.append(("all", "", "", *(fmt(ar.get(v), 3) for v in VARIANTS)))
    apart = ", a split rendered apart" if held.get("whole_split") else ""
    return (f"Held-out train_pbr ({held.get('images')} images, {held.get('instances')} instances{apart}, never trained "
            f"on; the model's split has {card.get('images')} images, trained {fmt(card.get('train_seconds'), 0)} s on "
            f"{card.get('device')}):\n\n"
            + format_table(["obj", "recall@0.5", "AP@0.5", *(f"AR {LABELS[v]}" for v in VARIANTS)], rows) + "\n")


def _cost_part(cost: dict[str, Any] | None, ax: Any) -> tuple[str, str]:
    """The cost table and advice from ``learned_cost.json`` (and its plot on ``ax``)."""
    if cost is None:
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no learned_cost.json yet", ha="center", va="center")
        return (f"What accuracy costs: not measured for this work directory yet: `python benchmarks/learned_cost.py "
                f"SPEC MODELS <workdir>/{COST_FILE.parent} --bundle BUNDLE` (beside the model's folder) writes it.\n", "")
    pts = cost["points"]
    rows, xs = [], []
    for p in pts:
        a, g = p.get("heldout_ar", {}), p.get("agents", {})
        total = num(p.get("train_s")) + (num(p.get("synth_s")) if p.get("synth_s") is not None else 0.0)
        xs.append(total)
        rows.append((p.get("images"), p.get("steps"), fmt(p.get("synth_s"), 0), fmt(p.get("train_s"), 0),
                     fmt(a.get("true_box_rgb"), 3), fmt(a.get("true_box_depth"), 3), fmt(a.get("detected_depth"), 3),
                     fmt(p.get("recall_min"), 2),
                     *(fmt(g.get(k), 3) for k in ("learned-static", "learned-active", "learned-static-depth",
                                                  "learned-active-depth"))))
    for key, style in (("true_box_depth", "o-"), ("detected_depth", "s--")):
        plot_line(ax, xs, [p.get("heldout_ar", {}).get(key) for p in pts], f"held-out AR, {LABELS[key]}", fmt=style)
    for key, style in (("learned-static-depth", "v:"), ("learned-active-depth", "^:")):
        if any(key in p.get("agents", {}) for p in pts):
            plot_line(ax, xs, [p.get("agents", {}).get(key) for p in pts], f"{key} (splat episodes)", fmt=style)
    for x, p in zip(xs, pts):
        ax.annotate(f"{p.get('images')} img / {p.get('steps')} st", (x, num(p.get("heldout_ar", {}).get("true_box_depth"))),
                    fontsize=7)
    ax.set_xlabel("synth + training time [s]")
    ax.set_ylabel("BOP Average Recall")
    ax.set_ylim(-0.03, 1.03)
    legend(ax)
    table = ("What accuracy costs (`benchmarks/learned_cost.py`; synth time priced at "
             f"{fmt(cost.get('synth_images_per_s'), 2)} images/s):\n\n"
             + format_table(["images", "steps/net", "synth s", "train s", "AR true RGB", "AR true +D", "AR det +D",
                             "recall min", "static", "active", "static +D", "active +D"], rows) + "\n")
    best = max(zip(xs, pts), key=lambda xp: num(xp[1].get("heldout_ar", {}).get("detected_depth")), default=None)
    advice = ""
    if best is not None:
        cheapest = min(zip(xs, pts), key=lambda xp: xp[0])
        advice = (f" Training cost: the best held-out AR (detected box, + depth) "
                  f"{fmt(best[1].get('heldout_ar', {}).get('detected_depth'), 3)} came from {best[1].get('images')} images "
                  f"x {best[1].get('steps')} steps ({fmt(best[0], 0)} s of synth + training); the cheapest point "
                  f"({cheapest[1].get('images')} x {cheapest[1].get('steps')}, {fmt(cheapest[0], 0)} s) reached "
                  f"{fmt(cheapest[1].get('heldout_ar', {}).get('detected_depth'), 3)}.")
    return table, advice


def _distance_part(rows: list[dict[str, Any]]) -> tuple[str, str]:
    """Why AR moves with distance (per ring: the RGB-only pose's VSD / MSSD / MSPD on the splat, given
    true boxes) and whether the nearest ring beats the farthest (the benchmark's premise: coming closer
    helps), with its standard error."""
    v = "true_box_rgb"
    ok = [r for r in rows if r.get("targets")]
    if not ok or not all(math.isfinite(num(r.get(f"splat_{v}_vsd"))) for r in ok):
        return "", ""
    table = ("The RGB-only pose given true boxes, per ring, on the splat's renders (captured frames in brackets): "
             "VSD and MSSD count 3D errors against the object's size, MSPD pixels in the image, so a constant "
             "angular error costs more MSPD the nearer the camera:\n\n"
             + format_table(["cm", "targets", "AR", "AR VSD", "AR MSSD", "AR MSPD"],
                            [(fmt(r["distance_m"] * 100, 0), r["targets"],
                              f"{fmt(r[f'splat_{v}'], 3)} ({fmt(r[f'real_{v}'], 3)})",
                              *(f"{fmt(r[f'splat_{v}_{k}'], 2)} ({fmt(r[f'real_{v}_{k}'], 2)})" for k in METRICS))
                             for r in ok]) + "\n")
    nf = near_far(ok)
    if nf is None:
        return table, ""
    a, b, d, se = nf
    near, far = fmt(ok[0]["distance_m"] * 100, 0), fmt(ok[-1]["distance_m"] * 100, 0)
    verdict = ("resolved at two standard errors" if math.isfinite(se) and abs(d) >= 2 * se else
               f"not resolved at two standard errors with {ok[0]['targets']} and {ok[-1]['targets']} targets: "
               "more views per ring (`LearnedSweep.holdout_per_level`) would tell")
    advice = (f" Coming closer, RGB-only given true boxes on the splat: AR {fmt(a, 3)} at {near} cm against "
              f"{fmt(b, 3)} at {far} cm ({_signed(d, 3)} ± {fmt(se, 3)}, {verdict}).")
    return table, advice


def _ablation_part(rows: list[dict[str, Any]], ax: Any) -> tuple[str, str]:
    """What each part of the learned active agent buys alone (paired by start against its static twin),
    as a table, a plot on ``ax`` and a verdict on the agents' claimed gains."""
    if not rows:
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no learned-agent episodes yet", ha="center", va="center")
        return ("The learned active agent's parts: no paired episodes of the learned agents in this work "
                "directory's evaluation yet (`brave6d demo --only evaluate`).\n", "")
    labels = [r["agent"] for r in rows]
    y = list(range(len(rows)))
    means = [num(r["mean"]) for r in rows]
    errors = [2.0 * num(r["se"]) if r.get("se") is not None else 0.0 for r in rows]
    ax.barh(y, means, xerr=errors, color=["C0" if "depth" not in n else "C1" for n in labels], alpha=0.8)
    ax.set_yticks(y, labels, fontsize=7)
    ax.axvline(0.0, color="0.3", lw=0.8)
    ax.invert_yaxis()
    ax.set_xlabel("AR gain over the static twin (paired by start; bars: ± 2 SE)")
    table = ("What the learned active agent's parts buy, each alone (`learned-active-closeness`: comes closer, "
             "submits the nearest view's estimate; `-selection`: stays at the start distance, looks from the sides, "
             "submits the best-ranked view's; `-fusion`: stays, looks from the sides, fuses every view into the start "
             "view's estimate), each minus its static twin over the same seeded starts:\n\n"
             + format_table(["agent", "part", "paired starts", "AR", "static AR", "gain", "SE", "resolved?"],
                            [(r["agent"], r["part"], r["pairs"], fmt(r["active_ar"], 3), fmt(r["static_ar"], 3),
                              _signed(num(r["mean"]), 3), fmt(r.get("se"), 3), r["verdict"]) for r in rows]) + "\n")
    advice = ""
    for active, claimed in CLAIMED_GAIN.items():
        full = next((r for r in rows if r["agent"] == active), None)
        if full is None:
            continue
        parts = {r["part"]: num(r["mean"]) for r in rows if r["agent"].startswith(active + "-")
                 and r["part"] in ABLATION_PARTS and ("depth" in active) == ("depth" in r["agent"])}
        source = max(parts, key=lambda k: parts[k]) if parts else None
        advice += (f" {active} gains {_signed(num(full['mean']), 3)} ± {fmt(full.get('se'), 3)} over {full['static']} "
                   f"(claimed {_signed(claimed, 2)}: {full['verdict']})"
                   + (f"; alone, {source} buys the most ({_signed(parts[source], 3)})" if source else "") + ".")
    return table, advice


def render_learned(m: Measurement | None, out_dir: Path, cost: dict[str, Any] | None = None,
                   detect_scale: list[dict[str, Any]] | None = None,
                   detector_patch: list[dict[str, Any]] | None = None,
                   precision: list[dict[str, Any]] | None = None,
                   rgb_distance: list[dict[str, Any]] | None = None,
                   played: Sequence[Any] = ()) -> RenderedSection:
    """Section 10 from its measurement (and the cost benchmarks' results, when there are some; ``played``:
    the evaluation's scored episodes, :func:`read_played`, for the active agent's ablation)."""
    if m is None or not m.usable or not m.points:
        return unavailable(TITLE, m, "The learned estimator's study")
    rows = ring_rows(m.points)
    card = m.summary.get("card") or {}
    fig, (ax_ar, ax_gap, ax_parts, ax_cost) = new_figure(4, panel=(4.6, 3.8))
    cm = [r["distance_m"] * 100.0 for r in rows]
    dropped = 0
    for i, v in enumerate(VARIANTS):
        dropped += plot_line(ax_ar, cm, [r[f"real_{v}"] for r in rows], f"captured, {LABELS[v]}", fmt="o-", color=f"C{i}")
        dropped += plot_line(ax_ar, cm, [r[f"splat_{v}"] for r in rows], None, fmt="s--", color=f"C{i}", alpha=0.7)
        dropped += plot_line(ax_gap, cm, [r[f"gap_{v}"] for r in rows], LABELS[v], fmt="o-", color=f"C{i}")
    for ax in (ax_ar, ax_gap):
        ax.set_xlabel("capture distance level [cm]")
    ax_ar.set_ylabel("BOP AR (solid: captured, dashed: splat)")
    ax_ar.set_ylim(-0.03, 1.03)
    ax_gap.set_ylabel("AR gap: captured - splat")
    for y in (-LARGE_GAP, 0.0, LARGE_GAP):
        ax_gap.axhline(y, color="0.3", lw=0.8, ls="-" if y == 0 else ":")
    legend(ax_ar)
    legend(ax_gap)
    cost_table, cost_advice = _cost_part(cost, ax_cost)
    scale_table, scale_advice = _detect_scale_part(detect_scale, m.summary.get("detect_widths"))
    patch_table, patch_advice = _detector_patch_part(detector_patch, card)
    precision_table, precision_advice = _precision_part(precision, card)
    distance_table, distance_advice = _rgb_distance_part(rgb_distance)
    near_table, near_advice = _distance_part(rows)
    parts_table, parts_advice = _ablation_part(ablation_rows(played), ax_parts)
    png = save_figure(fig, out_dir / FIGURE, "Learned estimator: AR against distance on captured frames and splat renders",
                      describe_machine(m.machine), settings_line(m))
    table = [(fmt(r["distance_m"] * 100, 0), r["views"], r["targets"], fmt(r["bbox_diag_px"], 0),
              *(f"{fmt(r[f'real_{v}'], 2)} / {fmt(r[f'splat_{v}'], 2)} ({fmt(r[f'gap_{v}'], 2)} ± {fmt(r[f'gap_se_{v}'], 2)})"
                for v in VARIANTS)) for r in rows]
    body = ("The learned estimator of the demo (`" + str(m.summary.get("model")) + "`: a detector and a coordinate "
            "network trained from scratch on the scene's own synthetic train_pbr, one robust PnP over each box's crops at a few zooms, "
            "the distance from the mask's area, optionally scaled and ICP-refined with depth) on held-out synthetic images, then on the captured frames of the annotation's BOP "
            "export and on the splat's renders of the same poses, each target estimated four ways (true or detected "
            "box; RGB alone or with depth) and scored on the captured frame's test depth. The gap per ring is the "
            "learned estimator's realism gap (captured - splat); a ring's targets resolve it to about ± 2 SE. In the "
            "demo the captured frames come from the simulated camera.\n\n"
            + _heldout_table(card) + "\n"
            f"![learned estimator]({png.name})\n\n"
            "AR captured / splat (gap ± SE) per ring:\n\n"
            + format_table(["cm", "views", "targets", "box diag px", *(LABELS[v] for v in VARIANTS)], table) + "\n\n"
            + (near_table + "\n" if near_table else "") + parts_table + "\n" + cost_table + "\n" + (scale_table + "\n" if scale_table else "")
            + (patch_table + "\n" if patch_table else "") + (precision_table + "\n" if precision_table else "")
            + (distance_table + "\n" if distance_table else "")
            + provenance(m) + "\n" + nan_note(dropped, "plotted learned-estimator values"))
    return RenderedSection(TITLE, body, advice_learned(rows, card) + near_advice + parts_advice + cost_advice
                           + scale_advice + patch_advice + precision_advice + distance_advice, [png])


def advice_learned(rows: list[dict[str, Any]], card: Mapping[str, Any]) -> str:
    """Where the learned estimator can be trusted on the splat, and what depth buys it."""
    ok = [r for r in rows if r["targets"]]
    if not ok:
        return ""
    main = "true_box_depth"
    worst = max(ok, key=lambda r: abs(num(r[f"gap_{main}"])) if math.isfinite(num(r[f"gap_{main}"])) else -1.0)
    large = [r for r in ok for v in VARIANTS if math.isfinite(num(r[f"gap_{v}"])) and abs(r[f"gap_{v}"]) >= LARGE_GAP]
    near, far = ok[0], ok[-1]
    text = (f"**Learned estimator:** given true boxes and depth its AR runs {fmt(near[f'real_{main}'], 2)} at "
            f"{fmt(near['distance_m'] * 100, 0)} cm to {fmt(far[f'real_{main}'], 2)} at {fmt(far['distance_m'] * 100, 0)} cm "
            f"on captured frames; the largest captured - splat gap (true box, + depth) is {fmt(worst[f'gap_{main}'], 2)} "
            f"at {fmt(worst['distance_m'] * 100, 0)} cm")
    if large:
        cells = sorted({f"{fmt(r['distance_m'] * 100, 0)} cm" for r in large})
        text += f"; some variant's gap reaches {fmt(LARGE_GAP, 2)} or more at {', '.join(cells)}: splat scores of the learned agents are least trustworthy there"
    else:
        text += f"; no ring or variant has a gap of {fmt(LARGE_GAP, 2)} or more, so the learned agents' splat scores stand in for captured ones"
        se = num(worst[f"gap_se_{main}"])
        if math.isfinite(se) and abs(num(worst[f"gap_{main}"])) + 2.0 * se >= LARGE_GAP:
            text += f" (within two standard errors, ±{fmt(2.0 * se, 2)}, the largest could still reach {fmt(LARGE_GAP, 2)})"
    rgb, depth = mean([r["real_true_box_rgb"] for r in ok]), mean([r[f"real_{main}"] for r in ok])
    text += f". Depth lifts its captured-frame AR from {fmt(rgb, 2)} (RGB only) to {fmt(depth, 2)}."
    held = num((card.get("heldout") or {}).get("pose_ar", {}).get(main))
    if math.isfinite(held) and math.isfinite(depth):
        text += f" On held-out synthetic images the same model scores {fmt(held, 2)} (true box, + depth): "
        text += ("the synthetic -> scene gap is what holds it down on captured frames; `brave6d synth`'s randomisation "
                 "is where to close it" if held - depth >= LARGE_GAP else
                 "captured frames cost it no more than the synthetic ones, so its own accuracy (training images and "
                 "steps, below) limits it, not the synthetic -> scene gap")
        text += "."
    return text


class LearnedSection:
    """Section 10 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> LearnedSweep:
        """Full: up to 12 held-out and 3 training views per ring at the captured size; quick: one
        held-out view per ring at half the size."""
        if quick:
            return LearnedSweep(holdout_per_level=1, train_per_level=0, stride=2)
        return LearnedSweep()

    def measure(self, inputs: MeasureInputs, settings: LearnedSweep) -> Measurement:
        return measure_learned(inputs, settings)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        m = measurements.get(NAME)
        evaluation = m.summary.get("evaluation") if m is not None else None
        played = read_played(Path(str(evaluation))) if evaluation else []
        cost = m.summary.get("cost") if m is not None else None
        if not cost:
            return render_learned(m, out_dir, played=played)
        folder = Path(str(cost)).parent
        return render_learned(m, out_dir, read_cost(Path(str(cost))), read_benchmark_rows(folder / DETECT_SCALE_FILE),
                              read_benchmark_rows(folder / DETECTOR_PATCH_FILE),
                              read_benchmark_rows(folder / PRECISION_FILE),
                              read_benchmark_rows(folder / RGB_DISTANCE_FILE), played)


SECTION = LearnedSection()

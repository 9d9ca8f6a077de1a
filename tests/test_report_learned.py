"""Report section 10 (the learned estimator): per-ring captured vs splat AR and its gap, the four
ways a target is estimated with their refusal causes, the held-out table from the card and the
cost table from ``benchmarks/learned_cost.py``'s JSON. The real measurement on a trained model is
the quick demo's (tests/test_demo_e2e.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.evaluation.report.measurements import Measurement
from brave6d.evaluation.report.sections.learned import COST_FILE, DETECT_SCALE_FILE, DETECTOR_PATCH_FILE, PRECISION_FILE, \
    RGB_DISTANCE_FILE, VARIANTS, best_detections, \
    cost_path, estimate_target, read_benchmark_rows, read_cost
from brave6d.evaluation.report.sections.learned import render_learned
from brave6d.evaluation.report.sections.learned import ring_rows, xywh_to_box

MACHINE = {"cpu": "Test CPU", "cores": 2, "gpu": None, "device": "cpu", "torch": "2.13.0", "torch_threads": 2}


def _point(level: int, d: float, real: float, splat: float, n: int = 2) -> dict:
    return {"id": f"im{level}", "im_id": level, "level": level, "distance_m": d, "holdout": True, "render_s": 0.1,
            "objects": [{"obj_id": 1, "object": "cup", "visib_fract": 1.0, "bbox_diag_px": 400 * (1 - d),
                         **{f"real_{v}_ar": real for v in VARIANTS}, **{f"splat_{v}_ar": splat for v in VARIANTS},
                         **{f"{s}_{v}_cause": None for s in ("real", "splat") for v in VARIANTS}}] * n}


def _measurement(points: list[dict], card: dict | None = None) -> Measurement:
    return Measurement(name="learned", key={"t": 1}, settings={"views": len(points)}, machine=MACHINE,
                       status="complete", points=points, summary={"card": card or {}, "model": "/x/model"},
                       seconds=1.0)


def test_ring_rows_give_captured_splat_and_the_gap_per_ring() -> None:
    rows = ring_rows([_point(0, 0.2, 0.8, 0.5), _point(1, 0.5, 0.4, 0.4)])
    assert [r["distance_m"] for r in rows] == [0.2, 0.5]
    for v in VARIANTS:
        assert math.isclose(rows[0][f"gap_{v}"], 0.3) and rows[1][f"gap_{v}"] == 0.0
        assert rows[0][f"real_{v}"] == 0.8 and rows[0][f"splat_{v}"] == 0.5
    assert rows[0]["targets"] == 2 and rows[0]["bbox_diag_px"] == pytest.approx(320.0)


def test_objects_the_model_never_saw_are_no_targets_of_the_rings() -> None:
    p = _point(0, 0.3, 0.6, 0.6)
    p["objects"].append({"obj_id": 9, "object": "new", "note": "object 9 was not in the model's training split"})
    assert ring_rows([p])[0]["targets"] == 2


def test_page_names_large_gaps_the_heldout_table_and_the_cost(tmp_path: Path) -> None:
    card = {"images": 300, "train_seconds": 600.0, "device": "cpu",
            "heldout": {"images": 30, "instances": 70, "detection_recall_iou50": {"1": 0.9},
                        "detection_ap_iou50": {"1": 0.85}, "pose_ar": {v: 0.6 for v in VARIANTS},
                        "pose_ar_per_object": {v: {"1": 0.6} for v in VARIANTS}}}
    cost = {"synth_images_per_s": 1.5, "points": [
        {"images": 100, "steps": 300, "synth_s": 66.0, "train_s": 200.0, "recall_min": 0.4,
         "heldout_ar": {v: 0.3 for v in VARIANTS}, "agents": {"learned-static-depth": 0.3, "learned-active-depth": 0.35}},
        {"images": 300, "steps": 1000, "synth_s": 200.0, "train_s": 600.0, "recall_min": 0.7,
         "heldout_ar": {v: 0.6 for v in VARIANTS}, "agents": {"learned-static-depth": 0.55, "learned-active-depth": 0.6}}]}
    section = render_learned(_measurement([_point(0, 0.2, 0.8, 0.5), _point(1, 0.5, 0.4, 0.4)], card), tmp_path, cost)
    assert (tmp_path / "learned.png").is_file()
    assert "| 1   | 0.90       | 0.85" in section.body  # the card's held-out row
    assert "0.80 / 0.50 (0.30 ±" in section.body  # captured / splat (gap) at 20 cm
    assert "gap reaches 0.10 or more at 20 cm" in section.advice and "50 cm" not in section.advice.split("or more at")[1].split(":")[0]
    assert "| 300    | 1000" in section.body and "1.50 images/s" in section.body
    assert "came from 300 images x 1000 steps (800 s" in section.advice
    no_cost = render_learned(_measurement([_point(0, 0.2, 0.6, 0.6)]), tmp_path, None)
    assert "not measured for this work directory yet" in no_cost.body
    assert "no ring or variant has a gap of 0.10 or more" in no_cost.advice


def test_cost_file_is_read_only_when_it_has_points(tmp_path: Path) -> None:
    path = cost_path(tmp_path / "learned" / "model")
    assert path == tmp_path / COST_FILE
    assert read_cost(path) is None
    path.parent.mkdir(parents=True)
    path.write_text("{not json")
    assert read_cost(path) is None
    path.write_text(json.dumps({"points": "none"}))
    assert read_cost(path) is None
    path.write_text(json.dumps({"points": []}))
    assert read_cost(path) == {"points": []}


def _scale_row(scales: list[float], widths: list[int], recall: list[float], ms: float) -> dict:
    return {"scales": scales, "detect_widths": widths, "recall": {str(i + 1): r for i, r in enumerate(recall)},
            "ap": {str(i + 1): r - 0.05 for i, r in enumerate(recall)}, "recall_min": min(recall),
            "detected_ar": {"detected_rgb": 0.2, "detected_depth": 0.55}, "detect_ms": ms, "refine_ms": 7.0}


def test_the_detector_width_table_and_advice_come_from_the_benchmark_file(tmp_path: Path) -> None:
    path = tmp_path / DETECT_SCALE_FILE
    assert read_benchmark_rows(path) is None
    path.write_text("[]")
    assert read_benchmark_rows(path) is None
    path.write_text(json.dumps({"rows": [_scale_row([1.0], [320], [0.8, 0.75], 27.0),
                                         _scale_row([1.0, 1.375], [320, 440], [0.9, 0.86], 70.0)]}))
    rows = read_benchmark_rows(path)
    assert rows is not None and len(rows) == 2
    m = _measurement([_point(0, 0.2, 0.6, 0.6)])
    m.summary["detect_widths"] = [320, 440]
    section = render_learned(m, tmp_path, None, rows)
    assert "the estimator detects at 320 + 440 px" in section.body and "0.90 / 0.86" in section.body
    assert "320 + 440 px give the best worst-object recall (0.86) for 70.0 ms" in section.advice
    assert "the cheapest, 320 px, 0.75 for 27.0 ms" in section.advice
    without = render_learned(_measurement([_point(0, 0.2, 0.6, 0.6)]), tmp_path, None, None)
    assert "input widths" not in without.body and "Detector widths" not in without.advice


def _patch_row(patch: int, steps: int, seconds: float, recall: list[float]) -> dict:
    return {"patch": patch, "steps": steps, "detector_s": seconds, "steps_per_s": steps / seconds,
            "recall": {str(i + 1): r for i, r in enumerate(recall)}, "recall_min": min(recall),
            "ap": {str(i + 1): r - 0.05 for i, r in enumerate(recall)},
            "detected_ar": {"detected_rgb": 0.2, "detected_depth": 0.58}}


def test_the_detector_patch_table_and_advice_come_from_the_benchmark_file(tmp_path: Path) -> None:
    path = tmp_path / DETECTOR_PATCH_FILE
    path.write_text(json.dumps({"rows": [_patch_row(128, 1200, 283.0, [0.83, 0.75]),
                                         _patch_row(96, 1900, 285.0, [0.86, 0.81]),
                                         _patch_row(96, 2100, 310.0, [0.88, 0.81])]}))
    played = json.loads(path.read_text())
    played["rows"][0]["agents"] = {"learned-static": 0.2, "learned-active": 0.28, "learned-static-depth": 0.5,
                                   "learned-active-depth": 0.61}
    played["rows"][1]["agents"] = {"learned-static": 0.15, "learned-active": 0.19, "learned-static-depth": 0.41,
                                   "learned-active-depth": 0.5}
    rows = read_benchmark_rows(path)
    m = _measurement([_point(0, 0.2, 0.6, 0.6)])
    m.summary["card"] = {"preset": {"detector_patch": 96, "detector_steps": 1900}}
    section = render_learned(m, tmp_path, None, None, rows)
    assert "this model trained 96 px x 1900 steps" in section.body
    assert any(line.replace(" ", "").startswith("|96|2100|310|") for line in section.body.splitlines())
    assert "96 px x 1900 steps give the best worst-object recall (0.81) in 285 s" in section.advice
    assert "the quickest, 128 px x 1200 steps, 0.75 in 283 s" in section.advice
    assert "training patches" not in render_learned(m, tmp_path, None, None, None).body
    assert "As agents" not in section.advice
    path.write_text(json.dumps(played))
    with_agents = render_learned(m, tmp_path, None, None, read_benchmark_rows(path))
    assert "0.200 / 0.280 (0.500 / 0.610)" in with_agents.body
    assert "As agents, 128 px x 1200 steps give learned-active-depth the best AR (0.610)" in with_agents.advice


def _precision_row(precision: str, steps: tuple[int, int], seconds: float, recall: list[float], ar_depth: float) -> dict:
    return {"point": f"{precision}:{steps[0]}:{steps[1]}", "precision": precision, "detector_steps": steps[0],
            "pose_steps": steps[1], "train_s": seconds,
            "recall": {str(i + 1): r for i, r in enumerate(recall)}, "recall_min": min(recall),
            "ap": {str(i + 1): r - 0.05 for i, r in enumerate(recall)},
            "detected_ar": {"detected_rgb": 0.2, "detected_depth": ar_depth},
            "pose_ar": {"true_box_rgb": 0.25, "true_box_depth": 0.7, "detected_rgb": 0.2, "detected_depth": ar_depth}}


def test_the_precision_table_and_advice_come_from_the_benchmark_file(tmp_path: Path) -> None:
    path = tmp_path / PRECISION_FILE
    path.write_text(json.dumps({"rows": [_precision_row("fp32", (1200, 1000), 111.0, [0.88, 0.75], 0.573),
                                         _precision_row("bf16", (1200, 1000), 74.0, [0.82, 0.74], 0.569),
                                         _precision_row("bf16", (2400, 2000), 128.0, [0.84, 0.91], 0.716)]}))
    m = _measurement([_point(0, 0.2, 0.6, 0.6)])
    m.summary["card"] = {"preset": {"precision": "bf16", "detector_steps": 2400, "pose_steps": 2000}}
    section = render_learned(m, tmp_path, None, None, None, read_benchmark_rows(path))
    assert "this model trained bf16 x 2400 + 2000 steps" in section.body
    assert any(line.replace(" ", "").startswith("|bf16|2400+2000|128|0.250|0.700|") for line in section.body.splitlines())
    assert "bf16 x 2400 + 2000 steps gives the best AR given detected boxes with depth (0.716" in section.advice
    assert "the quickest, bf16 x 1200 + 1000 steps, 0.569 (0.74) in 74 s" in section.advice
    assert "At the same steps bf16 trains in 0.67x fp32's time" in section.advice
    without = render_learned(m, tmp_path, None, None, None, None)
    assert "Training precision" not in without.body and "At the same steps" not in without.advice



def _distance_row(setting: str, true_rgb: float, ms: float, agents: dict | None = None) -> dict:
    row = {"setting": setting, "ms_per_estimate": ms,
           "pose_ar": {"true_box_rgb": true_rgb, "true_box_depth": 0.87, "detected_rgb": true_rgb - 0.01,
                       "detected_depth": 0.8},
           "true_box_rgb": {"ar": true_rgb, "vsd": 0.15, "mssd": 0.17, "mspd": 0.87,
                            "ceilings": {"true distance": 0.655, "distance 1% off": 0.6}}}
    return row | ({"agents": agents} if agents else {})


def test_the_rgb_distance_table_and_advice_come_from_the_benchmark_file(tmp_path: Path) -> None:
    path = tmp_path / RGB_DISTANCE_FILE
    agents = {"learned-static": 0.3, "learned-active": 0.5, "learned-static-depth": 0.6, "learned-active-depth": 0.7}
    path.write_text(json.dumps({"rows": [_distance_row("pnp", 0.396, 16.6), _distance_row("mask-area", 0.459, 19.5, agents),
                                         _distance_row("mask-area, 3 zooms", 0.489, 29.5)]}))
    m = _measurement([_point(0, 0.2, 0.6, 0.6)])
    section = render_learned(m, tmp_path, None, None, None, None, read_benchmark_rows(path))
    assert any(line.replace(" ", "").startswith("|mask-area|0.459(0.150/0.170/0.870)|0.449|19.5|0.300/0.500(0.600/0.700)|")
               for line in section.body.splitlines())
    assert "true distance 0.655, distance 1% off 0.600" in section.body
    assert "changes AR given true boxes by +0.063 (0.396 -> 0.459) for +2.9 ms per estimate: keep it on" in section.advice
    assert ("Three zooms of each box under one PnP change it by +0.030 (given detected boxes +0.030, with depth "
            "+0.000) for +10.0 ms per estimate: keep them") in section.advice
    assert "with it 1 % off 0.600: what is left between that and AR is the RGB-only distance" in section.advice
    path.write_text(json.dumps({"rows": [_distance_row("pnp", 0.46, 16.6), _distance_row("mask-area", 0.44, 19.5),
                                         _distance_row("mask-area, 3 zooms", 0.43, 29.5)]}))
    worse = render_learned(m, tmp_path, None, None, None, None, read_benchmark_rows(path))
    assert "by -0.020" in worse.advice and "it does not pay here" in worse.advice
    assert "change it by -0.010" in worse.advice and "they do not pay here" in worse.advice
    without = render_learned(m, tmp_path, None, None, None, None, None)
    assert "RGB-only pose" not in without.body and "mask's area changes" not in without.advice

@given(st.lists(st.floats(-1e6, 1e6), min_size=4, max_size=4), st.integers(1, 8))
@settings(max_examples=200, deadline=None)
def test_true_box_is_finite_and_ordered_or_none(bbox: list[float], stride: int) -> None:
    box = xywh_to_box(bbox, stride)
    if bbox[2] <= 0 or bbox[3] <= 0:
        assert box is None
    if box is not None:  # a box the estimator gets is finite with an area
        assert all(math.isfinite(b) for b in box) and box[2] > box[0] and box[3] > box[1]
    if min(bbox[2], bbox[3]) >= 1.0 and max(abs(v) for v in bbox) < 1e5:  # any pixel-sized box is kept
        assert box is not None


class _Estimator:
    """An estimator whose detector finds nothing and whose pose net refuses object 2: the section
    must record each variant's cause and give no pose where refused."""

    obj_ids = [1, 2]

    def detect(self, rgb: np.ndarray, K: np.ndarray) -> list:
        return []

    def refine_box(self, rgb: np.ndarray, K: np.ndarray, det: object) -> object:
        raise AssertionError("nothing was detected, so nothing is refined")

    def estimate_both(self, rgb: np.ndarray, K: np.ndarray, obj_id: int, box: tuple, depth: object,
                      score: float) -> tuple:
        from types import SimpleNamespace

        from brave6d.evaluation.learned import LearnedRefused

        if obj_id == 2:
            raise LearnedRefused("pnp-failed", "too few correspondences")
        rgb_pose = SimpleNamespace(cam_T_obj=np.eye(4), score=score)
        return rgb_pose, (None if depth is None else SimpleNamespace(cam_T_obj=2 * np.eye(4), score=score))


def test_each_variant_records_its_refusal_cause_and_no_pose() -> None:
    rgb, K, depth = np.zeros((40, 64, 3), np.uint8), np.eye(3), np.ones((40, 64), np.float32)
    found = best_detections(_Estimator(), rgb, K, [1, 2])
    assert found == {1: "no-detection", 2: "no-detection"}
    out = estimate_target(_Estimator(), rgb, depth, K, 1, (1.0, 1.0, 10.0, 10.0), found[1])
    assert out["detected_rgb"][1] == out["detected_depth"][1] == "no-detection"
    assert out["true_box_rgb"][1] is None and out["true_box_depth"][1] is None
    assert out["true_box_rgb"][0].cam_T_obj[0, 0] == 1.0 and out["true_box_depth"][0].cam_T_obj[0, 0] == 2.0
    refused = estimate_target(_Estimator(), rgb, depth, K, 2, (1.0, 1.0, 10.0, 10.0), found[2])
    assert refused["true_box_rgb"][1] == refused["true_box_depth"][1] == "pnp-failed"
    assert refused["true_box_depth"][0].cam_T_obj is None
    assert estimate_target(_Estimator(), rgb, None, K, 1, None, "no-detection")["true_box_depth"][1] == "no-box"


def test_missing_model_is_named_where_the_report_was_told_to_look(tmp_path: Path) -> None:
    """A dataset's scenes share ``WORKDIR/learned/model``; the demo's is ``<workdir>/learned/model``."""
    from brave6d.core.layout import SceneDir
    from brave6d.evaluation.report.measurements import MeasurementStore
    from brave6d.evaluation.report.protocol import MeasureInputs
    from brave6d.evaluation.report.sections.learned import LearnedSweep, measure_learned

    store = MeasurementStore(tmp_path / "measurements")
    shared = tmp_path / "dataset" / "learned" / "model"
    m = measure_learned(MeasureInputs(tmp_path, SceneDir(tmp_path / "scene"), store, shared), LearnedSweep())
    assert m.status == "missing" and str(shared / "model.pt") in m.note
    demo = measure_learned(MeasureInputs(tmp_path, SceneDir(tmp_path / "scene"), store), LearnedSweep())
    assert str(tmp_path / "learned" / "model" / "model.pt") in demo.note


def test_advice_tells_a_domain_gap_from_a_weak_model() -> None:
    from brave6d.evaluation.report.sections.learned import advice_learned

    rows = ring_rows([_point(0, 0.2, 0.4, 0.4), _point(1, 0.5, 0.4, 0.4)])
    card = {"heldout": {"pose_ar": {"true_box_depth": 0.75}}}
    assert "the synthetic -> scene gap is what holds it down" in advice_learned(rows, card)
    card["heldout"]["pose_ar"]["true_box_depth"] = 0.45
    assert "its own accuracy (training images and steps, below) limits it" in advice_learned(rows, card)
    assert "On held-out" not in advice_learned(rows, {})


def _metric_point(level: int, d: float, splat: dict[str, float], n: int = 3) -> dict:
    p = _point(level, d, 0.5, sum(splat.values()) / 3, n)
    p["objects"] = [dict(o) for o in p["objects"]]  # one dict per target (_point repeats one)
    for o in p["objects"]:
        o.update({f"{side}_true_box_rgb_{k}": v for side in ("real", "splat") for k, v in splat.items()})
    return p


def test_the_page_says_why_ar_moves_with_distance_and_whether_near_beats_far(tmp_path: Path) -> None:
    points = [_metric_point(0, 0.2, {"vsd": 0.6, "mssd": 0.6, "mspd": 0.7}),
              _metric_point(1, 0.5, {"vsd": 0.3, "mssd": 0.3, "mspd": 0.9})]
    for o in points[0]["objects"][:1]:
        o["splat_true_box_rgb_ar"] = 0.7  # a spread, so the rings' SEs are finite
    section = render_learned(_measurement(points), tmp_path)
    assert "| 20 | 3       | 0.656 (0.500) | 0.60 (0.60) | 0.60 (0.60) | 0.70 (0.70) |" in section.body  # per ring:
    assert "| 50 | 3       | 0.500 (0.500) | 0.30 (0.30) | 0.30 (0.30) | 0.90 (0.90) |" in section.body  # AR, its metrics
    assert ("Coming closer, RGB-only given true boxes on the splat: AR 0.656 at 20 cm against 0.500 at 50 cm "
            "(+0.156 ± 0.022, resolved at two standard errors)") in section.advice


def test_the_page_gives_each_active_part_alone_paired_by_start_and_says_what_is_not_resolved(tmp_path: Path) -> None:
    from brave6d.evaluation.report.sections.learned import ablation_rows

    def played(agent: str, gains: list[float]) -> list:
        return [(agent, ("s", i % 4, i % 4 + 1, i), 0.4 + g) for i, g in enumerate(gains)]

    starts = 24
    episodes = (played("learned-static", [0.0] * starts) + played("learned-active", [0.12 + 0.02 * (i % 3) for i in range(starts)])
                + played("learned-active-closeness", [0.1] * starts)
                + played("learned-active-selection", [0.3 * ((-1) ** i) for i in range(starts)])
                + played("learned-active-fusion", [0.01] * 4)  # only four starts
                + played("learned-static-depth", [0.4] * starts) + played("learned-active-depth", [0.42] * starts))
    rows = {r["agent"]: r for r in ablation_rows(episodes)}
    assert rows["learned-active"]["verdict"].startswith("resolved") and rows["learned-active"]["pairs"] == starts
    assert rows["learned-active-closeness"]["mean"] == pytest.approx(0.1)
    assert rows["learned-active-selection"]["verdict"].startswith("not resolved")
    assert rows["learned-active-fusion"]["pairs"] == 4
    # with depth the claimed gain is +0.05: +0.02 everywhere is resolved as a difference but not as the claim
    assert "not resolved" in rows["learned-active-depth"]["verdict"]
    section = render_learned(_measurement([_point(0, 0.2, 0.6, 0.6)]), tmp_path, played=episodes)
    assert "learned-active-closeness | closeness" in section.body
    assert "learned-active gains +0.140 ± 0.003 over learned-static" in section.advice
    assert "alone, closeness buys the most (+0.100)" in section.advice
    empty = render_learned(_measurement([_point(0, 0.2, 0.6, 0.6)]), tmp_path)
    assert "no paired episodes of the learned agents" in empty.body


def test_the_ablation_reads_both_leaderboards_of_the_evaluation(tmp_path: Path) -> None:
    import json as _json

    from brave6d.evaluation.report.sections.learned import ablation_rows, read_played

    def rows(agent: str, ar: float) -> list[dict]:
        return [{"agent": agent, "scene": "demo", "target_gt_id": g, "obj_id": g + 1, "seed": g, "ar": ar + 0.1 * g}
                for g in range(4)]

    (tmp_path / "ablation").mkdir(parents=True)
    (tmp_path / "leaderboard.json").write_text(_json.dumps({"episodes": rows("learned-static", 0.2)
                                                            + rows("learned-active", 0.3)}))
    (tmp_path / "ablation" / "leaderboard.json").write_text(_json.dumps({"episodes": rows("learned-active-closeness", 0.25)}))
    by_agent = {r["agent"]: r for r in ablation_rows(read_played(tmp_path))}
    assert by_agent["learned-active"]["pairs"] == 4 and abs(by_agent["learned-active-closeness"]["mean"] - 0.05) < 1e-9
    assert read_played(tmp_path / "absent") == []

"""BOP19 Average Recall: targets, greedy matching, recall per threshold, AR per metric and overall."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.core.errors import DataError
from brave6d.evaluation.metrics.recall import (
    EvalConfig,
    Estimate,
    GTInstance,
    ObjectModel,
    evaluate_bop19,
    greedy_match,
)
from brave6d.evaluation.metrics.depth_renderer import DepthRenderer

W, H = 640, 480
K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
I3 = np.eye(3)


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def flat4(R: np.ndarray) -> list[float]:
    T = np.eye(4)
    T[:3, :3] = R
    return T.reshape(-1).tolist()


@pytest.fixture(scope="module")
def models() -> dict[int, ObjectModel]:
    """1: hexagonal nut (60 deg symmetries), 2: cylinder (continuous symmetry), 3: cube, no symmetry."""
    nut = trimesh.creation.cylinder(radius=10.0, height=8.0, sections=6)
    cyl = trimesh.creation.cylinder(radius=20.0, height=40.0, sections=96)
    box = trimesh.creation.box(extents=(30.0, 30.0, 30.0))
    return {
        1: ObjectModel.from_models_info(1, nut.vertices, {
            "diameter": math.hypot(20.0, 8.0),
            "symmetries_discrete": [flat4(rot("z", 60 * k)) for k in range(1, 6)],
        }, nut.faces),
        2: ObjectModel.from_models_info(2, cyl.vertices, {
            "diameter": 50.0,  # declared (the true one is 56.6): thresholds use the declared value
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
        }, cyl.faces),
        3: ObjectModel.from_models_info(3, box.vertices, {"diameter": math.sqrt(3) * 30.0}, box.faces),
    }


@pytest.fixture(scope="module")
def renderer(models) -> DepthRenderer:
    r = DepthRenderer()
    for obj_id, m in models.items():
        r.add_object(obj_id, m.points, m.faces)
    return r


# Ground-truth poses of one test image: (obj_id, R, t mm).
POSES = [
    (1, rot("x", 30) @ rot("z", 10), np.array([-60.0, 20.0, 400.0])),
    (2, rot("x", 60), np.array([40.0, -10.0, 500.0])),
    (3, rot("y", 25) @ rot("x", 15), np.array([60.0, 60.0, 450.0])),
]


def make_gts(renderer, poses=POSES, scene_id=1, im_id=0, visib=None, K_=K, size=(W, H)) -> list[GTInstance]:
    depth = np.full((size[1], size[0]), np.inf)
    for obj_id, R, t in poses:
        d = renderer.render(obj_id, R, t, K_, size[0], size[1])
        depth = np.where((d > 0) & (d < depth), d, depth)
    depth = np.where(np.isfinite(depth), depth, 1000.0)  # table behind the objects
    visib = visib or [1.0] * len(poses)
    return [GTInstance(scene_id, im_id, o, R, t, v, K_, size, depth) for (o, R, t), v in zip(poses, visib)]


def exact_estimates(gts, score=1.0) -> list[Estimate]:
    return [Estimate(g.scene_id, g.im_id, g.obj_id, score, g.R, g.t, 0.25) for g in gts]


# ----------------------------------------------------------------------------- matching
def test_greedy_match_follows_score_order():
    # Estimates are already in descending score order; one GT.
    m = greedy_match([[[0.3]], [[0.1]]], [0.5])
    np.testing.assert_array_equal(m, [[0], [-1]])  # the first (higher score) takes it


def test_greedy_match_lowest_error_and_per_threshold():
    err = np.array([[[0.1, 0.1], [0.2, 0.2]], [[0.15, 0.15], [0.9, 0.9]]])  # (E=2, G=2, T=2)
    m = greedy_match(err, [0.5, 1.0])
    np.testing.assert_array_equal(m, [[0, 0], [-1, 1]])  # est 1 gets GT 1 only when 0.9 < th
    # Strictly below the threshold.
    np.testing.assert_array_equal(greedy_match([[[0.5]]], [0.5]), [[-1]])
    # Ties: the lower GT index wins; NaN never matches.
    np.testing.assert_array_equal(greedy_match([[[0.2], [0.2]]], [0.5]), [[0]])
    np.testing.assert_array_equal(greedy_match([[[np.nan], [0.3]]], [0.5]), [[1]])
    assert greedy_match(np.zeros((2, 0, 3)), [1, 2, 3]).tolist() == [[-1] * 3] * 2


def _reference_match(errors: np.ndarray, th: float) -> list[int]:
    """The matching rule written out literally for one threshold (errors: E x G)."""
    matched: set[int] = set()
    out = []
    for row in errors:
        best, best_err = -1, th
        for g, e in enumerate(row):
            if g not in matched and e < best_err:
                best, best_err = g, e
        if best >= 0:
            matched.add(best)
        out.append(best)
    return out


@given(
    errors=st.integers(0, 5).flatmap(lambda e: st.integers(0, 4).flatmap(lambda g: st.lists(
        st.lists(st.sampled_from([0.0, 0.1, 0.2, 0.3, 0.45, 0.5, 0.7, np.inf]), min_size=g, max_size=g),
        min_size=e, max_size=e).map(lambda rows: np.array(rows, dtype=float).reshape(e, g)))),
)
def test_greedy_match_equals_the_literal_rule(errors):
    ths = np.array([0.05, 0.1, 0.2, 0.3, 0.5, 1.0])
    got = greedy_match(np.repeat(errors[:, :, None], len(ths), axis=2), ths)
    for j, th in enumerate(ths):
        assert got[:, j].tolist() == _reference_match(errors, th)


# ----------------------------------------------------------------------------- AR
def test_exact_poses_score_one(models, renderer):
    gts = make_gts(renderer)
    res = evaluate_bop19(gts, exact_estimates(gts), models, renderer=renderer)
    assert res.ar == 1.0 and res.ar_vsd == 1.0 and res.ar_mssd == 1.0 and res.ar_mspd == 1.0
    assert res.n_targets == 3 and res.n_estimates_evaluated == 3
    assert res.metrics["vsd"].recall.shape == (10, 10)
    assert np.all(res.metrics["vsd"].recall == 1.0)
    assert {k: v.ar for k, v in res.per_object.items()} == {1: 1.0, 2: 1.0, 3: 1.0}
    assert res.average_time_per_image == pytest.approx(0.25)
    for e in res.errors:
        assert np.all(e.vsd == 0) and np.all(e.mssd < 1e-9) and np.all(e.mspd < 1e-9)


def test_empty_result_scores_zero(models, renderer):
    gts = make_gts(renderer)
    res = evaluate_bop19(gts, [], models, renderer=renderer)
    assert res.ar == 0.0 and res.ar_vsd == 0.0 and res.ar_mssd == 0.0 and res.ar_mspd == 0.0
    assert res.n_targets == 3 and res.n_estimates_evaluated == 0
    assert res.average_time_per_image == -1.0


def test_no_targets_scores_zero_without_nan(models, renderer):
    gts = make_gts(renderer, visib=[0.05, 0.0, 0.09])
    res = evaluate_bop19(gts, exact_estimates(gts), models, renderer=renderer)
    assert res.n_targets == 0 and res.ar == 0.0 and res.n_estimates_evaluated == 0
    json.dumps(res.to_json(), allow_nan=False)


def test_instances_below_10_percent_visible_are_not_targets(models, renderer):
    gts = make_gts(renderer, visib=[1.0, 0.099, 0.1])
    res = evaluate_bop19(gts, exact_estimates(gts), models, renderer=renderer)
    assert res.n_targets == 2 and res.ar == 1.0
    assert set(res.per_object) == {1, 3}
    # Missing the barely visible one costs nothing; missing a target costs 1/2.
    res2 = evaluate_bop19(gts, exact_estimates(gts)[:1], models, renderer=renderer)
    assert res2.ar == pytest.approx(0.5)


def test_known_translation_offset(models, renderer):
    """Cylinder facing the camera, shifted 6 mm sideways: MSSD = 6 mm = 0.12 of the declared
    50 mm diameter (correct for 8 of 10 thresholds); MSPD = f * 6 / z_near = 600 * 6 / 480 =
    7.5 px (correct for 9 of 10 thresholds)."""
    t = np.array([0.0, 0.0, 500.0])
    gts = make_gts(renderer, poses=[(2, I3, t)])
    est = [Estimate(1, 0, 2, 1.0, I3, t + [6.0, 0.0, 0.0])]
    res = evaluate_bop19(gts, est, models, renderer=renderer)
    assert res.errors[0].mssd[0] == pytest.approx(6.0, rel=1e-9)
    assert res.errors[0].mspd[0] == pytest.approx(7.5, rel=1e-9)
    np.testing.assert_array_equal(res.metrics["mssd"].recall, [0, 0] + [1] * 8)
    np.testing.assert_array_equal(res.metrics["mspd"].recall, [0] + [1] * 9)
    assert res.ar_mssd == pytest.approx(0.8) and res.ar_mspd == pytest.approx(0.9)
    assert 0.0 < res.ar_vsd < 1.0
    assert res.ar == pytest.approx((0.8 + 0.9 + res.ar_vsd) / 3)


def test_mspd_is_scaled_to_640_px(models, renderer):
    """The same scene at twice the resolution: 15 px in the image, 7.5 px at 640 px width."""
    K2 = K.copy()
    K2[:2] *= 2.0
    K2[0, 2], K2[1, 2] = 639.5, 479.5
    t = np.array([0.0, 0.0, 500.0])
    gts = make_gts(renderer, poses=[(2, I3, t)], K_=K2, size=(1280, 960))
    res = evaluate_bop19(gts, [Estimate(1, 0, 2, 1.0, I3, t + [6.0, 0.0, 0.0])], models, renderer=renderer,
                         config=EvalConfig(metrics=("mspd",)))
    assert res.errors[0].mspd[0] == pytest.approx(15.0, rel=1e-9)
    assert res.ar_mspd == pytest.approx(0.9) and res.ar == res.ar_mspd and res.ar_vsd is None


def test_rotation_by_a_symmetry_scores_one(models, renderer):
    gts = make_gts(renderer)
    (o1, R1, t1), (o2, R2, t2), _ = POSES
    ests = [
        Estimate(1, 0, o1, 1.0, R1 @ rot("z", 240), t1),  # nut: 240 deg is a declared symmetry
        Estimate(1, 0, o2, 1.0, R2 @ rot("z", 37), t2),  # cylinder: any angle about its axis
    ]
    res = evaluate_bop19(gts[:2], ests, models, renderer=renderer)
    assert res.ar == 1.0
    # The same nut rotation with the symmetries left out is wrong for MSSD and MSPD.
    plain = dict(models)
    plain[1] = ObjectModel(1, models[1].points, models[1].diameter, models[1].faces)
    res2 = evaluate_bop19(gts[:1], ests[:1], plain, renderer=renderer)
    assert res2.ar_mssd == 0.0  # vertices moved 17.3 mm > 0.5 x 21.5 mm
    assert res2.errors[0].mspd[0] > 20.0 and res2.ar_mspd < 0.7


def test_far_off_and_depth_shifted_estimates(models, renderer):
    gts = make_gts(renderer)
    _, R3, t3 = POSES[2]
    far = evaluate_bop19(gts, [Estimate(1, 0, 3, 1.0, R3, t3 + [300.0, 0.0, 0.0])], models, renderer=renderer)
    assert far.ar == 0.0
    assert np.all(far.errors[0].vsd == 1.0) and far.errors[0].mssd[0] == math.inf  # BOP's shortcuts
    deep = evaluate_bop19(gts, [Estimate(1, 0, 3, 1.0, R3, t3 + [0.0, 0.0, 40.0])], models, renderer=renderer)
    assert deep.ar_vsd == 0.0 and deep.ar_mssd == 0.0
    assert deep.errors[0].vsd.min() > 0.9


def test_score_order_and_duplicates(models, renderer):
    gts = make_gts(renderer)[2:]  # the cube only: one target
    g = gts[0]
    wrong = Estimate(1, 0, 3, 0.9, g.R, g.t + [0.0, 200.0, 0.0])
    right = Estimate(1, 0, 3, 0.5, g.R, g.t)
    # BOP19 evaluates as many estimates per object as it has targets (n_top = -1): the top one.
    res = evaluate_bop19(gts, [right, wrong], models, renderer=renderer)
    assert res.ar == 0.0 and res.n_estimates_evaluated == 1
    assert evaluate_bop19(gts, [Estimate(1, 0, 3, 0.95, g.R, g.t), wrong], models, renderer=renderer).ar == 1.0
    # With all estimates considered, the wrong one matches nothing and the right one matches.
    assert evaluate_bop19(gts, [right, wrong], models, renderer=renderer, config=EvalConfig(n_top=0)).ar == 1.0


def test_duplicates_on_one_of_two_instances(models, renderer):
    t_a, t_b = np.array([-50.0, 0.0, 450.0]), np.array([50.0, 0.0, 450.0])
    gts = make_gts(renderer, poses=[(3, I3, t_a), (3, I3, t_b)])
    dup = [Estimate(1, 0, 3, 0.8, I3, t_a), Estimate(1, 0, 3, 0.7, I3, t_a)]
    res = evaluate_bop19(gts, dup, models, renderer=renderer)
    assert res.n_targets == 2 and res.n_estimates_evaluated == 2
    assert res.ar == pytest.approx(0.5)  # one GT matched once; the duplicate finds no free GT
    both = evaluate_bop19(gts, [Estimate(1, 0, 3, 0.2, I3, t_b), dup[0]], models, renderer=renderer)
    assert both.ar == 1.0


def test_estimates_without_targets_are_ignored(models, renderer):
    gts = make_gts(renderer)
    extra = [Estimate(1, 0, 99, 1.0, I3, [0, 0, 500.0]), Estimate(7, 3, 1, 1.0, I3, [0, 0, 500.0])]
    res = evaluate_bop19(gts, exact_estimates(gts) + extra, models, renderer=renderer)
    assert res.ar == 1.0 and res.n_estimates == 5 and res.n_estimates_evaluated == 3


def test_multiple_images_and_per_object_breakdown(models, renderer):
    gts0 = make_gts(renderer, im_id=0)
    gts1 = make_gts(renderer, im_id=1)
    ests = exact_estimates(gts0) + exact_estimates(gts1)[:1]  # image 1: only the nut is found
    res = evaluate_bop19(gts0 + gts1, ests, models, renderer=renderer)
    assert res.n_images == 2 and res.n_targets == 6
    assert res.ar == pytest.approx(4 / 6)
    assert res.per_object[1].ar == 1.0 and res.per_object[2].ar == pytest.approx(0.5)
    assert res.per_object[3].n_targets == 2
    assert "AR_VSD" in res.table()


def test_to_json_round_trip(models, renderer, tmp_path):
    gts = make_gts(renderer)
    res = evaluate_bop19(gts, exact_estimates(gts)[:2], models, renderer=renderer)
    path = atomic_write_json(tmp_path / "scores.json", res.to_json())
    data = read_json(path)
    assert data["ar"] == pytest.approx(2 / 3)
    assert data["per_metric"]["vsd"]["recall"][0][0] == pytest.approx(2 / 3)
    assert data["per_object"]["3"]["ar"] == 0.0
    assert len(data["per_metric"]["mspd"]["thresholds"]) == 10


def test_input_errors(models, renderer):
    gts = make_gts(renderer)
    with pytest.raises(DataError, match="no object model"):
        evaluate_bop19(gts, exact_estimates(gts), {1: models[1]}, renderer=renderer)
    no_depth = [GTInstance(g.scene_id, g.im_id, g.obj_id, g.R, g.t, g.visib_fract, g.K, g.image_size) for g in gts]
    with pytest.raises(DataError, match="depth"):
        evaluate_bop19(no_depth, exact_estimates(gts), models)
    # Without VSD no depth is needed.
    assert evaluate_bop19(no_depth, exact_estimates(gts), models, config=EvalConfig(metrics=("mssd", "mspd"))).ar == 1.0
    with pytest.raises(DataError, match="disagree"):
        evaluate_bop19([gts[0], GTInstance(1, 0, 2, I3, [0, 0, 500.0], 1.0, K * 2, (W, H))], [], models)
    with pytest.raises(DataError, match="score"):
        Estimate(1, 0, 1, float("nan"), I3, [0, 0, 1])
    with pytest.raises(DataError, match="diameter"):
        ObjectModel(1, np.zeros((3, 3)), 0.0)
    with pytest.raises(ValueError):
        EvalConfig(metrics=("add",))


def test_depth_loader_is_called_once_per_image(models, renderer):
    gts = make_gts(renderer)
    calls = []
    depth = gts[0].depth

    def loader():
        calls.append(1)
        return depth

    lazy = [GTInstance(g.scene_id, g.im_id, g.obj_id, g.R, g.t, g.visib_fract, g.K, g.image_size, loader) for g in gts]
    assert evaluate_bop19(lazy, exact_estimates(gts), models, renderer=renderer).ar == 1.0
    assert len(calls) == 1
    evaluate_bop19(lazy, [], models, renderer=renderer)
    assert len(calls) == 1  # no estimate, no depth needed


@settings(max_examples=15)
@given(
    noise=st.lists(st.tuples(st.floats(-8, 8), st.floats(-8, 8), st.floats(-15, 15), st.floats(-20, 20)),
                   min_size=3, max_size=3),
    scores=st.lists(st.floats(0, 1), min_size=3, max_size=3),
    keep=st.lists(st.booleans(), min_size=3, max_size=3),
)
def test_ar_in_unit_interval_for_perturbed_estimates(models, renderer, noise, scores, keep):
    gts = make_gts(renderer)
    ests = []
    for g, (dx, dy, dz, ang), s, k in zip(gts, noise, scores, keep):
        if k:
            ests.append(Estimate(1, 0, g.obj_id, s, g.R @ rot("x", ang), g.t + [dx, dy, dz]))
    res = evaluate_bop19(gts, ests, models, renderer=renderer)
    for v in (res.ar, res.ar_vsd, res.ar_mssd, res.ar_mspd):
        assert 0.0 <= v <= 1.0
    for m in res.metrics.values():
        assert np.all((m.recall >= 0) & (m.recall <= 1))
    assert res.ar <= sum(keep) / 3 + 1e-12
    for e in res.errors:
        assert np.all(np.isfinite(e.vsd)) and np.all((e.vsd >= 0) & (e.vsd <= 1))
        assert np.all(e.mspd >= 0) and not np.any(np.isnan(e.mssd))

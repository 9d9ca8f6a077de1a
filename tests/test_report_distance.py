"""The distance study's measuring code on the synthetic bundle: the sweep's points, exact poses
scoring AR 1 and wrong ones less, resuming, and the estimator's anchor on a pixel's ray."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from brave6d.core.layout import SceneDir
from brave6d.core.transforms import make_transform
from brave6d.evaluation.report.measurements import MeasurementStore
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.sections.distance import DistanceSweep, by_distance, measure_distance
from brave6d.evaluation.report.single_view import ViewEstimate, ViewScorer, anchor_on_ray


@pytest.fixture(scope="module")
def bundle_workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.serve import make_synthetic_bundle

    work = tmp_path_factory.mktemp("distance")
    make_synthetic_bundle(work / "scene", n_gaussians=8000)
    return work


def _inputs(workdir: Path) -> MeasureInputs:
    return MeasureInputs(workdir, SceneDir(workdir / "scene"), MeasurementStore(workdir / "report" / "measurements"))


@pytest.mark.slow
def test_distance_sweep_on_the_synthetic_bundle(bundle_workdir: Path) -> None:
    sweep = DistanceSweep(distances_m=(0.25, 0.4), views=2, scale=0.5, device="cpu")
    m = measure_distance(_inputs(bundle_workdir), sweep)
    assert m.status == "complete" and m.settings["image"] == "160x120"
    assert len(m.points) == 2 * 2 * 2  # objects x distances x views
    targets = [p for p in m.points if p["target"]]
    assert targets, "no view saw its cube"
    for p in targets:
        assert 0.0 <= p["ar"] <= 1.0 and p["render_s"] > 0 and p["estimate_s"] > 0
        assert abs(p["ar"] - np.mean([p["ar_vsd"], p["ar_mssd"], p["ar_mspd"]])) < 1e-9
    near, far = by_distance(m.points)
    assert near["distance_m"] == 0.25 and far["distance_m"] == 0.4
    assert near["bbox_diag_px"] > far["bbox_diag_px"]  # the cubes look smaller farther away
    # the seeded viewpoints do not depend on the order of measuring: a fresh run draws the same poses
    again = measure_distance(_inputs(bundle_workdir), sweep)
    assert again.points == m.points  # complete and cached: nothing measured again
    fresh = MeasurementStore(bundle_workdir / "other", refresh=True)
    redo = measure_distance(MeasureInputs(bundle_workdir, SceneDir(bundle_workdir / "scene"), fresh), sweep)
    assert [(p["azimuth_deg"], p["elevation_deg"]) for p in redo.points] == \
        [(p["azimuth_deg"], p["elevation_deg"]) for p in m.points]


def test_an_exact_pose_scores_ar_1_and_a_wrong_one_less(bundle_workdir: Path) -> None:
    from brave6d.core.transforms import look_at
    from brave6d.evaluation.metrics import models_from_bundle
    from brave6d.serve import SceneServer, load_bundle

    bundle = load_bundle(bundle_workdir / "scene" / "bundle")
    server = SceneServer(bundle, "cpu")
    camera = bundle.camera.scaled(160, 120)
    scorer = ViewScorer(models_from_bundle(bundle))
    obj = bundle.objects[0]
    centre = server.centres_world[obj.gt_id]
    T = look_at(centre + np.array([-0.2, 0.05, 0.2]), centre)
    view = server.observe(T, camera, obj.gt_id)
    truth = view.target()
    assert truth is not None and truth.visib_fract > 0.5
    size = (camera.width, camera.height)
    exact = scorer.score(ViewEstimate(truth.cam_T_obj, 1.0, 0.0, "exact"), obj.obj_id, truth.cam_T_obj, camera.K,
                         size, view.depth, truth.visib_fract)
    assert exact.ar == 1.0 and exact.ar_vsd == exact.ar_mssd == exact.ar_mspd == 1.0
    assert exact.mssd_mm is not None and exact.mssd_mm < 1e-6
    shifted = truth.cam_T_obj @ make_transform(np.eye(3), np.array([0.006, 0.0, 0.0]))  # 6 mm: 0.21 diameters
    off = scorer.score(ViewEstimate(shifted, 1.0, 0.0, "shifted"), obj.obj_id, truth.cam_T_obj, camera.K, size,
                       view.depth, truth.visib_fract)
    assert 0.0 < off.ar_mssd < 1.0 and off.ar < 1.0
    assert abs(off.mssd_mm - 6.0) < 1e-6
    missed = scorer.score(ViewEstimate(None, 0.0, 0.0, "none"), obj.obj_id, truth.cam_T_obj, camera.K, size,
                          view.depth, truth.visib_fract)
    assert missed.ar == 0.0


@given(st.floats(-50, 250), st.floats(-50, 250), st.sampled_from(["empty", "nan", "ok"]))
def test_anchor_on_ray_is_finite_and_on_the_ray(u: float, v: float, kind: str) -> None:
    K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    depth = np.full((120, 160), 0.4, dtype=np.float32)
    if kind == "empty":
        depth[:] = 0.0
    elif kind == "nan":
        depth[:, :80] = np.nan
    p = anchor_on_ray(depth, K, (u, v))
    assert np.all(np.isfinite(p)) and p[2] > 0
    assert abs(K[0, 0] * p[0] / p[2] + K[0, 2] - u) < 1e-6 and abs(K[1, 1] * p[1] / p[2] + K[1, 2] - v) < 1e-6
    if kind == "ok":
        assert abs(p[2] - 0.4) < 1e-6

"""Fidelity where agents look: the metric functions on hand-made arrays, the pooling per distance
with hard views (target not visible, no depth), and the measurement end to end on a miniature
simulated scene (the synthetic tabletop with a ``simulation:`` part), its report section and the
benchmark's clear errors."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir
from brave6d.evaluation.report.fidelity import (FidelityProbe, FidelitySweep, TrainingSampling, depth_errors,
                                                fidelity_rows, fidelity_table, image_scores, sampling_ceiling,
                                                sampling_ratio, target_box, training_sampling)

SPEC = importlib.util.spec_from_file_location(
    "fidelity_benchmark", Path(__file__).resolve().parent.parent / "benchmarks" / "fidelity.py")
bench = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(bench)  # type: ignore[union-attr]


# ----------------------------------------------------------------------------- depth errors
def test_depth_errors_leave_truth_holes_out_and_count_splat_holes_as_misses() -> None:
    truth = np.array([[1.0, 1.0, 1.0, 0.0, 1.0, np.nan]], dtype=np.float32)
    splat = np.array([[1.002, 1.010, 0.0, 1.0, 1.1, 1.0]], dtype=np.float32)
    e = depth_errors(splat, truth, np.ones_like(truth, dtype=bool))
    assert e.pixels == 4  # the truth's hole (0) and NaN are no reference pixels
    assert e.median_mm == pytest.approx(10.0, abs=1e-3)  # of 2, 10 and 100 mm (the splat's hole has no error)
    assert e.within_5mm == pytest.approx(1 / 4) and e.within_15mm == pytest.approx(2 / 4)
    assert e.no_depth == pytest.approx(1 / 4)


def test_depth_errors_on_the_mask_only_and_exact_depth_is_all_within() -> None:
    truth = np.full((4, 5), 0.3, dtype=np.float32)
    splat = truth.copy()
    splat[0] = 0.9  # off by 600 mm, outside the mask
    mask = np.zeros_like(truth, dtype=bool)
    mask[1:3, 1:4] = True
    e = depth_errors(splat, truth, mask)
    assert (e.pixels, e.median_mm, e.within_5mm, e.within_15mm, e.no_depth) == (6, 0.0, 1.0, 1.0, 0.0)


def test_depth_errors_without_target_depth_are_nan_not_an_error() -> None:
    truth = np.zeros((3, 3), dtype=np.float32)
    e = depth_errors(truth, truth, np.ones((3, 3), dtype=bool))
    assert e.pixels == 0 and all(math.isnan(v) for v in (e.median_mm, e.within_5mm, e.within_15mm, e.no_depth))
    with pytest.raises(DataError, match="shapes differ"):
        depth_errors(truth, truth[:2], np.ones((3, 3), dtype=bool))


finite_or_holes = st.one_of(st.floats(0.0, 3.0, width=32), st.just(float("nan")), st.just(float("inf")),
                            st.just(0.0), st.floats(-1.0, 0.0, width=32))


@given(arrays(np.float32, (5, 6), elements=finite_or_holes), arrays(np.float32, (5, 6), elements=finite_or_holes),
       arrays(np.bool_, (5, 6)))
def test_depth_errors_are_shares_or_nan_for_any_depth(splat: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> None:
    e = depth_errors(splat, truth, mask)
    values = (e.median_mm, e.within_5mm, e.within_15mm, e.no_depth)
    if e.pixels == 0:
        assert all(math.isnan(v) for v in values)
        return
    for share in values[1:]:
        assert 0.0 <= share <= 1.0
    assert e.within_5mm <= e.within_15mm <= 1.0 - e.no_depth + 1e-12
    assert math.isnan(e.median_mm) == (e.no_depth == 1.0)
    assert math.isnan(e.median_mm) or (0.0 <= e.median_mm < math.inf)


# ----------------------------------------------------------------------------- image scores
def test_box_psnr_scores_the_targets_box_only() -> None:
    truth = np.full((40, 60, 3), 120, dtype=np.uint8)
    splat = truth.copy()
    splat[10:20, 30:45] += 10  # the target's box is off by 10 levels everywhere
    mask = np.zeros((40, 60), dtype=bool)
    mask[12:18, 31:44] = True
    mask[10, 30] = mask[19, 44] = True  # corners: the box is rows 10-19, columns 30-44
    box = target_box(mask)
    assert box == (slice(10, 20), slice(30, 45))
    box_psnr, box_ssim = image_scores(splat, truth, box=box)
    assert box_psnr == pytest.approx(20 * math.log10(255 / 10))
    whole, _ = image_scores(splat, truth)
    assert whole == pytest.approx(box_psnr + 10 * math.log10(40 * 60 / (10 * 15)))  # 1/16 of the pixels differ
    assert box_ssim < 1.0
    assert target_box(np.zeros((4, 4), dtype=bool)) is None


@pytest.mark.parametrize("level", [0, 128, 255])
def test_identical_and_constant_images_give_defined_scores(level: int) -> None:
    a = np.full((12, 16, 3), level, dtype=np.uint8)
    assert image_scores(a, a.copy()) == (100.0, pytest.approx(1.0))
    psnr, ssim = image_scores(a, np.full_like(a, 255 - level))
    assert math.isfinite(psnr) and math.isfinite(ssim)
    one_px = (slice(3, 4), slice(5, 6))
    assert image_scores(a, a.copy(), box=one_px) == (100.0, pytest.approx(1.0))
    nothing = np.zeros((12, 16), dtype=bool)
    assert all(math.isnan(v) for v in image_scores(a, a, valid=nothing))


# ----------------------------------------------------------------------------- the sampling ceiling
def _checkerboard(h: int, w: int, cell: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    board = (((yy // cell) + (xx // cell)) % 2 * 200 + 30).astype(np.uint8)
    return np.repeat(board[..., None], 3, axis=2)


def test_sampling_ceiling_loses_detail_finer_than_the_training_pixel_and_keeps_coarse_detail() -> None:
    fine, coarse = _checkerboard(64, 80, 1), _checkerboard(64, 80, 16)
    box = (slice(8, 56), slice(8, 72))
    assert sampling_ceiling(fine, 2.0, box) < 12.0  # a 1-pixel pattern averages away at half the sampling
    assert sampling_ceiling(coarse, 2.0, box) > sampling_ceiling(fine, 2.0, box) + 8.0
    ceilings = [sampling_ceiling(coarse, r, box) for r in (2.0, 4.0, 8.0)]
    assert all(a > b for a, b in zip(ceilings, ceilings[1:]))  # coarser training, lower ceiling
    flat = np.full((40, 50, 3), 77, dtype=np.uint8)
    assert sampling_ceiling(flat, 4.0) == 100.0  # nothing to lose: the PSNR of identical images


@pytest.mark.parametrize("ratio", [1.0, 0.5, 0.0, -3.0, math.nan, math.inf])
def test_sampling_ceiling_is_nan_where_the_training_sampled_at_least_as_finely(ratio: float) -> None:
    assert math.isnan(sampling_ceiling(_checkerboard(16, 16, 1), ratio))


@given(arrays(np.uint8, st.tuples(st.integers(1, 24), st.integers(1, 24), st.just(3))),
       st.floats(0.0, 1e9, allow_nan=False), st.integers(0, 23), st.integers(0, 23))
def test_sampling_ceiling_is_finite_or_nan_never_inf_for_any_image_and_ratio(img: np.ndarray, ratio: float, r0: int,
                                                                             c0: int) -> None:
    box = (slice(min(r0, img.shape[0] - 1), img.shape[0]), slice(min(c0, img.shape[1] - 1), img.shape[1]))
    value = sampling_ceiling(img, ratio, box)
    if ratio <= 1.0:
        assert math.isnan(value)
    else:
        assert math.isfinite(value) and 0.0 <= value <= 100.0


def test_sampling_ratio_compares_the_training_and_view_pixel_footprints() -> None:
    train = TrainingSampling(nearest_m=0.2, focal_px=457.0 / 2)  # the demo: 20 cm ring, half resolution
    assert sampling_ratio(0.1, 457.0, train) == pytest.approx(4.0)
    assert sampling_ratio(0.2, 457.0, train) == pytest.approx(2.0)
    assert sampling_ratio(0.5, 457.0, train) == pytest.approx(0.8)
    assert sampling_ratio(0.2, 457.0 / 4, train) == pytest.approx(0.5)  # a quarter-size view is coarser
    assert math.isnan(sampling_ratio(0.2, 457.0, None)) and math.isnan(sampling_ratio(0.0, 457.0, train))


def test_training_sampling_reads_the_recorded_downscale_and_the_nearest_ring(tmp_path: Path) -> None:
    import json

    from brave6d.core.layout import FrameLog, FrameRecord

    scene = SceneDir(tmp_path / "scene")
    assert training_sampling(scene, 460.0) is None  # no training recorded
    scene.metrics_path.parent.mkdir(parents=True)
    scene.metrics_path.write_text(json.dumps({"preset_config": {"downscale": 4}}))
    scene.frames_path.parent.mkdir(parents=True)
    log = FrameLog(scene.frames_path)
    for k, d in enumerate((0.4, 0.25, 0.3)):
        log.append(FrameRecord(index=k, view_id=str(k), distance_level=k, distance_m=d, rgb=f"rgb/{k:06d}.png",
                               base_T_tcp=np.eye(4).tolist(), joints=[0.0] * 6, timestamp=float(k)))
    assert training_sampling(scene, 460.0) == TrainingSampling(0.25, 115.0)
    scene.metrics_path.write_text(json.dumps({"images": {"downscale": 2}, "preset_config": {"downscale": 4}}))
    assert training_sampling(scene, 460.0) == TrainingSampling(0.25, 230.0)  # the images' record first
    assert training_sampling(scene, 460.0, downscale=1) == TrainingSampling(0.25, 460.0)  # a given one wins
    with pytest.raises(DataError, match="downscale must be positive"):
        training_sampling(scene, 460.0, downscale=0)


# ----------------------------------------------------------------------------- pooling per distance
def _target(px: int, **figures: float) -> dict:
    return {"obj_id": 1, "object": "cube", "px": px, **figures}


def test_rows_and_table_stay_defined_with_invisible_targets_and_no_depth() -> None:
    good = _target(900, box_psnr=30.0, box_ssim=0.9, depth_px=900, depth_median_mm=2.0, within_5mm=0.8,
                   within_15mm=0.95, no_depth=0.0, ar_truth=1.0, ar_splat=0.5, sampling_ratio=4.0,
                   box_psnr_ceiling=31.5)
    no_depth = _target(400, box_psnr=26.0, box_ssim=0.8, depth_px=0, depth_median_mm=None, within_5mm=None,
                       within_15mm=None, no_depth=None, sampling_ratio=0.8, box_psnr_ceiling=math.nan)
    points = [
        {"distance_m": 0.1, "psnr": 30.0, "ssim": 0.9, "targets": [good]},
        {"distance_m": 0.1, "psnr": 100.0, "ssim": 1.0, "targets": [_target(0)]},  # not visible
        {"distance_m": 0.5, "psnr": 28.0, "ssim": 0.95, "targets": [no_depth]},
        {"distance_m": 0.5, "note": "every drawn viewpoint collides", "targets": []},
    ]
    near, far = fidelity_rows(points)
    assert (near["views"], near["targets"], near["scored"]) == (2, 2, 1)
    assert near["px"] == 450.0  # the invisible target counts with 0 pixels
    assert near["box_psnr"] == 30.0 and near["within_5mm"] == 0.8  # ... but has no box or depth figures
    assert near["ar_gap"] == pytest.approx(0.5)
    assert far["box_psnr"] == 26.0 and math.isnan(far["depth_median_mm"]) and math.isnan(far["ar_gap"])
    assert (near["box_psnr_ceiling"], near["sampling_ratio"], far["sampling_ratio"]) == (31.5, 4.0, 0.8)
    assert math.isnan(far["box_psnr_ceiling"])  # r <= 1: no ceiling below the truth
    headers, lines = fidelity_table([near, far])
    assert headers == ["metric", "10 cm", "50 cm"]
    by_label = {line[0]: line[1:] for line in lines}
    assert by_label["box PSNR ceiling at the training's sampling (dB)"] == ["31.5", "n/a"]
    assert by_label["sampling ratio r (training pixel / view pixel on the target)"] == ["4.00", "0.80"]
    text = " ".join(c for line in lines for c in line).lower()
    assert "nan" not in text and "inf" not in text and "n/a" in text
    assert fidelity_table(fidelity_rows([{**points[0], "distance_m": 0.125}]))[0][1] == "12.5 cm"


# ----------------------------------------------------------------------------- end to end on a tiny scene
@pytest.fixture(scope="module")
def sim_scene(tmp_path_factory: pytest.TempPathFactory) -> SceneDir:
    """The synthetic tabletop (two 20 mm cubes, their splat, a bundle) made a simulated scene."""
    from brave6d.serve import make_synthetic_bundle

    root = tmp_path_factory.mktemp("fidelity") / "scene"
    make_synthetic_bundle(root, n_gaussians=6000)
    scene = SceneDir(root)
    spec = yaml.safe_load(scene.spec_path.read_text())
    spec["simulation"] = {"true_tcp_T_camera": {"xyz": [0.0, -0.06, 0.03], "rpy_deg": [0.0, 0.0, 0.0]},
                          "background_rgb": [0, 0, 0]}
    scene.spec_path.write_text(yaml.safe_dump(spec, sort_keys=False))
    scene.metrics_path.parent.mkdir(parents=True, exist_ok=True)  # trained at 1/8: coarser than the quarter-size views
    scene.metrics_path.write_text('{"images": {"downscale": 8}}')
    return scene


@pytest.mark.slow
def test_probe_measures_a_simulated_scene_against_its_truth(sim_scene: SceneDir) -> None:
    from brave6d.serve import SplatRenderer, load_bundle
    from brave6d.training import read_ply

    sweep = FidelitySweep(distances_m=(0.2, 0.4), views=1, scale=0.25, device="cpu")
    bundle = load_bundle(sim_scene.bundle_dir)
    probe = FidelityProbe(sim_scene, bundle, sweep)
    assert probe.mode == "simulated" and len(probe.items()) == 2 * 2 * 1  # objects x distances x views
    points = [probe.measure(item) for _, item in probe.items()]
    for p in points:
        (t,) = p["targets"]
        assert t["px"] > 0, "the viewed cube is not in the truth's object-id buffer"
        assert 0.0 <= t["within_5mm"] <= t["within_15mm"] <= 1.0 and t["no_depth"] == 0.0
        assert t["visib_fract"] == 1.0  # nothing stands between the camera and the cube in the truth
        assert 0.0 <= t["ar_truth"] <= 1.0 and 0.0 <= t["ar_splat"] <= 1.0
        assert math.isfinite(p["psnr"]) and math.isfinite(t["box_psnr"])
        # frames at 30 cm, trained at 1/8, viewed at 1/4: r = 0.3 * 8 / (d * 4)
        assert t["sampling_ratio"] == pytest.approx(0.6 / p["distance_m"], rel=0.01)
        assert 0.0 < t["box_psnr_ceiling"] <= 100.0
    near, far = fidelity_rows(points)
    assert near["px"] > far["px"]  # the cubes look larger from closer
    assert probe.settings()["training_sampling"] == {"nearest_ring_m": 0.3, "focal_px": bundle.camera.fx / 8}
    full = FidelityProbe(sim_scene, bundle, sweep, downscale=1)  # trained at full size: finer than these views
    point = full.measure(full.items()[0][1])
    assert point["targets"][0]["sampling_ratio"] < 1.0 and math.isnan(point["targets"][0]["box_psnr_ceiling"])
    # the same views of the splat lifted by 3 cm: the depth error on the targets grows by about that
    splat = read_ply(bundle.splat_path)
    splat.means[:, 2] += 0.03
    lifted = FidelityProbe(sim_scene, bundle, sweep, SplatRenderer.from_splat(splat, "cpu"))
    moved = [lifted.measure(item) for _, item in lifted.items()]
    assert [(p["azimuth_deg"], p["elevation_deg"]) for p in moved] == \
        [(p["azimuth_deg"], p["elevation_deg"]) for p in points]  # seeded: the same viewpoints
    before = np.median([p["targets"][0]["depth_median_mm"] for p in points])
    after = np.median([p["targets"][0]["depth_median_mm"] for p in moved if p["targets"][0]["depth_px"]])
    assert after > before + 10.0


def test_report_section_measures_and_renders(sim_scene: SceneDir, tmp_path: Path) -> None:
    from brave6d.evaluation.report.measurements import MeasurementStore
    from brave6d.evaluation.report.protocol import MeasureInputs
    from brave6d.evaluation.report.sections import names
    from brave6d.evaluation.report.sections.fidelity import SECTION

    assert "fidelity" in names()
    sweep = FidelitySweep(distances_m=(0.2,), views=1, scale=0.25, device="cpu")
    m = SECTION.measure(MeasureInputs(tmp_path, sim_scene, MeasurementStore(tmp_path / "m")), sweep)
    assert m.status == "complete" and len(m.points) == 2 and m.summary["mode"] == "simulated"
    page = SECTION.render({"fidelity": m}, tmp_path)
    assert (tmp_path / "fidelity.png").is_file() and "depth error on the target's pixels" in page.body
    assert "nan" not in page.body.lower()
    ceiling = next(line for line in page.body.splitlines() if "box PSNR ceiling at the training's sampling" in line)
    assert "n/a" not in ceiling  # r = 0.3 * 8 / (0.2 * 4) = 3: a measured ceiling
    assert "an estimate of what the training images could hold" in page.body


def test_clear_errors_for_a_bundle_without_objects_or_a_spec_without_them(sim_scene: SceneDir,
                                                                          tmp_path: Path) -> None:
    from brave6d.serve import load_bundle

    empty = SimpleNamespace(root=tmp_path / "bundle", objects=())
    with pytest.raises(DataError, match="no objects"):
        FidelityProbe(sim_scene, empty, FidelitySweep())
    bundle = load_bundle(sim_scene.bundle_dir)
    renamed = SimpleNamespace(**{k: getattr(bundle, k) for k in ("root", "camera", "holdout")},
                              objects=(SimpleNamespace(name="ghost", obj_id=9, gt_id=0),))
    with pytest.raises(DataError, match="no simulated object named ghost"):
        FidelityProbe(sim_scene, renamed, FidelitySweep())


def test_benchmark_refuses_a_missing_bundle_by_name(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = tmp_path / "scene"
    scene.mkdir()
    assert bench.main([str(scene), "--bundle", str(tmp_path / "nothing")]) == 2
    assert "scene.yaml" in capsys.readouterr().err
    (scene / "scene.yaml").write_text("name: x\n")
    assert bench.main([str(scene), "--bundle", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert "nothing: not a bundle" in err and err.count("\n") == 1
    with pytest.raises(SystemExit):
        bench.main([str(scene)])  # neither --bundle nor --a/--b
    assert bench.bundle_arg("new=/x/y") == ("new", Path("/x/y"))


@pytest.mark.slow
def test_benchmark_trains_two_configurations_and_measures_both(sim_scene: SceneDir, tmp_path: Path) -> None:
    import json

    out = tmp_path / "fidelity.json"
    assert bench.main([str(sim_scene.root), "--a", "a=fast,steps=10,coarse_steps=0", "--b",
                       "b=fast,steps=20,coarse_steps=0", "--views", "1", "--distances", "0.3", "--every", "10",
                       "--chunk", "5", "--device", "cpu", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    a, b = data["configurations"]
    assert (a["name"], a["steps"], b["name"], b["steps"]) == ("a", 10, "b", 20)
    assert a["train_s"] > 0 and b["train_s"] > 0 and a["source"]["preset"]["steps"] == 10
    assert [r["distance_m"] for r in a["rows"]] == [0.3] and len(b["points"]) == 2
    assert out.with_suffix(".png").is_file()


@pytest.mark.slow
def test_captured_frames_that_are_the_splats_own_renders_score_perfect(tmp_path: Path) -> None:
    """A captured scene: held-out frames (here the splat's own renders, depth in mm) against the splat."""
    from test_report_realism import _splat_frames_as_capture

    from brave6d.serve import load_bundle, make_synthetic_bundle

    make_synthetic_bundle(tmp_path / "scene", n_gaussians=6000, n_views=6, bop=True)
    scene = SceneDir(tmp_path / "scene")
    _splat_frames_as_capture(scene)
    probe = FidelityProbe(scene, load_bundle(scene.bundle_dir), FidelitySweep(holdout_per_level=2, device="cpu"))
    assert probe.mode == "captured" and 1 <= len(probe.items()) <= 2
    points = [probe.measure(item) for _, item in probe.items()]
    targets = [t for p in points for t in p["targets"] if t["px"] > 0]
    assert targets and all(p["holdout"] and p["psnr"] == 100.0 for p in points)
    for t in targets:
        assert t["box_psnr"] == 100.0 and t["no_depth"] == 0.0 and t["within_5mm"] == 1.0
        assert t["depth_median_mm"] <= 0.5  # the capture's depth is the render's, rounded to mm
        if "ar_truth" in t:
            assert t["ar_truth"] == t["ar_splat"]
    (row,) = fidelity_rows(points)
    assert row["distance_m"] == 0.3 and row["scored"] >= 1 and row["ar_gap"] == 0.0


def test_a_bundles_recorded_training_is_read_only_from_its_own_metrics(tmp_path: Path) -> None:
    import hashlib
    import json

    scene = SceneDir(tmp_path / "scene")
    scene.metrics_path.parent.mkdir(parents=True)
    scene.metrics_path.write_text(json.dumps({"train_time_s": 105.0, "steps": 2000, "holdout": {"psnr": 32.19}}))
    digest = hashlib.sha256(scene.metrics_path.read_bytes()).hexdigest()
    bundle = SimpleNamespace(manifest={"source": {"metrics_sha256": digest}})
    got = bench.recorded_training(scene.bundle_dir, bundle)
    assert (got["train_s"], got["holdout_psnr"], got["steps"]) == (105.0, 32.19, 2000)
    other = SimpleNamespace(manifest={"source": {"metrics_sha256": "0" * 64}})  # retrained since the export
    assert bench.recorded_training(scene.bundle_dir, other) == {"train_s": None, "holdout_psnr": None}


def test_rows_give_the_ar_gap_with_the_standard_error_of_its_paired_differences() -> None:
    """Targets with truth - splat differences 1.0, 0.0, 0.5: mean 0.5, SE = 0.5 / sqrt(3)."""
    targets = [_target(900, ar_truth=1.0, ar_splat=0.0), _target(900, ar_truth=0.5, ar_splat=0.5),
               _target(900, ar_truth=1.0, ar_splat=0.5)]
    (row,) = fidelity_rows([{"distance_m": 0.3, "psnr": 30.0, "ssim": 0.9, "targets": targets}])
    assert row["ar_gap"] == pytest.approx(0.5) and row["ar_gap_se"] == pytest.approx(0.5 / math.sqrt(3.0))
    assert "its standard error (per-target differences)" in [line[0] for line in fidelity_table([row])[1]]

"""The realism section's measuring code on the synthetic scene: when the "captured" frames are the
splat's own renders the AR gap is exactly 0 (and PSNR/SSIM perfect); when they are not, the code
sees it. Also the view choice and the image metrics."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from brave6d.core.atomic import depth_m_to_mm_u16, read_png, write_png
from brave6d.core.layout import SceneDir
from brave6d.evaluation.report.image_quality import psnr, ssim
from brave6d.evaluation.report.measurements import MeasurementStore
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.sections.realism import RealismSweep, choose_views, gap_rows, measure_realism


def _splat_frames_as_capture(scene: SceneDir) -> list[int]:
    """Overwrite the BOP export's RGB-D with the splat's renders of the same poses; the image ids."""
    from brave6d.annotation import BopLayout, read_scene_camera
    from brave6d.core.camera import PinholeCamera
    from brave6d.core.transforms import invert
    from brave6d.serve import SplatRenderer, load_bundle

    layout = BopLayout.of_scene(scene)
    bundle = load_bundle(scene.bundle_dir)
    renderer = SplatRenderer(bundle.splat_path, "cpu")
    cams = read_scene_camera(layout.scene_camera_path)
    for im_id, cam in cams.items():
        h, w = read_png(layout.rgb_path(im_id), "rgb").shape[:2]
        K = cam.cam_K
        out = renderer.render(invert(cam.cam_T_world()), PinholeCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2]),
                              near=bundle.render.near, far=bundle.render.far, background=bundle.render.background,
                              depth_alpha_min=bundle.render.depth_alpha_min)
        write_png(layout.rgb_path(im_id), out.rgb)
        write_png(layout.depth_path(im_id), depth_m_to_mm_u16(out.depth))
    return sorted(cams)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.serve import make_synthetic_bundle

    work = tmp_path_factory.mktemp("realism")
    make_synthetic_bundle(work / "scene", n_gaussians=8000, n_views=6, bop=True)
    _splat_frames_as_capture(SceneDir(work / "scene"))
    return work


@pytest.mark.slow
def test_flip_colour_benchmark_prints_each_weight_per_ring_and_times_them_interleaved(workdir: Path) -> None:
    """benchmarks/flip_colour.py end to end (before the test below changes the frames): each weight's
    rows, a zero gap for both (the frames are the splat's renders), and the interleaved timing."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, str(root / "benchmarks" / "flip_colour.py"), str(workdir), "--weights", "0,0.1",
                          "--holdout-per-level", "1", "--train-per-level", "1", "--device", "cpu", "--time-every", "2"],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [line.split("|")[1:-1] for line in out.stdout.splitlines() if line.startswith("| 0")]
    assert {r[0].strip() for r in rows} == {"0", "0.1"} and len(rows) % 2 == 0 and rows
    assert all(r[5].strip() == "0.000 ± 0.000" for r in rows), rows
    timing = [line for line in out.stdout.splitlines() if line.startswith("weight ")]
    assert len(timing) == 2 and "median ratio to weight 0: 1.000" in timing[0], timing
    assert int(timing[1].split(": ")[1].split()[0]) > 0


@pytest.mark.slow
def test_gap_is_zero_when_the_real_frames_are_the_splats_own_renders(workdir: Path) -> None:
    scene = SceneDir(workdir / "scene")
    store = MeasurementStore(workdir / "report" / "measurements")
    sweep = RealismSweep(holdout_per_level=2, train_per_level=2, stride=2, device="cpu")
    m = measure_realism(MeasureInputs(workdir, scene, store), sweep)
    assert m.status == "complete", m.note
    objects = [o for p in m.points for o in p["objects"]]
    assert len(m.points) >= 2 and objects
    assert any(p["holdout"] for p in m.points) and not all(p["holdout"] for p in m.points)
    for p in m.points:
        assert p["psnr"] == 100.0 and abs(p["ssim"] - 1.0) < 1e-9
    for o in objects:
        assert o["real_found"] == o["splat_found"]
        for k in ("ar", "ar_vsd", "ar_mssd", "ar_mspd"):
            assert o[f"real_{k}"] == o[f"splat_{k}"]
    assert any(o["real_found"] for o in objects), "the estimator found no cube at all"
    assert [r["gap"] for r in gap_rows(m.points)] == [0.0] * len(gap_rows(m.points))

    # frames that differ from the renders (a 3 cm deeper table and objects, brighter image): the code sees it
    from brave6d.annotation import BopLayout

    layout = BopLayout.of_scene(scene)
    for p in m.points:
        depth = read_png(layout.depth_path(p["im_id"]), "depth").astype(np.int64)
        write_png(layout.depth_path(p["im_id"]), np.where(depth > 0, depth + 30, 0).astype(np.uint16))
        rgb = read_png(layout.rgb_path(p["im_id"]), "rgb").astype(np.int64)
        write_png(layout.rgb_path(p["im_id"]), np.clip(rgb + 40, 0, 255).astype(np.uint8))
    changed = measure_realism(MeasureInputs(workdir, scene, store), sweep)  # new input stamps: measured again
    assert all(p["psnr"] < 30.0 for p in changed.points)
    pairs = [(o["real_ar"], o["splat_ar"]) for p in changed.points for o in p["objects"]]
    assert any(r != s for r, s in pairs)


def test_views_are_chosen_per_level_held_out_first() -> None:
    levels = {i: i // 10 for i in range(30)}  # ten images per level
    holdout = {2, 5, 13, 27, 28, 29}
    chosen = choose_views(levels, holdout, set(range(30)) - {0}, RealismSweep(holdout_per_level=2, train_per_level=1))
    assert chosen == [(2, True), (5, True), (6, False), (13, True), (15, False), (27, True), (29, True), (23, False)]


def test_image_metrics() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    assert psnr(a, a) == 100.0 and abs(ssim(a, a) - 1.0) < 1e-12
    b = a.copy()
    b[:, :10] = 0
    valid = np.ones((40, 50), bool)
    valid[:, :10] = False
    assert psnr(a, b, valid) == 100.0 and abs(ssim(a, b, valid) - 1.0) < 1e-12  # the border is left out
    assert psnr(a, b) < 20.0 and ssim(a, b) < 0.9
    noisy = np.clip(a.astype(int) + rng.integers(-8, 9, a.shape), 0, 255).astype(np.uint8)
    mse = np.mean(((a.astype(float) - noisy) / 255.0) ** 2)
    assert abs(psnr(a, noisy) - (-10 * np.log10(mse))) < 1e-9


@pytest.mark.parametrize(("gaps", "says"), [
    ([0.1, 0.3, 0.5, 0.7], "higher PSNR came with a larger gap"),
    ([0.7, 0.5, 0.3, 0.1], "(higher PSNR, smaller gap)"),
    ([0.4, 0.1, 0.5, 0.2], "PSNR alone does not predict the gap"),
])
def test_realism_advice_says_which_way_psnr_and_the_gap_go(gaps: list[float], says: str) -> None:
    from brave6d.evaluation.report.sections.realism import advice_realism

    rows = [{"distance_m": d, "gap": g, "psnr": p, "estimate_s": 1.0, "render_s": 0.1}
            for d, g, p in zip((0.2, 0.3, 0.4, 0.5), gaps, (28.0, 29.0, 30.0, 31.0))]
    text = advice_realism(rows, [])
    assert says in text
    assert sum(s in text for s in ("larger gap", "smaller gap", "alone does not predict")) == 1


def test_gap_rows_give_the_paired_standard_error_of_the_gap() -> None:
    """Two targets per level, differences 0.6 and 0.0: mean 0.3, SE = std(ddof=1) / sqrt(2) = 0.3."""
    points = [{"level": 0, "distance_m": 0.3, "holdout": True, "objects": [
        {"obj_id": 1, "real_ar": 1.0, "splat_ar": 0.4}, {"obj_id": 2, "real_ar": 0.5, "splat_ar": 0.5}]}]
    (row,) = gap_rows(points)
    assert row["gap"] == pytest.approx(0.3) and row["gap_se"] == pytest.approx(0.3)
    one = [{"level": 0, "distance_m": 0.3, "objects": [{"obj_id": 1, "real_ar": 1.0, "splat_ar": 0.4}]}]
    assert math.isnan(gap_rows(one)[0]["gap_se"])


@pytest.mark.parametrize(("gap", "se", "unresolved"), [(0.109, 0.039, True), (0.09, 0.039, True),
                                                       (0.109, 0.004, False), (0.02, 0.03, False)])
def test_realism_advice_names_a_gap_its_targets_cannot_place_against_the_limit(gap: float, se: float,
                                                                             unresolved: bool) -> None:
    from brave6d.evaluation.report.sections.realism import advice_realism

    rows = [{"distance_m": 0.3, "gap": gap, "gap_se": se, "targets": 48, "psnr": 30.0, "estimate_s": 1.0,
             "render_s": 0.1}]
    assert ("cannot tell which side" in advice_realism(rows, [])) is unresolved


def test_realism_advice_claims_stand_in_scores_only_when_every_level_is_resolved() -> None:
    from brave6d.evaluation.report.sections.realism import advice_realism

    def rows(se: float) -> list[dict]:
        return [{"distance_m": d, "gap": 0.05, "gap_se": se, "targets": 16, "psnr": 30.0, "estimate_s": 1.0,
                 "render_s": 0.1} for d in (0.2, 0.3)]
    assert "stand in for scores on the capture" in advice_realism(rows(0.01), [])
    vague = advice_realism(rows(0.07), [])
    assert "stand in" not in vague and "cannot tell which side of 0.10 the gap is on at 20 cm, 30 cm" in vague

"""Hard cases of the learned estimator: PnP with few, collinear or non-finite correspondences, crops
at the image border, objects the model never saw, empty or NaN inputs, a NaN loss in training.
No NaN or inf pose ever comes out; every failure is a LearnedRefused naming its cause."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.core.errors import BraveError
from brave6d.evaluation.learned import REFUSAL_CAUSES, LearnedEstimator, LearnedRefused, get_learn_preset, solve_pnp
from brave6d.evaluation.learned.crops import iou
from brave6d.evaluation.learned.inference import NMS_IOU
from learned_helpers import untrained_model

K = np.array([[228.0, 0.0, 159.5], [0.0, 228.0, 99.5], [0.0, 0.0, 1.0]])
PRESET = get_learn_preset("tiny")


@pytest.fixture(scope="module")
def estimator() -> LearnedEstimator:
    return LearnedEstimator(untrained_model(PRESET, [1, 2]))


def _project(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    cam = points @ R.T + t
    return np.stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]], axis=1)


@settings(max_examples=40, deadline=None)
@given(rotvec=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3), depth=st.floats(0.1, 2.0),
       seed=st.integers(0, 2**16), n=st.integers(8, 200))
def test_pnp_recovers_a_pose_from_clean_correspondences(rotvec: list[float], depth: float, seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.015, 0.015, size=(n, 3))
    R, t = Rotation.from_rotvec(rotvec).as_matrix(), np.array([0.01, -0.005, depth])
    R_est, t_est, inliers = solve_pnp(points, _project(points, R, t), K)
    assert np.all(np.isfinite(R_est)) and np.all(np.isfinite(t_est))
    assert np.linalg.norm(t_est - t) < 1e-4 * max(1.0, depth) and np.abs(R_est - R).max() < 1e-3
    assert len(inliers) >= 0.9 * n


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 5), seed=st.integers(0, 2**16))
def test_pnp_with_too_few_correspondences_is_refused(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    with pytest.raises(LearnedRefused) as info:
        solve_pnp(rng.normal(size=(n, 3)), rng.normal(size=(n, 2)) * 50 + 100, K)
    assert info.value.cause == "few-correspondences"


@settings(max_examples=40, deadline=None)
@given(n=st.integers(6, 100), seed=st.integers(0, 2**16), noise=st.sampled_from([0.0, 1e-9, 1e-6]))
def test_collinear_or_coincident_points_are_refused_not_solved(n: int, seed: int, noise: float) -> None:
    rng = np.random.default_rng(seed)
    line = np.outer(rng.uniform(-0.02, 0.02, size=n), rng.normal(size=3)) + rng.normal(0.0, noise, size=(n, 3))
    image = _project(line, np.eye(3), np.array([0.0, 0.0, 0.4]))
    with pytest.raises(LearnedRefused) as info:
        solve_pnp(line, image, K)
    assert info.value.cause == "degenerate-correspondences"
    same = np.repeat(rng.normal(size=(1, 3)), n, axis=0)
    with pytest.raises(LearnedRefused) as info:
        solve_pnp(same, rng.normal(size=(n, 2)) * 30 + 100, K)
    assert info.value.cause == "degenerate-correspondences"


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_correspondences_are_refused(bad: float) -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.01, 0.01, size=(20, 3))
    image = _project(points, np.eye(3), np.array([0.0, 0.0, 0.3]))
    image[3, 1] = bad
    with pytest.raises(LearnedRefused) as info:
        solve_pnp(points, image, K)
    assert info.value.cause == "bad-input"


@pytest.mark.parametrize("threshold", [0.0, -1.0, np.nan, np.inf])
def test_a_pnp_threshold_that_is_not_a_positive_pixel_count_is_refused(threshold: float) -> None:
    from brave6d.core.errors import BraveError

    points = np.random.default_rng(0).uniform(-0.01, 0.01, size=(20, 3))
    with pytest.raises(BraveError, match="reprojection_px"):
        solve_pnp(points, _project(points, np.eye(3), np.array([0.0, 0.0, 0.3])), K, reprojection_px=threshold)


def test_random_correspondences_give_a_finite_pose_or_a_named_refusal() -> None:
    rng = np.random.default_rng(1)
    for _ in range(60):
        n = int(rng.integers(6, 80))
        try:
            R, t, _ = solve_pnp(rng.normal(0, 0.01, size=(n, 3)), rng.uniform(0, 320, size=(n, 2)), K)
        except LearnedRefused as exc:
            assert exc.cause in REFUSAL_CAUSES
        else:
            assert np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and t[2] > 0
            assert math.isclose(np.linalg.det(R), 1.0, abs_tol=1e-6)


def _noisy_correspondences(seed: int, n: int, outliers: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points of a 6 cm object 20-60 cm away, their projections with 0.7 px of noise, a share
    ``outliers`` of them anywhere in the image (a coordinate net's wrong cells)."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.03, 0.03, size=(n, 3))
    R, t = Rotation.random(random_state=seed).as_matrix(), np.array([0.01, -0.02, rng.uniform(0.2, 0.6)])
    image = _project(points, R, t) + rng.normal(0.0, 0.7, size=(n, 2))
    wrong = rng.random(n) < outliers
    image[wrong] = rng.uniform(0.0, 320.0, size=(int(wrong.sum()), 2))
    return points, image


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(30, 600), outliers=st.floats(0.0, 0.3),
       size=st.floats(1e-7, 1e-6))
def test_pnp_is_continuous_in_its_inputs(seed: int, n: int, outliers: float, size: float) -> None:
    """Moving every correspondence by float noise (1e-7..1e-6, the size of torch's and ONNX Runtime's
    differences) moves the pose by about as much: no other consensus, no flipped pose."""
    points, image = _noisy_correspondences(seed, n, outliers)
    R, t, _ = solve_pnp(points, image, K, reprojection_px=3.0)
    rng = np.random.default_rng(seed + 1)
    for _ in range(3):
        R2, t2, _ = solve_pnp(points + rng.uniform(-size, size, points.shape) * 1e-2,
                              image + rng.uniform(-size, size, image.shape), K, reprojection_px=3.0)
        assert np.abs(R2 - R).max() < 1e-4 and np.abs(t2 - t).max() < 1e-4


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(6, 200), behind=st.floats(0.05, 1.0),
       outliers=st.floats(0.0, 1.0))
def test_points_behind_the_camera_give_a_pose_in_front_or_a_named_refusal(seed: int, n: int, behind: float,
                                                                          outliers: float) -> None:
    """Image points projected from an object behind the camera (and any share of them random): a finite
    rotation and a translation in front of the camera, or a refusal naming its cause."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.03, 0.03, size=(n, 3))
    image = _project(points, Rotation.random(random_state=seed).as_matrix(), np.array([0.0, 0.0, -behind]))
    wrong = rng.random(n) < outliers
    image[wrong] = rng.uniform(0.0, 320.0, size=(int(wrong.sum()), 2))
    try:
        R, t, inliers = solve_pnp(points, image, K)
    except LearnedRefused as exc:
        assert exc.cause in REFUSAL_CAUSES
    else:
        assert np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and t[2] > 0
        assert math.isclose(np.linalg.det(R), 1.0, abs_tol=1e-6) and len(inliers) >= 6


@settings(max_examples=30, deadline=None)
@given(x0=st.floats(-400.0, 400.0), y0=st.floats(-300.0, 300.0), w=st.floats(0.5, 300.0), h=st.floats(0.5, 300.0),
       use_depth=st.booleans(), value=st.integers(0, 255))
def test_any_box_even_off_the_image_gives_a_finite_pose_or_a_named_refusal(estimator: LearnedEstimator, x0: float,
                                                                            y0: float, w: float, h: float,
                                                                            use_depth: bool, value: int) -> None:
    rgb = np.full((200, 320, 3), value, np.uint8)  # a constant image, too
    depth = np.full((200, 320), 0.4, np.float32) if use_depth else None
    try:
        pose = estimator.estimate(rgb, K, 1, (x0, y0, x0 + w, y0 + h), depth)
    except LearnedRefused as exc:
        assert exc.cause in REFUSAL_CAUSES
    else:
        assert np.all(np.isfinite(pose.cam_T_obj)) and pose.cam_T_obj[2, 3] > 0 and 0.0 <= pose.score <= 1.0


@settings(max_examples=30, deadline=None)
@given(x0=st.floats(-40.0, 330.0), y0=st.floats(-40.0, 210.0), w=st.floats(0.5, 400.0), h=st.floats(0.5, 300.0),
       value=st.integers(0, 255), noise=st.booleans())
def test_a_refined_box_is_finite_and_non_empty_anywhere_in_or_off_the_image(
        estimator: LearnedEstimator, x0: float, y0: float, w: float, h: float, value: int, noise: bool) -> None:
    from brave6d.evaluation.learned import Detection

    rng = np.random.default_rng(int(x0 * 7 + y0) % 1000)
    rgb = rng.integers(0, 256, size=(200, 320, 3), dtype=np.uint8) if noise else np.full((200, 320, 3), value, np.uint8)
    det = Detection(1, (x0, y0, x0 + w, y0 + h), 0.7)
    out = estimator.refine_box(rgb, K, det)
    assert out.obj_id == 1 and out.score == 0.7
    assert all(math.isfinite(b) for b in out.box) and out.box[2] > out.box[0] and out.box[3] > out.box[1]


@settings(max_examples=60, deadline=None)
@given(scales=st.lists(st.floats(1e-3, 100.0), min_size=1, max_size=3), work=st.sampled_from([64, 320, 640]),
       source=st.sampled_from([320, 640, 1280]))
def test_the_detector_widths_stay_between_64_px_and_the_crops_source(scales: list[float], work: int, source: int) -> None:
    est = LearnedEstimator(untrained_model(PRESET, [1]))
    est.preset = dict(est.preset, work_width=work, crop_source_width=max(source, work))
    est.detect_scales = tuple(scales)
    widths = est.detect_widths
    assert widths == sorted(set(widths)) and all(64 <= w <= max(source, work) for w in widths)
    for x in scales:
        if 64 <= work * x <= max(source, work):
            assert any(abs(w - work * x) <= 0.5 for w in widths)


def test_the_fast_preset_detects_at_one_or_two_widths_and_a_bad_scale_is_named() -> None:
    fast = LearnedEstimator(untrained_model(get_learn_preset("fast"), [1, 2]))
    assert fast.detect_widths == [320]  # the default: one pass at the training width
    fast.detect_scales = (1.0, 1.375)
    assert fast.detect_widths == [320, 440]  # 320 x (1, 1.375), under the crops' 640
    paper = LearnedEstimator(untrained_model(get_learn_preset("paper"), [1]))
    paper.detect_scales = (1.0, 1.375)
    assert paper.detect_widths == [640]  # never wider than the camera's own pixels
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, size=(400, 640, 3), dtype=np.uint8)
    K640 = np.array([[456.0, 0.0, 319.5], [0.0, 456.0, 199.5], [0.0, 0.0, 1.0]])
    found = fast.detect(rgb, K640, min_score=0.0)
    assert 0 < len(found) <= 20 and [d.score for d in found] == sorted((d.score for d in found), reverse=True)
    for a in found:  # boxes in the input image's pixels; no two of one object overlap by the NMS IoU
        assert all(math.isfinite(b) for b in a.box)
        assert all(b is a or b.obj_id != a.obj_id or iou(a.box, b.box) < NMS_IOU for b in found)
    fast.upscaled_max_box_px = 0.0  # the wider pass keeps nothing: what the training width alone finds
    only_upscaled_small = fast.detect(rgb, K640, min_score=0.0)
    fast.detect_scales = (1.0,)
    assert [(d.obj_id, d.box, d.score) for d in fast.detect(rgb, K640, min_score=0.0)] == \
        [(d.obj_id, d.box, d.score) for d in only_upscaled_small]
    fast.detect_scales, fast.upscaled_max_box_px = (1.375,), math.inf
    assert {(d.obj_id, d.box) for d in fast.detect(rgb, K640, min_score=0.0)} != \
        {(d.obj_id, d.box) for d in only_upscaled_small}  # another width finds other boxes
    for bad in ((), (0.0,), (1.0, -1.0), (float("nan"),), (float("inf"),)):
        fast.detect_scales = bad
        with pytest.raises(BraveError, match="detect_scales"):
            fast.detect(rgb, K640)


def test_an_object_the_model_never_saw_is_refused_naming_it(estimator: LearnedEstimator) -> None:
    rgb = np.zeros((200, 320, 3), np.uint8)
    for call in (lambda: estimator.best_detection(rgb, K, 7), lambda: estimator.estimate(rgb, K, 7, (10, 10, 40, 40))):
        with pytest.raises(LearnedRefused) as info:
            call()
        assert info.value.cause == "unknown-object" and "object 7" in str(info.value) and "1, 2" in str(info.value)


@pytest.mark.parametrize("rgb, K_, cause", [
    (np.zeros((8, 8, 3), np.uint8), K, "bad-input"),
    (np.zeros((200, 320), np.uint8), K, "bad-input"),
    (np.zeros((200, 320, 3), np.float32), K, "bad-input"),
    (np.zeros((200, 320, 3), np.uint8), np.full((3, 3), np.nan), "bad-input"),
    (np.zeros((200, 320, 3), np.uint8), np.zeros((3, 3)), "bad-input"),
])
def test_bad_images_and_cameras_are_refused(estimator: LearnedEstimator, rgb: np.ndarray, K_: np.ndarray,
                                            cause: str) -> None:
    with pytest.raises(LearnedRefused) as info:
        estimator.detect(rgb, K_)
    assert info.value.cause == cause


def test_an_empty_or_non_finite_box_is_refused(estimator: LearnedEstimator) -> None:
    rgb = np.zeros((200, 320, 3), np.uint8)
    for box in ((10, 10, 10, 40), (10, 10, 5, 5), (np.nan, 0, 10, 10), (0, 0, np.inf, 10)):
        with pytest.raises(LearnedRefused) as info:
            estimator.estimate(rgb, K, 1, box)
        assert info.value.cause == "bad-input"


def test_detections_on_constant_and_noise_images_are_finite(estimator: LearnedEstimator) -> None:
    rng = np.random.default_rng(0)
    for rgb in (np.zeros((200, 320, 3), np.uint8), np.full((400, 640, 3), 255, np.uint8),
                rng.integers(0, 256, size=(123, 77, 3), dtype=np.uint8)):
        for d in estimator.detect(rgb, K, min_score=0.0):
            assert all(math.isfinite(b) for b in d.box) and 0.0 <= d.score <= 1.0 and d.obj_id in (1, 2)


def test_a_non_finite_loss_stops_training_naming_the_network_and_step(tmp_path, monkeypatch) -> None:
    import torch

    from brave6d.evaluation.learned import losses, training
    from learned_helpers import DEMO_SPEC, write_models
    from brave6d.synth import SynthOptions, synthesize

    synthesize(DEMO_SPEC, tmp_path / "synth", SynthOptions(images=3, seed=0, width=160, height=100))
    models = write_models(DEMO_SPEC, tmp_path / "models")
    monkeypatch.setattr(losses, "pose_loss", lambda *a, **k: torch.tensor(float("nan"), requires_grad=True))
    preset = PRESET.with_overrides(detector_steps=3, pose_steps=3, work_width=160)
    with pytest.raises(BraveError, match=r"the pose loss is nan at step 0"):
        training.train_learned(tmp_path / "synth", models, tmp_path / "out", preset, "cpu", show_progress=False)
    assert not (tmp_path / "out" / "model.pt").exists()


def test_a_non_finite_loss_read_late_still_names_its_step_and_leaves_no_checkpoint_after_it(tmp_path,
                                                                                           monkeypatch) -> None:
    """A GPU reads its losses every few steps: a NaN at pose step 5, read with steps 4-7, names step 5,
    and the checkpoint holds the pose network as of step 4 (finite), not the steps after the NaN."""
    import torch

    from brave6d.evaluation.learned import losses, training
    from learned_helpers import DEMO_SPEC, write_models
    from brave6d.synth import SynthOptions, synthesize

    synthesize(DEMO_SPEC, tmp_path / "synth", SynthOptions(images=3, seed=0, width=160, height=100))
    models = write_models(DEMO_SPEC, tmp_path / "models")
    real, calls = losses.pose_loss, []

    def nan_from_step_5(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - the loss's own signature
        calls.append(1)
        loss = real(*args, **kwargs)
        return loss * float("nan") if len(calls) > 5 else loss

    monkeypatch.setattr(losses, "pose_loss", nan_from_step_5)
    monkeypatch.setattr(training, "loss_reads", lambda device: 4)
    preset = PRESET.with_overrides(detector_steps=2, pose_steps=12, work_width=160, checkpoint_every=4)
    with pytest.raises(BraveError, match=r"the pose loss is nan at step 5"):
        training.train_learned(tmp_path / "synth", models, tmp_path / "out", preset, "cpu", show_progress=False,
                               ahead=2)
    assert not (tmp_path / "out" / "model.pt").exists() and len(calls) == 8  # stopped at the read of 4-7
    saved = torch.load(tmp_path / "out" / "checkpoint.pt", weights_only=True)["phases"]["pose"]
    assert saved["step"] == 4 and all(torch.isfinite(v).all() for v in saved["net"].values() if v.is_floating_point())


def test_a_preset_trains_the_same_steps_whatever_the_precision_and_the_model_says_what_ran(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    import torch

    from brave6d.evaluation.learned import training
    from brave6d.evaluation.learned.presets import PRESETS

    cpu = torch.device("cpu")
    for name, preset in PRESETS.items():  # one preset, one schedule: precision changes the time only
        for native in (True, False):
            monkeypatch.setattr(training, "native_bf16", lambda device, native=native: native)
            ran = training.resolve_precision(preset, cpu)
            assert ran.precision == (preset.precision if preset.precision != "auto" else ("bf16" if native else "fp32"))
            assert {k for k, v in ran.to_json().items() if preset.to_json()[k] != v} <= {"precision"}, name
    auto = get_learn_preset("fast")
    assert auto.precision == "auto"
    fast, long = auto.to_json(), get_learn_preset("long").to_json()  # the same networks, images and detector
    assert {k for k in fast if fast[k] != long[k]} == {"name", "pose_steps", "checkpoint_every"}
    with caplog.at_level("WARNING"):  # asked for explicitly, bf16 runs (emulated), and says so
        assert training.resolve_precision(auto.with_overrides(precision="bf16"), cpu).precision == "bf16"
    assert "without native bfloat16" in caplog.text


def test_a_process_capped_below_bfloat16_trains_as_a_cpu_without_it(monkeypatch: pytest.MonkeyPatch) -> None:
    # ATEN_CPU_CAPABILITY=avx2 / ONEDNN_MAX_CPU_ISA=AVX2 make a bfloat16 CPU run as an AVX2-only one: native_bf16
    # must then say no, so such a process trains (and is timed) in fp32 as that CPU would
    import torch

    from brave6d.evaluation.learned import training

    cpu = torch.device("cpu")
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True)
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX512")
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)
    assert training.native_bf16(cpu)
    for isa in ("AVX2", "avx512_core", "AVX2_VNNI"):
        monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", isa)
        assert not training.native_bf16(cpu), isa
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX512_CORE_BF16")
    assert training.native_bf16(cpu)
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX2")
    assert not training.native_bf16(cpu)
    assert training.resolve_precision(get_learn_preset("fast"), cpu).precision == "fp32"


def test_preset_overrides_from_the_command_line_keep_types_and_name_bad_fields() -> None:
    from brave6d.evaluation.learned.cli import parse_overrides

    fast = get_learn_preset("fast")
    changed = fast.with_overrides(**parse_overrides(fast, ["work_width=640", "detector_lr=1e-3"]))
    assert changed.work_width == 640 and isinstance(changed.work_width, int) and changed.detector_lr == 1e-3
    assert fast.with_overrides(**parse_overrides(fast, ["precision=bf16"])).precision == "bf16"
    for bad, says in (("colour=1", "a field of the preset"), ("work_width", "FIELD=VALUE"),
                      ("work_width=6.5", "not a valid integer"), ("detector_lr=fast", "not a valid number"),
                      ("name=3", "a field of the preset")):
        with pytest.raises(BraveError, match=says):
            parse_overrides(fast, [bad])
    with pytest.raises(BraveError, match=r"precision must be one of auto, fp32, bf16, got 'fp16'"):
        fast.with_overrides(**parse_overrides(fast, ["precision=fp16"]))
    with pytest.raises(BraveError, match="crop_source_width"):  # the preset's own checks still apply
        fast.with_overrides(**parse_overrides(fast, ["work_width=1280"]))


def test_the_estimators_crop_follows_the_box_where_the_preset_says_and_older_models_keep_one_size() -> None:
    preset = PRESET.with_overrides(crop_source_width=640, crop_px=128, crop_px_min=48)
    following = LearnedEstimator(untrained_model(preset, [1]))
    # a box of 40 px in a 320-wide image is 80 px at the crops' source width: its padded crop 120 px -> 128
    assert following.crop_px(320, (100.0, 100.0, 140.0, 130.0)) == 128
    assert following.crop_px(640, (100.0, 100.0, 120.0, 110.0)) == 48  # 30 px padded: the smallest crop
    assert following.crop_px(640, (100.0, 100.0, 140.0, 120.0)) == 64  # 60 px padded: its own size, to 16
    older = untrained_model(PRESET, [1])
    older.preset.pop("crop_px_min")  # a model trained before crops followed their boxes
    assert LearnedEstimator(older).crop_px(640, (0.0, 0.0, 300.0, 300.0)) == PRESET.crop_px
    with pytest.raises(BraveError, match="crop_px_min"):
        PRESET.with_overrides(crop_px_min=96, crop_px=64)

"""Camera-side effects: each changes the output only when listed; unlisted ones cost nothing."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import brave6d.capture.effects as fx
from brave6d.core.camera import PinholeCamera
from brave6d.core.spec import (
    DefocusBlur,
    DepthNoise,
    EffectsSpec,
    ExposureChange,
    MotionBlur,
    SensorNoise,
    Vignetting,
)
from brave6d.core.transforms import look_at
from brave6d.capture.scene_model import MeshPart, SceneModel
from brave6d.capture.sim_camera import SimCamera

CAMERA = PinholeCamera.from_hfov(96, 64, 70.0)
WORLD_T_CAM = look_at((0.05, -0.12, 0.35), (0.0, 0.0, 0.0))


def _scene() -> SceneModel:
    rng = np.random.default_rng(3)
    texture = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    table = MeshPart("table", 1000, np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float),
                     np.array([[0, 1, 2], [0, 2, 3]]), uv=np.array([[0, 0], [8, 0], [8, 8], [0, 8]], float),
                     texture=texture)
    s = 0.03
    corners = np.array([[x, y, z] for x in (-s, s) for y in (-s, s) for z in (0.0, 2 * s)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    box = MeshPart("box", 1, corners, faces, color=(200, 40, 40))
    return SceneModel([table, box])


MODEL = _scene()

#: Parameters that visibly change the output, per effect.
STRONG: dict[str, dict[str, Any]] = {
    "sensor_noise": {"sigma": 3.0, "shot_noise": 0.5},
    "motion_blur": {"exposure_s": 0.03, "residual_speed_m_s": 0.2},
    "defocus_blur": {"focus_distance_m": 1.0, "aperture_px": 2.0},
    "lens_distortion": {"dist": [0.2, -0.1, 0.0, 0.0, 0.0]},
    "vignetting": {"strength": 0.5},
    "exposure_change": {"max_gain": 2.0},
    "depth_noise": {"sigma_at_1m": 0.01, "sigma_const": 0.001, "dropout": 0.05},
    "robot_pose_error": {},
    "time_offset": {},
}
#: What each effect may change: (rgb, depth).
CHANGES = {
    "sensor_noise": (True, False), "motion_blur": (True, False), "defocus_blur": (True, False),
    "lens_distortion": (True, True), "vignetting": (True, False), "exposure_change": (True, False),
    "depth_noise": (False, True), "robot_pose_error": (False, False), "time_offset": (False, False),
}


def moving_pose(t: float) -> np.ndarray:
    """The camera slides along its x axis at 0.3 m/s (so motion blur has real motion)."""
    T = WORLD_T_CAM.copy()
    T[:3, 3] += T[:3, 0] * 0.3 * t
    return T


def camera(effects: EffectsSpec, seed: int = 0) -> SimCamera:
    return SimCamera(MODEL, CAMERA, effects, moving_pose, lambda: 0.0, seed=seed, depth_range=(0.05, 2.0))


def test_all_spec_effects_are_covered() -> None:
    assert set(CHANGES) == set(EffectsSpec.model_fields)
    assert set(fx.CAMERA_EFFECTS) | set(fx.GEOMETRIC_EFFECTS) | set(fx.ROBOT_EFFECTS) == set(EffectsSpec.model_fields)


def test_nothing_listed_gives_the_effect_free_render_bytes() -> None:
    cam = camera(EffectsSpec())
    frame = cam.capture()
    truth = cam.render(WORLD_T_CAM)
    assert frame.rgb.tobytes() == truth.rgb.tobytes()
    assert frame.depth_m is not None and frame.depth_m.tobytes() == truth.depth_m.tobytes()
    assert frame.extras["effects"] == [] and frame.extras["effect_times_s"] == {}


def test_unlisted_effects_are_never_called_and_draw_no_random_numbers(monkeypatch: pytest.MonkeyPatch) -> None:
    def explode(*args: Any) -> Any:
        raise AssertionError("an unlisted effect ran")

    monkeypatch.setattr(fx, "PIPELINE", tuple(fx.EffectStep(s.name, s.domain, explode) for s in fx.PIPELINE))
    robot_only = EffectsSpec.model_validate({"robot_pose_error": {}, "time_offset": {}})
    for effects in (EffectsSpec(), robot_only):
        cam = camera(effects)
        monkeypatch.setattr(cam, "rng_for", explode)
        frame = cam.capture()
        assert frame.rgb.tobytes() == cam.render(WORLD_T_CAM).rgb.tobytes()
    # The same trap fires as soon as one effect is listed (so the test above can fail).
    cam = camera(EffectsSpec.model_validate({"vignetting": {}}))
    with pytest.raises(AssertionError, match="unlisted effect ran"):
        cam.capture()


@pytest.mark.parametrize("name", sorted(CHANGES))
def test_listing_one_effect_changes_only_what_it_should(name: str) -> None:
    baseline = camera(EffectsSpec()).capture()
    frame = camera(EffectsSpec.model_validate({name: STRONG[name]})).capture()
    rgb_changed = frame.rgb.tobytes() != baseline.rgb.tobytes()
    depth_changed = frame.depth_m.tobytes() != baseline.depth_m.tobytes()  # type: ignore[union-attr]
    assert (rgb_changed, depth_changed) == CHANGES[name]
    camera_side = name not in fx.ROBOT_EFFECTS
    assert frame.extras["effects"] == ([name] if camera_side else [])
    if name in fx.CAMERA_EFFECTS:
        assert set(frame.extras["effect_times_s"]) == {name}


def test_effects_are_reproducible_and_independent() -> None:
    noise = {"sensor_noise": STRONG["sensor_noise"]}
    both = {**noise, "vignetting": STRONG["vignetting"], "depth_noise": STRONG["depth_noise"]}
    a = camera(EffectsSpec.model_validate(noise), seed=7)
    b = camera(EffectsSpec.model_validate(noise), seed=7)
    fa, fb = a.capture(), b.capture()
    assert fa.rgb.tobytes() == fb.rgb.tobytes()
    assert a.capture().rgb.tobytes() != fa.rgb.tobytes()  # the next frame draws new noise
    assert camera(EffectsSpec.model_validate(noise), seed=8).capture().rgb.tobytes() != fa.rgb.tobytes()
    # Listing other effects does not change the sensor-noise draws (own generator per effect).
    c = camera(EffectsSpec.model_validate(both), seed=7)
    noise_only = a.rng_for("sensor_noise", 0).standard_normal(5)
    assert np.array_equal(noise_only, c.rng_for("sensor_noise", 0).standard_normal(5))


def test_effect_order_is_physical() -> None:
    assert [s.name for s in fx.PIPELINE] == ["defocus_blur", "motion_blur", "vignetting", "exposure_change",
                                            "sensor_noise", "depth_noise"]
    domains = [s.domain for s in fx.PIPELINE]
    assert domains == sorted(domains, key=["linear", "dn", "depth"].index)


def test_depth_noise_grows_with_z_squared() -> None:
    params = DepthNoise(sigma_at_1m=0.01, sigma_const=0.0)
    ctx = _ctx(np.full((64, 96), 1.0, np.float32))
    for z in (0.5, 1.0, 2.0):
        depth = np.full((200, 200), z, np.float32)
        _, noisy = fx.depth_noise(np.zeros((1, 1, 3), np.float32), depth, params, np.random.default_rng(0),
                                  fx.EffectContext(ctx.camera, ctx.rays_cam, ctx.z_m, ctx.world_T_cam, depth_range=(0, 10)))
        assert noisy is not None
        assert np.std(noisy - z) == pytest.approx(0.01 * z * z, rel=0.05)


def test_vignetting_profile() -> None:
    gain = fx.vignetting_gain(101, 51, 50.0, 25.0, 0.3)
    assert gain[25, 50] == pytest.approx(1.0)
    assert gain[0, 0] == pytest.approx(0.7) and gain[50, 100] == pytest.approx(0.7)


def test_motion_blur_follows_the_camera_motion() -> None:
    """A camera sliding sideways smears a vertical edge horizontally, not vertically."""
    h, w = 64, 96
    image = np.zeros((h, w, 3), np.float32)
    image[:, w // 2:] = 1.0
    ctx = _ctx(np.full((h, w), 0.5, np.float32))
    T0 = np.eye(4)

    def slide(t: float) -> np.ndarray:
        T = T0.copy()
        T[0, 3] = 0.5 * t
        return T

    ctx = fx.EffectContext(ctx.camera, ctx.rays_cam, ctx.z_m, T0, 0.0, slide)
    out, _ = fx.motion_blur(image, None, MotionBlur(exposure_s=0.02, residual_speed_m_s=0.0),
                            np.random.default_rng(0), ctx)
    row = out[h // 2, :, 0]
    ramp = np.flatnonzero((row > 0.02) & (row < 0.98))
    blur_px = 0.5 * 0.02 * CAMERA.fx / 0.5  # 10 mm at 0.5 m
    assert abs(len(ramp) - blur_px) <= 2
    assert np.allclose(out[:, :, 0], out[h // 2, :, 0][None, :], atol=1e-6)  # no vertical smear


def test_defocus_is_sharp_at_the_focus_distance() -> None:
    image = (np.random.default_rng(1).random((64, 96, 3)) > 0.5).astype(np.float32)
    params = DefocusBlur(focus_distance_m=0.4, aperture_px=3.0)
    sharp, _ = fx.defocus_blur(image, None, params, np.random.default_rng(0), _ctx(np.full((64, 96), 0.4, np.float32)))
    blurred, _ = fx.defocus_blur(image, None, params, np.random.default_rng(0), _ctx(np.full((64, 96), 0.2, np.float32)))
    assert np.array_equal(sharp, image)
    assert blurred.std() < 0.7 * image.std()
    assert abs(float(blurred.mean()) - float(image.mean())) < 0.02  # blur keeps energy


# ----------------------------------------------------------------------------- property tests
def _ctx(z: np.ndarray) -> fx.EffectContext:
    h, w = z.shape
    cam = CAMERA.scaled(w, h) if (w, h) != (CAMERA.width, CAMERA.height) else CAMERA
    grid = cam.pixel_grid()
    rays = np.c_[cam.normalized_rays(grid), np.ones(len(grid))]
    return fx.EffectContext(cam, rays, z.astype(np.float32), np.eye(4), 0.0, None, (0.05, 3.0))


finite = {"allow_nan": False, "allow_infinity": False}
params_strategy = st.one_of(
    st.builds(SensorNoise, sigma=st.floats(0, 1e3, **finite), shot_noise=st.floats(0, 1e3, **finite)),
    st.builds(MotionBlur, exposure_s=st.floats(1e-6, 1.0, **finite), residual_speed_m_s=st.floats(0, 5.0, **finite)),
    st.builds(DefocusBlur, focus_distance_m=st.floats(1e-3, 100, **finite), aperture_px=st.floats(0, 100, **finite)),
    st.builds(Vignetting, strength=st.floats(0, 1, **finite)),
    st.builds(ExposureChange, max_gain=st.floats(1, 4, **finite)),
    st.builds(DepthNoise, sigma_at_1m=st.floats(0, 10, **finite), sigma_const=st.floats(0, 10, **finite),
              dropout=st.floats(0, 1, **finite)),
)
FUNCTIONS = {SensorNoise: fx.sensor_noise, MotionBlur: fx.motion_blur, DefocusBlur: fx.defocus_blur,
             Vignetting: fx.vignetting, ExposureChange: fx.exposure_change, DepthNoise: fx.depth_noise}


@given(params=params_strategy, kind=st.sampled_from(["zeros", "ones", "bright", "random"]),
       z_kind=st.sampled_from(["empty", "zero", "near", "random"]), seed=st.integers(0, 2**32 - 1),
       moving=st.booleans())
def test_effects_keep_values_finite_and_in_range(params: Any, kind: str, z_kind: str, seed: int, moving: bool) -> None:
    h, w = 24, 32
    rng = np.random.default_rng(seed)
    image = {"zeros": np.zeros((h, w, 3)), "ones": np.ones((h, w, 3)), "bright": np.full((h, w, 3), 3.0),
             "random": rng.random((h, w, 3))}[kind].astype(np.float32)
    z = {"empty": np.full((h, w), np.inf), "zero": np.zeros((h, w)), "near": np.full((h, w), 1e-4),
         "random": rng.uniform(0.05, 5.0, (h, w))}[z_kind].astype(np.float32)
    depth = np.where(np.isfinite(z) & (z >= 0.05) & (z <= 3.0), z, 0).astype(np.float32)
    ctx = _ctx(z)
    if moving:
        ctx = fx.EffectContext(ctx.camera, ctx.rays_cam, ctx.z_m, ctx.world_T_cam, 0.0,
                               lambda t: look_at((t, 0.1 * t, 0.0), (t, 0.1 * t + 0.3, 1.0)), ctx.depth_range)
    image_in, depth_in = image.copy(), depth.copy()
    dn_domain = isinstance(params, SensorNoise)
    source = fx.linear_to_srgb_dn(image) if dn_domain else image
    out, out_depth = FUNCTIONS[type(params)](source, depth, params, np.random.default_rng(seed), ctx)
    assert np.array_equal(image, image_in) and np.array_equal(depth, depth_in)  # inputs untouched
    assert out.shape == (h, w, 3) and out.dtype == np.float32
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    if dn_domain:
        assert np.all(out <= 255)
    assert out_depth is not None and out_depth.dtype == np.float32 and out_depth.shape == (h, w)
    assert np.all(np.isfinite(out_depth)) and np.all(out_depth >= 0)
    valid = out_depth > 0
    assert np.all((out_depth[valid] >= 0.05) & (out_depth[valid] <= 3.0))
    assert np.all(out_depth[depth == 0] == 0)  # no depth appears from nowhere
    rgb = fx.quantize_dn(out if dn_domain else fx.linear_to_srgb_dn(out))
    assert rgb.dtype == np.uint8


@given(gain=st.floats(0.0, 10.0, allow_nan=False), value=st.floats(-1.0, 5.0, allow_nan=False))
def test_quantisation_is_clipped(gain: float, value: float) -> None:
    rgb = fx.radiance_to_rgb8(np.full((2, 2, 3), value * gain, np.float32))
    assert rgb.dtype == np.uint8
    expected = 0 if value * gain <= 0 else (255 if value * gain >= 1 else None)
    if expected is not None:
        assert np.all(rgb == expected)

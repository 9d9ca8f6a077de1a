"""Camera-side simulation effects: one small pure function per effect, run in a fixed order.

Every effect has the signature ``effect(image, depth, params, rng, ctx) -> (image, depth)``:
it returns new arrays (inputs are never modified), draws random numbers only from ``rng``
and reads the frame's geometry from ``ctx`` (:class:`EffectContext`).

Physical order (:data:`PIPELINE`), applied by :func:`apply_camera_effects`:

1. on linear radiance (float32 RGB, 1.0 = white paper under full light):
   ``defocus_blur`` (optics), ``motion_blur`` (integration over the exposure),
   ``vignetting`` (lens fall-off), ``exposure_change`` (per-frame gain);
2. encoding to sRGB digital numbers (DN, float32 0..255, the camera's ISP);
3. on DN: ``sensor_noise``;
4. quantisation to uint8 (round half to even, clipped to 0..255);
5. on depth (float32 metres, 0 = no data): ``depth_noise``.

``lens_distortion`` is geometric: :class:`~brave6d.capture.sim_camera.SimCamera` casts its rays
through the distorted model, so it costs nothing per frame here. ``robot_pose_error`` and
``time_offset`` belong to the simulated robot.

An effect that is not listed in the :class:`~brave6d.core.spec.EffectsSpec` is never called, never
timed and never asks for a random generator: it costs nothing and changes nothing. Each listed
effect gets its own generator from ``rng_for(name)``, so listing one effect does not change
the random draws of another.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.spec import DefocusBlur, DepthNoise, EffectsSpec, ExposureChange, MotionBlur, SensorNoise, Vignetting
from brave6d.core.transforms import invert, transform_points
from brave6d.capture.scene_model import linear_to_srgb_dn

FloatImage = NDArray[np.float32]
Depth = NDArray[np.float32] | None

#: z used for pixels that hit nothing when computing motion-blur flow (far background).
BACKGROUND_Z_M = 100.0
#: Largest defocus blur radius (px); larger radii are clipped.
MAX_DEFOCUS_RADIUS_PX = 16.0
#: Blur radii (px) rendered as layers; a pixel interpolates between the two around its radius.
DEFOCUS_LAYERS_PX = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 16.0)
#: Most samples along the motion path per pixel (a longer blur is sampled more sparsely).
MAX_MOTION_SAMPLES = 48
#: Motion-blur flow is computed every this many pixels and interpolated in between.
MOTION_FLOW_STEP = 4

#: Effects handled outside this module.
GEOMETRIC_EFFECTS = ("lens_distortion",)
ROBOT_EFFECTS = ("robot_pose_error", "time_offset")


@dataclass(frozen=True)
class EffectContext:
    """What an effect may know about the frame besides the image.

    ``camera``: the model the image was rendered with (with distortion when listed);
    ``rays_cam``: (H*W, 3) camera-frame ray directions with z = 1 at the pixel centres
    (row-major); ``z_m``: (H, W) true z-depth, inf where nothing was hit; ``world_T_cam``:
    the true pose at ``time_s`` (mid-exposure); ``pose_at(t)``: the true pose at any time
    (None = the camera does not move); ``depth_range``: valid depth (metres).
    """

    camera: PinholeCamera
    rays_cam: NDArray[np.float64]
    z_m: NDArray[np.float32]
    world_T_cam: NDArray[np.float64]
    time_s: float = 0.0
    pose_at: Callable[[float], NDArray[np.float64]] | None = None
    depth_range: tuple[float, float] = (0.0, math.inf)


EffectFn = Callable[[FloatImage, Depth, Any, np.random.Generator, EffectContext], tuple[FloatImage, Depth]]


@dataclass(frozen=True)
class EffectStep:
    """One step of the pipeline: the spec field name, the data it works on, the function."""

    name: str
    domain: Literal["linear", "dn", "depth"]
    apply: EffectFn


@dataclass
class EffectsOutput:
    """Result of :func:`apply_camera_effects`."""

    rgb: NDArray[np.uint8]
    depth_m: Depth
    applied: list[str] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------- conversions
def quantize_dn(dn: NDArray[np.floating]) -> NDArray[np.uint8]:
    """sRGB digital numbers (float) -> uint8 (clip to 0..255, round half to even)."""
    return np.rint(np.clip(dn, 0.0, 255.0)).astype(np.uint8)


def radiance_to_rgb8(radiance: FloatImage) -> NDArray[np.uint8]:
    """Linear radiance -> 8-bit sRGB exactly as the effect pipeline does without effects."""
    return quantize_dn(linear_to_srgb_dn(radiance))


# ----------------------------------------------------------------------------- linear-radiance effects
def disc_kernel(radius_px: float) -> NDArray[np.float32]:
    """Normalised anti-aliased disc of ``radius_px`` (4x4 sub-samples per kernel pixel)."""
    if radius_px < 0.25:
        return np.ones((1, 1), dtype=np.float32)
    half = int(math.ceil(radius_px))
    sub = (np.arange(4) + 0.5) / 4.0 - 0.5
    offsets = (np.arange(-half, half + 1)[:, None] + sub[None, :]).ravel()
    inside = (offsets[:, None] ** 2 + offsets[None, :] ** 2) <= radius_px**2
    size = 2 * half + 1
    coverage = inside.reshape(size, 4, size, 4).mean(axis=(1, 3))
    return (coverage / coverage.sum()).astype(np.float32)


def defocus_blur(image: FloatImage, depth: Depth, params: DefocusBlur, rng: np.random.Generator,
                 ctx: EffectContext) -> tuple[FloatImage, Depth]:
    """Disc blur of radius ``aperture_px * |1/z - 1/focus_distance_m|`` px (thin-lens circle of
    confusion; ``aperture_px`` is the radius at one dioptre of defocus).

    Approximated with layers: the image is blurred at the radii of :data:`DEFOCUS_LAYERS_PX`
    and each pixel interpolates between the two layers around its own radius (pixels that hit
    nothing count as infinitely far). Occlusion edges are not treated specially. Depth is
    unchanged.
    """
    z = ctx.z_m
    inv_z = np.where(np.isfinite(z) & (z > 0), 1.0 / np.maximum(z, 1e-6), 0.0)
    radius = np.clip(params.aperture_px * np.abs(inv_z - 1.0 / params.focus_distance_m), 0.0, MAX_DEFOCUS_RADIUS_PX)
    radius = radius.astype(np.float32)
    top = float(radius.max())
    layers = [r for r in DEFOCUS_LAYERS_PX if r < top]
    layers.append(next((r for r in DEFOCUS_LAYERS_PX if r >= top), MAX_DEFOCUS_RADIUS_PX))
    if len(layers) == 1:  # every radius is 0
        return image.copy(), depth
    lv = np.asarray(layers, dtype=np.float64)
    out = np.zeros_like(image)
    for k, level in enumerate(lv):
        weight = np.interp(radius, lv, np.eye(len(lv))[k]).astype(np.float32)  # tent around this layer
        if not weight.any():
            continue
        layer = image if level == 0 else cv2.filter2D(image, -1, disc_kernel(float(level)), borderType=cv2.BORDER_REFLECT)
        out += layer * weight[..., None]
    return out, depth


def motion_blur(image: FloatImage, depth: Depth, params: MotionBlur, rng: np.random.Generator,
                ctx: EffectContext) -> tuple[FloatImage, Depth]:
    """Average of the image over the exposure, following each pixel's image-space motion.

    The camera moves from ``pose_at(t - exposure/2)`` to ``pose_at(t + exposure/2)`` plus a
    random residual drift (speed ``residual_speed_m_s``, uniform direction, the arm's
    vibration while "still"). Each pixel's scene point (from the true depth) is projected at
    both ends; the output averages the sharp image sampled along that path (``2p - uv(s)``,
    exact for locally constant flow). Depth is unchanged.
    """
    h, w = image.shape[:2]
    half = params.exposure_s / 2.0
    T_mid = np.asarray(ctx.world_T_cam, dtype=np.float64)
    if ctx.pose_at is not None:
        T0 = np.array(ctx.pose_at(ctx.time_s - half), dtype=np.float64)
        T1 = np.array(ctx.pose_at(ctx.time_s + half), dtype=np.float64)
    else:
        T0, T1 = T_mid.copy(), T_mid.copy()
    if params.residual_speed_m_s > 0:
        direction = rng.standard_normal(3)
        direction /= max(float(np.linalg.norm(direction)), 1e-12)
        drift = direction * params.residual_speed_m_s * half
        T0[:3, 3] -= drift
        T1[:3, 3] += drift
    # Flow on a coarse grid (every MOTION_FLOW_STEP px), bilinearly upsampled: the flow is smooth
    # except at occlusion edges, and projecting every pixel through the distortion is costly.
    step = MOTION_FLOW_STEP
    rows = np.arange(0, h, step)
    cols = np.arange(0, w, step)
    z = ctx.z_m[np.ix_(rows, cols)].astype(np.float64)
    z = np.where(np.isfinite(z) & (z > 0), z, BACKGROUND_Z_M).ravel()
    rays = ctx.rays_cam.reshape(h, w, 3)[np.ix_(rows, cols)].reshape(-1, 3)
    points_cam = rays * z[:, None]
    grid_u, grid_v = np.meshgrid(cols.astype(np.float64), rows.astype(np.float64))
    grid = np.stack([grid_u.ravel(), grid_v.ravel()], axis=1)
    flows = []
    for T in (T0, T1):
        proj = ctx.camera.project(transform_points(invert(T) @ T_mid, points_cam))
        flow = np.where(proj.valid[:, None], proj.uv - grid, 0.0).reshape(len(rows), len(cols), 2)
        # Upsample so that coarse sample (i, j) lands on pixel (i * step, j * step).
        map_x = (np.arange(w, dtype=np.float32) / step)[None, :].repeat(h, axis=0)
        map_y = (np.arange(h, dtype=np.float32) / step)[:, None].repeat(w, axis=1)
        flows.append(cv2.remap(flow.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE))
    span = np.linalg.norm(flows[1] - flows[0], axis=2)
    longest = float(np.percentile(span, 99.5)) if span.size else 0.0
    n = int(np.clip(math.ceil(longest / 0.5) + 1, 1, MAX_MOTION_SAMPLES))
    pix_x = np.arange(w, dtype=np.float32)[None, :]
    pix_y = np.arange(h, dtype=np.float32)[:, None]
    acc = np.zeros_like(image)
    for k in range(n):
        s = np.float32((k + 0.5) / n)
        f = flows[0] + s * (flows[1] - flows[0])
        acc += cv2.remap(image, pix_x - f[..., 0], pix_y - f[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).reshape(image.shape)
    return (acc / np.float32(n)).astype(np.float32), depth


def vignetting_gain(width: int, height: int, cx: float, cy: float, strength: float) -> NDArray[np.float32]:
    """(H, W) gain ``1 - strength * r^2``, r = distance to (cx, cy) over the farthest corner's."""
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], dtype=np.float64)
    r_max2 = max(float(np.max(np.sum((corners - (cx, cy)) ** 2, axis=1))), 1e-12)
    u = (np.arange(width, dtype=np.float64) - cx) ** 2
    v = (np.arange(height, dtype=np.float64) - cy) ** 2
    return (1.0 - strength * (v[:, None] + u[None, :]) / r_max2).astype(np.float32)


def vignetting(image: FloatImage, depth: Depth, params: Vignetting, rng: np.random.Generator,
               ctx: EffectContext) -> tuple[FloatImage, Depth]:
    """Radial fall-off ``1 - strength * r^2`` around the principal point (r = 1 at the farthest
    corner). Depth is unchanged."""
    h, w = image.shape[:2]
    gain = vignetting_gain(w, h, ctx.camera.cx, ctx.camera.cy, params.strength)
    return image * gain[..., None], depth


def exposure_change(image: FloatImage, depth: Depth, params: ExposureChange, rng: np.random.Generator,
                    ctx: EffectContext) -> tuple[FloatImage, Depth]:
    """Multiply by one gain per frame, log-uniform in ``[1/max_gain, max_gain]``. Depth unchanged."""
    log_max = math.log(params.max_gain)
    gain = math.exp(rng.uniform(-log_max, log_max)) if log_max > 0 else 1.0
    return image * np.float32(gain), depth


# ----------------------------------------------------------------------------- DN and depth effects
def sensor_noise(image_dn: FloatImage, depth: Depth, params: SensorNoise, rng: np.random.Generator,
                 ctx: EffectContext) -> tuple[FloatImage, Depth]:
    """Gaussian noise on sRGB digital numbers: std ``sqrt(sigma^2 + shot_noise * DN)`` (read noise
    plus signal-dependent shot noise; ``shot_noise`` is the variance per DN). Result clipped to
    0..255; depth unchanged."""
    signal = np.clip(image_dn, 0.0, 255.0)
    std = np.sqrt(np.float32(params.sigma) ** 2 + np.float32(params.shot_noise) * signal)
    noise = rng.standard_normal(image_dn.shape, dtype=np.float32)
    return np.clip(signal + noise * std, 0.0, 255.0).astype(np.float32), depth


def depth_noise(image: FloatImage, depth: Depth, params: DepthNoise, rng: np.random.Generator,
                ctx: EffectContext) -> tuple[FloatImage, Depth]:
    """Stereo-like depth noise: std ``sigma_const + sigma_at_1m * z^2``; each valid pixel drops
    out (0) with probability ``dropout``; values leaving the depth range become 0. RGB unchanged."""
    if depth is None:
        return image, depth
    d = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    d_safe = np.where(valid, d, np.float32(0.0))
    std = np.float32(params.sigma_const) + np.float32(params.sigma_at_1m) * d_safe * d_safe
    noisy = d_safe + rng.standard_normal(d.shape, dtype=np.float32) * std
    lo, hi = ctx.depth_range
    keep = valid & np.isfinite(noisy) & (noisy >= lo) & (noisy <= hi) & (noisy > 0)
    if params.dropout > 0:
        keep &= rng.random(d.shape) >= params.dropout
    return image, np.where(keep, noisy, np.float32(0.0)).astype(np.float32)


#: The fixed physical order of the camera-side effects.
PIPELINE: tuple[EffectStep, ...] = (
    EffectStep("defocus_blur", "linear", defocus_blur),
    EffectStep("motion_blur", "linear", motion_blur),
    EffectStep("vignetting", "linear", vignetting),
    EffectStep("exposure_change", "linear", exposure_change),
    EffectStep("sensor_noise", "dn", sensor_noise),
    EffectStep("depth_noise", "depth", depth_noise),
)

#: Names of the effects this module runs (in order).
CAMERA_EFFECTS = tuple(step.name for step in PIPELINE)


def apply_camera_effects(radiance: FloatImage, depth: Depth, effects: EffectsSpec, ctx: EffectContext,
                         rng_for: Callable[[str], np.random.Generator],
                         pipeline: Sequence[EffectStep] | None = None) -> EffectsOutput:
    """Run the listed camera-side effects in the fixed order and quantise the image.

    ``rng_for(name)`` is called once per *listed* effect (never for an unlisted one). With
    nothing listed the result is exactly ``radiance_to_rgb8(radiance)`` and ``depth``.
    """
    steps = PIPELINE if pipeline is None else pipeline
    out = EffectsOutput(rgb=np.zeros((0, 0, 3), np.uint8), depth_m=depth)
    image = radiance
    dn: FloatImage | None = None
    for step in steps:
        params = getattr(effects, step.name)
        if params is None:
            continue
        if step.domain == "depth" and depth is None:
            continue
        if step.domain == "dn" and dn is None:
            dn = linear_to_srgb_dn(image)  # not timed: the effect-free path encodes too
        start = time.perf_counter()
        if step.domain == "dn":
            assert dn is not None
            dn, depth = step.apply(dn, depth, params, rng_for(step.name), ctx)
        elif step.domain == "linear":
            image, depth = step.apply(image, depth, params, rng_for(step.name), ctx)
        else:
            _, depth = step.apply(image, depth, params, rng_for(step.name), ctx)
        out.timings_s[step.name] = time.perf_counter() - start
        out.applied.append(step.name)
    out.rgb = quantize_dn(dn) if dn is not None else radiance_to_rgb8(image)
    out.depth_m = depth
    return out

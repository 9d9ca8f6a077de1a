"""One pixel-centre convention end to end (issue 17): the simulator's images and the splat's.

The project's K is OpenCV's (pixel ``(u, v)`` centred at integer ``(u, v)``): the simulator and
the mask ray casters cast their rays through those centres, and the rasterizer converts K into
gsplat's +0.5 convention itself. A splat built from the same geometry as a simulated scene must
therefore render the same image, not one shifted by half a pixel.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from brave6d.core.camera import PinholeCamera
from brave6d.core.transforms import invert, look_at
from brave6d.capture.scene_model import MeshPart, SceneModel, srgb_to_linear
from brave6d.capture.sim_camera import SimCamera
from brave6d.training.rasterizer import rasterize

CAMERA = PinholeCamera(128, 96, 150.0, 150.0, 61.3, 49.8)  # principal point off the centre on purpose
SIDE_M = 0.3  # the textured square, centred on the world origin in the plane z = 0
TEXELS = 512
GRID_M = 0.002  # splat: one Gaussian every 2 mm (about 1 px at 0.3 m) ...
SIGMA_M = 0.002  # ... of 2 mm (so the sum of the Gaussians is smooth)
STRIDE = 8  # Gaussians rendered together lie STRIDE * 2 mm apart: their footprints never overlap


def _smooth_texture(seed: int = 7) -> np.ndarray:
    """Band-limited random colours (blurred noise, features of a few pixels in the view)."""
    noise = np.random.default_rng(seed).random((TEXELS, TEXELS, 3)).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 8.0)
    lo, hi = blurred.min(axis=(0, 1)), blurred.max(axis=(0, 1))
    return (20 + 215 * (blurred - lo) / (hi - lo)).round().astype(np.uint8)


def _sim_image(texture: np.ndarray, world_T_cam: np.ndarray) -> np.ndarray:
    """Linear radiance of the textured square, unlit (ambient 1), box-filtered 4 x 4 per pixel."""
    a = SIDE_M / 2
    square = MeshPart("square", 1, np.array([[-a, -a, 0], [a, -a, 0], [a, a, 0], [-a, a, 0]], float),
                      np.array([[0, 1, 2], [0, 2, 3]]), uv=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float),
                      texture=texture)
    cam = SimCamera(SceneModel([square]), CAMERA, None, lambda t: world_T_cam, lambda: 0.0,
                    light_direction=(0, 0, -1), ambient=1.0, supersample=4)
    return cam.render(world_T_cam).radiance.astype(np.float64)


def _splat_image(texture: np.ndarray, world_T_cam: np.ndarray) -> np.ndarray:
    """The same square as a grid of Gaussians coloured by the texture under their centres.

    Gaussians are rendered in STRIDE x STRIDE interleaved groups whose footprints never overlap,
    so each group composites exactly linearly; colour sums over alpha sums give a normalised
    Gaussian-weighted average of the texture (a symmetric filter: it blurs but never shifts).
    """
    a = SIDE_M / 2
    ticks = np.arange(-a + GRID_M / 2, a, GRID_M)
    gx, gy = np.meshgrid(ticks, ticks, indexing="ij")
    # Texel coordinates as the simulator samples them (OBJ UVs, origin bottom-left, texel centres).
    col = (gx + a) / SIDE_M * TEXELS - 0.5
    row = (1.0 - (gy + a) / SIDE_M) * TEXELS - 0.5
    linear = srgb_to_linear(texture.astype(np.float64)).astype(np.float32)
    colours = cv2.remap(linear, col.astype(np.float32), row.astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
    viewmat = torch.from_numpy(invert(world_T_cam)).float()[None]
    K = torch.from_numpy(CAMERA.K).float()[None]
    colour_sum = torch.zeros(CAMERA.height, CAMERA.width, 3, dtype=torch.float64)
    alpha_sum = torch.zeros(CAMERA.height, CAMERA.width, 1, dtype=torch.float64)
    for i in range(STRIDE):
        for j in range(STRIDE):
            sel = (slice(i, None, STRIDE), slice(j, None, STRIDE))
            means = torch.from_numpy(np.stack([gx[sel], gy[sel], np.zeros_like(gx[sel])], -1).reshape(-1, 3)).float()
            n = len(means)
            rgb, _, alpha, _ = rasterize(means, torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(n, 4),
                                         torch.full((n, 3), SIGMA_M), torch.full((n,), 0.5),
                                         torch.from_numpy(colours[sel].reshape(-1, 3)), viewmat, K,
                                         CAMERA.width, CAMERA.height, backend="cpu")
            colour_sum += rgb[0].double()
            alpha_sum += alpha[0].double()
    return (colour_sum / alpha_sum).numpy()


def _shift(a: np.ndarray, b: np.ndarray, margin: int = 8, iterations: int = 8) -> np.ndarray:
    """Translation ``d`` (px) with ``b(x) ~ a(x - d)``, by Gauss-Newton image alignment.

    Least squares over all interior pixels: unbiased for two differently filtered images of one
    scene, unlike ``cv2.phaseCorrelate``, whose 5 x 5 peak centroid read 0.7 px for these images
    shifted by 0.5 px, and up to 0.1 px for unshifted ones.
    """
    d = np.zeros(2)
    ys, xs = np.mgrid[0:a.shape[0], 0:a.shape[1]].astype(np.float32)
    inner = (slice(margin, -margin), slice(margin, -margin))
    for _ in range(iterations):
        moved = cv2.remap(a.astype(np.float32), xs - np.float32(d[0]), ys - np.float32(d[1]),
                          cv2.INTER_CUBIC).astype(np.float64)
        gy, gx = np.gradient(moved)
        J = np.stack([gx[inner].ravel(), gy[inner].ravel()], axis=1)
        d -= np.linalg.lstsq(J, (b - moved)[inner].ravel(), rcond=None)[0]
    return d


@pytest.mark.parametrize("eye", [(0.02, -0.015, 0.3), (0.0, 0.0, 0.3), (0.06, 0.03, 0.28)])
def test_simulator_and_splat_images_are_not_shifted(eye: tuple[float, float, float]) -> None:
    """The simulated and the rasterized image of one textured square align within 0.05 px.
    The old code rendered the splat (-0.5, -0.5) px off (K's centres at integers handed
    unchanged to gsplat's +0.5 convention)."""
    texture = _smooth_texture()
    world_T_cam = look_at(eye, [0.0, 0.0, 0.0], up=(0, 1, 0))
    sim = _sim_image(texture, world_T_cam).mean(axis=2)
    splat = _splat_image(texture, world_T_cam).mean(axis=2)
    assert np.corrcoef(sim.ravel(), splat.ravel())[0, 1] > 0.95  # the same picture
    dx, dy = _shift(sim, splat)
    assert np.hypot(dx, dy) < 0.05, (dx, dy)

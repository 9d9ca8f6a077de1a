"""Small synthetic scenes with known geometry, for tests and quick experiments.

- :func:`plane_views`: images and depths of a textured plane (``z = 0``) seen from rings of
  cameras, made exactly by a homography warp of the texture (no renderer needed).
- :func:`write_scene`: a complete scene directory (capture + calibration) from such views, so
  that the real loading, undistortion, COLMAP and training code runs on it.
- :func:`random_gaussians` / :func:`render_views`: a random Gaussian scene and its renders,
  ground truth that the trainer can fit exactly; :func:`gaussian_ring_data`: such renders from
  two rings as in-memory training data (the trainer's tests' tiny scene).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch
from numpy.typing import NDArray

from brave6d.core.atomic import depth_m_to_mm_u16, write_png
from brave6d.core.calibration_io import write_handeye, write_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir
from brave6d.core.transforms import invert, ring_orbit

if TYPE_CHECKING:
    from brave6d.training.views import TrainingData


def ring_poses(distances: list[float], per_ring: int, elevation_deg: float = 55.0,
               target: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> list[tuple[int, float, NDArray[np.float64]]]:
    """``(level, distance, base_T_cam)`` for cameras on rings around ``target``."""
    return ring_orbit(target, distances, per_ring, elevation_deg)


def texture(size: int = 1024, seed: int = 0) -> NDArray[np.uint8]:
    """A colourful texture with blobs at many scales (good SIFT features)."""
    rng = np.random.default_rng(seed)
    img = cv2.resize((rng.random((size // 16, size // 16, 3)) * 255).astype(np.uint8), (size, size),
                     interpolation=cv2.INTER_CUBIC)
    for _ in range(size // 4):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        centre = tuple(int(c) for c in rng.integers(0, size, 2))
        cv2.circle(img, centre, int(rng.integers(3, size // 25)), colour, -1)
    return img


@dataclass
class SyntheticView:
    level: int
    distance_m: float
    base_T_cam: NDArray[np.float64]
    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]


def plane_views(camera: PinholeCamera, distances: list[float], per_ring: int, plane_size_m: float = 0.6,
                seed: int = 0, blank: bool = False) -> list[SyntheticView]:
    """Exact views of a textured square plane ``z = 0`` centred at the origin (grey beyond it)."""
    tex = np.full((64, 64, 3), 128, np.uint8) if blank else texture(seed=seed)
    n = tex.shape[0]
    A = np.array([[plane_size_m / n, 0, -plane_size_m / 2], [0, plane_size_m / n, -plane_size_m / 2], [0, 0, 1]])
    K = camera.K
    views = []
    for level, dist, base_T_cam in ring_poses(distances, per_ring):
        cam_T_base = invert(base_T_cam)
        H = K @ np.stack([cam_T_base[:3, 0], cam_T_base[:3, 1], cam_T_base[:3, 3]], axis=1) @ A
        # pixel-centre convention: texel centres at integer coordinates as for the camera
        rgb = cv2.warpPerspective(tex, H, (camera.width, camera.height), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=(128, 128, 128))
        # depth of the plane z = 0 along each pixel ray
        rays = camera.unproject(camera.pixel_grid(), np.ones(camera.width * camera.height))
        d_world = rays @ base_T_cam[:3, :3].T
        o = base_T_cam[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[2] / d_world[:, 2]
        hit = o[None, :2] + t[:, None] * d_world[:, :2]
        inside = (t > 0) & (np.abs(hit) <= plane_size_m / 2).all(axis=1)
        depth = np.where(inside, t, 0.0).reshape(camera.height, camera.width).astype(np.float32)
        views.append(SyntheticView(level, dist, base_T_cam, rgb, depth))
    return views


def write_scene(root: Path | str, camera: PinholeCamera, views: list[SyntheticView],
                tcp_T_cam: NDArray[np.float64] | None = None, with_depth: bool = True) -> SceneDir:
    """A scene directory with ``capture/`` (frames, PNGs) and ``calibration/`` for ``views``."""
    scene = SceneDir(root)
    tcp_T = np.eye(4) if tcp_T_cam is None else np.asarray(tcp_T_cam, float)
    cam_T_tcp = invert(tcp_T)
    log = FrameLog(scene.frames_path)
    for i, v in enumerate(views):
        rgb_rel, depth_rel = f"rgb/{i:06d}.png", f"depth/{i:06d}.png"
        write_png(scene.capture.file(rgb_rel), v.rgb)
        if with_depth:
            write_png(scene.capture.file(depth_rel), depth_m_to_mm_u16(v.depth_m))
        log.append(FrameRecord(index=i, view_id=f"v{i:04d}", distance_level=v.level, distance_m=v.distance_m,
                               rgb=rgb_rel, depth=depth_rel if with_depth else None,
                               base_T_tcp=(v.base_T_cam @ cam_T_tcp).tolist(), joints=[0.0] * 6,
                               timestamp=float(i)))
    write_intrinsics(scene, camera, method="synthetic")
    write_handeye(scene, tcp_T, method="synthetic")
    return scene


# ----------------------------------------------------------------------------- Gaussian scenes
def random_gaussians(n: int, seed: int = 0, extent: float = 0.1) -> dict[str, torch.Tensor]:
    """Pre-activation parameters of ``n`` random, fairly opaque Gaussians in a cube of side ``2 * extent``."""
    g = torch.Generator().manual_seed(seed)
    return {
        "means": (torch.rand(n, 3, generator=g) * 2 - 1) * extent,
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.log(torch.rand(n, 3, generator=g) * 0.1 * extent + 0.05 * extent),
        "opacities": torch.logit(torch.rand(n, generator=g) * 0.5 + 0.45),
        "sh0": (torch.rand(n, 1, 3, generator=g) - 0.5) / 0.28209479177387814,
        "shN": torch.zeros(n, 0, 3),
    }


@torch.no_grad()
def render_views(params: dict[str, torch.Tensor], camera: PinholeCamera, poses: list[NDArray[np.float64]]
                 ) -> list[NDArray[np.uint8]]:
    """uint8 renders of a degree-0 Gaussian scene (the rasterizer's own CPU backend)."""
    from brave6d.training.rasterizer import rasterize

    K = torch.from_numpy(camera.K).float()[None]
    out = []
    for pose in poses:
        viewmat = torch.from_numpy(invert(pose)).float()[None]
        colors, _, _, _ = rasterize(params["means"], params["quats"], torch.exp(params["scales"]),
                                    torch.sigmoid(params["opacities"]), params["sh0"], viewmat, K,
                                    camera.width, camera.height, sh_degree=0)
        out.append((colors[0].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))
    return out


def gaussian_ring_data(camera: PinholeCamera, n: int = 150, seed: int = 1, extent: float = 0.08,
                       distances: tuple[float, ...] = (0.35, 0.45), per_ring: int = 6,
                       elevation_deg: float = 40.0, test: tuple[int, ...] = (2, 9)) -> TrainingData:
    """Training data of :func:`random_gaussians` rendered from rings of cameras (:func:`ring_poses`),
    views ``test`` held out: a scene the trainer fits in seconds on a CPU."""
    from brave6d.training.views import TrainingData, View

    poses = ring_poses(list(distances), per_ring, elevation_deg=elevation_deg)
    images = render_views(random_gaussians(n, seed=seed, extent=extent), camera, [p for _, _, p in poses])
    views = [View(i, f"v{i:02d}", lvl, d, pose, img) for i, ((lvl, d, pose), img) in enumerate(zip(poses, images))]
    return TrainingData(camera, [v for v in views if v.index not in test], [views[i] for i in test])

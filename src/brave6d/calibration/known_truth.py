"""Synthetic calibration data with a known truth, for tests and benchmarks.

Two levels: numeric views (board corners projected with ``cv2.projectPoints``, pixel noise and
robot pose error added) and rendered images of the board (the board texture warped by the
exact plane homography, optionally distorted, then detected like a real image). Not used by
the calibration itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.board import board_size_m
from brave6d.core.spec import BoardSpec, Pose
from brave6d.core.transforms import invert, make_transform, rpy_deg_to_matrix
from brave6d.calibration.board import board_corner_points, render_board
from brave6d.calibration.handeye import HandEyeView
from brave6d.calibration.plan import board_T_cam_view

__all__ = [
    "DEFAULT_IMAGE_SIZE",
    "SyntheticHandEye",
    "default_K",
    "default_board",
    "default_tcp_T_cam",
    "make_handeye_dataset",
    "perturb_pose",
    "project_corners",
    "random_board_views",
    "render_board_view",
    "simulate_views",
]

Array = NDArray[np.float64]
DEFAULT_IMAGE_SIZE = (640, 480)


def default_K() -> Array:
    """A 640x480 camera with a 56 deg horizontal field of view."""
    return np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])


def default_board() -> BoardSpec:
    """The spec's default board (7x5 squares of 30 mm) lying face up 0.45 m in front of the robot."""
    return BoardSpec(pose=Pose(xyz=(0.45, -0.1, 0.02), rpy_deg=(180.0, 0.0, 0.0)))


def default_tcp_T_cam() -> Array:
    """A plausible camera mounting: 90 deg about the tool axis, a few cm off the flange."""
    return make_transform(rpy_deg_to_matrix([1.5, -2.0, 91.0]), [0.032, -0.061, 0.047])


def perturb_pose(T: ArrayLike, translation_sigma_m: float, rotation_sigma_deg: float, rng: np.random.Generator) -> Array:
    """``T`` composed with a random rigid error (isotropic Gaussian, in ``T``'s own frame)."""
    rot = Rotation.from_rotvec(rng.normal(0.0, np.radians(rotation_sigma_deg), 3)).as_matrix()
    return np.asarray(T, dtype=np.float64) @ make_transform(rot, rng.normal(0.0, translation_sigma_m, 3))


def project_corners(
    object_points: ArrayLike, cam_T_board: ArrayLike, K: ArrayLike, dist: ArrayLike, image_size: tuple[int, int],
    edge_margin_px: float = 3.0,
) -> tuple[NDArray[np.int32], Array]:
    """Ids and pixels of the corners in front of the camera and inside the image (with margin)."""
    obj = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)
    T = np.asarray(cam_T_board, dtype=np.float64)
    P = obj @ T[:3, :3].T + T[:3, 3]
    front = P[:, 2] > 1e-3
    uv, _ = cv2.projectPoints(obj, Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3],
                              np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64).reshape(-1))
    uv = uv.reshape(-1, 2)
    w, h = image_size
    inside = (uv[:, 0] >= edge_margin_px) & (uv[:, 0] <= w - 1 - edge_margin_px) & (uv[:, 1] >= edge_margin_px) & (
        uv[:, 1] <= h - 1 - edge_margin_px)
    keep = front & inside
    return np.nonzero(keep)[0].astype(np.int32), uv[keep]


def random_board_views(
    n: int, rotation_span_deg: float, distance_m: float, center_board: ArrayLike, rng: np.random.Generator,
    center_jitter_m: float = 0.05, distance_jitter: float = 0.1,
) -> list[Array]:
    """``board_T_cam`` of ``n`` views looking near the board centre (aim point +-``center_jitter_m``):
    tilt up to +-span about a random in-plane axis, roll up to +-span about the optical axis,
    distance +-``distance_jitter`` (fraction)."""
    c = np.asarray(center_board, dtype=np.float64)
    out = []
    for _ in range(n):
        tilt = rng.uniform(-rotation_span_deg, rotation_span_deg)
        az = rng.uniform(0.0, 180.0)
        roll = rng.uniform(-rotation_span_deg, rotation_span_deg)
        d = distance_m * (1.0 + rng.uniform(-distance_jitter, distance_jitter))
        jitter = np.r_[rng.uniform(-center_jitter_m, center_jitter_m, 2), 0.0]
        out.append(board_T_cam_view(c + jitter, d, tilt, az, roll))
    return out


def simulate_views(
    base_T_tcp_true: Sequence[ArrayLike],
    tcp_T_cam: ArrayLike,
    base_T_board: ArrayLike,
    object_points: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike = (),
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
    *,
    pixel_noise_px: float = 0.0,
    robot_translation_noise_m: float = 0.0,
    robot_rotation_noise_deg: float = 0.0,
    rng: np.random.Generator | None = None,
) -> list[HandEyeView]:
    """Views as a real capture would give them: corners seen from the *true* poses (plus pixel
    noise), paired with robot poses that carry the robot's pose error."""
    gen = rng if rng is not None else np.random.default_rng(0)
    X = np.asarray(tcp_T_cam, dtype=np.float64)
    W = np.asarray(base_T_board, dtype=np.float64)
    views = []
    for k, G in enumerate(base_T_tcp_true):
        G = np.asarray(G, dtype=np.float64)
        ids, uv = project_corners(object_points, invert(G @ X) @ W, K, dist, image_size)
        uv = uv + gen.normal(0.0, pixel_noise_px, uv.shape) if pixel_noise_px > 0 else uv
        G_meas = perturb_pose(G, robot_translation_noise_m, robot_rotation_noise_deg, gen)
        views.append(HandEyeView(G_meas, ids, uv, f"view_{k:03d}"))
    return views


@dataclass(frozen=True)
class SyntheticHandEye:
    """A synthetic eye-in-hand capture and its truth."""

    views: list[HandEyeView]
    object_points: Array
    K: Array
    dist: Array
    image_size: tuple[int, int]
    board: BoardSpec
    tcp_T_cam: Array
    base_T_board: Array
    base_T_tcp_true: list[Array]


def make_handeye_dataset(
    n_poses: int = 15,
    rotation_span_deg: float = 30.0,
    *,
    seed: int = 0,
    pixel_noise_px: float = 0.2,
    robot_translation_noise_m: float = 1e-4,
    robot_rotation_noise_deg: float = 0.01,
    distance_m: float = 0.45,
    board: BoardSpec | None = None,
    K: ArrayLike | None = None,
    dist: ArrayLike = (),
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
    tcp_T_cam: ArrayLike | None = None,
) -> SyntheticHandEye:
    """Random views around the board (:func:`random_board_views`) simulated with noise."""
    rng = np.random.default_rng(seed)
    spec = board or default_board()
    X = np.asarray(tcp_T_cam, dtype=np.float64) if tcp_T_cam is not None else default_tcp_T_cam()
    K_arr = np.asarray(K, dtype=np.float64) if K is not None else default_K()
    W = spec.pose.matrix()
    w, h = board_size_m(spec)
    board_T_cams = random_board_views(n_poses, rotation_span_deg, distance_m, (w / 2, h / 2, 0.0), rng)
    G_true = [W @ bc @ invert(X) for bc in board_T_cams]
    obj = board_corner_points(spec)
    views = simulate_views(
        G_true, X, W, obj, K_arr, dist, image_size, pixel_noise_px=pixel_noise_px,
        robot_translation_noise_m=robot_translation_noise_m, robot_rotation_noise_deg=robot_rotation_noise_deg, rng=rng,
    )
    return SyntheticHandEye(views, obj, K_arr, np.asarray(dist, dtype=np.float64).reshape(-1), image_size, spec, X, W, G_true)


def render_board_view(
    spec: BoardSpec,
    K: ArrayLike,
    cam_T_board: ArrayLike,
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
    dist: ArrayLike = (),
    *,
    background: int = 110,
    supersample: int = 3,
    noise_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
    margin_m: float | None = None,
) -> NDArray[np.uint8]:
    """Grey uint8 image of the board seen by a camera (K, dist) at ``cam_T_board``.

    The board texture (:func:`~brave6d.calibration.board.render_board`, white margin of half a square)
    is warped with the exact homography ``K [r1 r2 t]`` of the plane z = 0 at ``supersample``
    times the resolution, distorted if ``dist`` is non-zero, then area-averaged down
    (anti-aliasing). Pixel centres follow OpenCV (integers).
    """
    K_arr = np.asarray(K, dtype=np.float64)
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    T = np.asarray(cam_T_board, dtype=np.float64)
    w, h = image_size
    s = int(supersample)
    S = np.array([[s, 0.0, (s - 1) / 2.0], [0.0, s, (s - 1) / 2.0], [0.0, 0.0, 1.0]])  # pixel -> high-res pixel
    K_hi = S @ K_arr
    depth = max(float(T[2, 3]), 1e-3)
    px_per_m = max(K_arr[0, 0] * s / depth * 1.5, 2.0 * 9 / spec.square_length_m)
    tex = render_board(spec, px_per_m, spec.square_length_m / 2 if margin_m is None else margin_m)
    H = K_hi @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]) @ tex.pixel_to_board
    ideal = cv2.warpPerspective(tex.image, H, (w * s, h * s), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    if d.size and np.any(d):
        # Each output pixel -> ideal (undistorted) pixel, computed at the output resolution and
        # interpolated to the high-res grid (cv2.resize aligns pixel centres exactly as S does).
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        und = cv2.undistortPoints(pix, K_arr, d, P=K_arr).reshape(h, w, 2) * s + (s - 1) / 2.0
        map_hi = cv2.resize(und.astype(np.float32), (w * s, h * s), interpolation=cv2.INTER_LINEAR)
        ideal = cv2.remap(ideal, map_hi[:, :, 0], map_hi[:, :, 1], cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    img = cv2.resize(ideal, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)
    if noise_sigma > 0:
        img += (rng if rng is not None else np.random.default_rng(0)).normal(0.0, noise_sigma, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)

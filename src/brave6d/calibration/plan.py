"""Calibration capture plan: camera poses around the ChArUco board with large, diverse rotations.

Hand-eye calibration needs robot motions whose rotation axes are not parallel and whose
rotations are large (tens of degrees); a plan of views that all look at the board from
above with the same orientation is degenerate. Each planned view looks at an *aim point*
near the board centre and is made of

* a *tilt* of ``tilt_deg`` about an axis in the board plane at ``azimuth_deg`` (0 = board x),
  rotating the camera around the aim point (the view becomes oblique), and
* a *roll* of ``roll_deg`` about the camera's optical axis.

Azimuths follow the golden angle, so successive tilt axes are never parallel; tilts cycle
through 100 %, 60 % and 80 % of ``max_tilt_deg`` and rolls through +-100 % and +-50 % of
``max_roll_deg``. The aim point moves around the board centre by up to ``aim_offset``
(fraction of the half board size): if every optical axis passed through the same board
point, a camera roll on the flange could be traded against a board rotation about its normal
up to a small perspective effect, and the roll of ``tcp_T_cam`` would be poorly determined
(synthetic study: 15 views, 0.2 px noise, 1-sigma about the optical axis 0.13 deg with the
aim fixed, 0.05 deg with +-5 cm offsets on a 21 x 15 cm board). Reachability is the capture
planner's job, not this module's.

Defaults (30 views, tilts up to 40 deg, rolls up to 30 deg) come from the synthetic study in
the tests: the same images also calibrate the intrinsics, and the principal point error
(about 0.3 px with 24 views at 35 deg) turns ``tcp_T_cam`` by the same angle (0.3 px / f);
30 views at 40 deg keep the hand-eye rotation error well below 0.05 deg.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.board import board_size_m
from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.spec import BoardSpec
from brave6d.core.transforms import check_rigid, invert, make_transform

__all__ = ["PlannedPose", "board_T_cam_view", "plan_calibration_poses", "plan_for_board", "plan_pairs"]

GOLDEN_ANGLE_DEG = 137.50776405003785


@dataclass(frozen=True)
class PlannedPose:
    """One calibration view: the camera pose, the implied TCP pose and how it was made."""

    name: str
    base_T_cam: NDArray[np.float64]
    base_T_tcp: NDArray[np.float64]
    tilt_deg: float
    azimuth_deg: float
    roll_deg: float
    distance_m: float

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (4x4 matrices as nested lists)."""
        return {
            "name": self.name,
            "base_T_cam": self.base_T_cam.tolist(),
            "base_T_tcp": self.base_T_tcp.tolist(),
            "tilt_deg": self.tilt_deg,
            "azimuth_deg": self.azimuth_deg,
            "roll_deg": self.roll_deg,
            "distance_m": self.distance_m,
        }


def board_T_cam_view(
    center_board: ArrayLike, distance_m: float, tilt_deg: float, azimuth_deg: float, roll_deg: float
) -> NDArray[np.float64]:
    """``board_T_cam`` of a camera ``distance_m`` from ``center_board`` looking at it.

    With zero tilt and roll the camera faces the printed side (it sits on the board's -z side)
    and its axes equal the board's (image upright, ``cam_R_board = I``). The tilt rotates the
    camera about the board centre around the in-plane axis at ``azimuth_deg``; the roll turns
    it about its own optical axis. The board centre stays on the optical axis.
    """
    c = np.asarray(center_board, dtype=np.float64).reshape(3)
    az = np.radians(azimuth_deg)
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(az), np.sin(az), 0.0]))
    roll = Rotation.from_rotvec(np.radians(roll_deg) * np.array([0.0, 0.0, 1.0]))
    R = (tilt * roll).as_matrix()
    position = c + tilt.apply(np.array([0.0, 0.0, -distance_m]))
    return make_transform(R, position)


def _board_fits(
    cam_T_board: NDArray[np.float64], outline: NDArray[np.float64], K: NDArray[np.float64],
    image_size: tuple[int, int], margin_px: float,
) -> bool:
    pts = outline @ cam_T_board[:3, :3].T + cam_T_board[:3, 3]
    if np.any(pts[:, 2] <= 1e-6):
        return False
    uv = (pts @ K.T)[:, :2] / pts[:, 2:3]
    w, h = image_size
    return bool(np.all(uv[:, 0] >= margin_px) and np.all(uv[:, 0] <= w - 1 - margin_px)
                and np.all(uv[:, 1] >= margin_px) and np.all(uv[:, 1] <= h - 1 - margin_px))


def plan_calibration_poses(
    base_T_board: ArrayLike,
    center_board: ArrayLike,
    distance_m: float,
    tcp_T_cam_guess: ArrayLike,
    n_poses: int = 30,
    *,
    max_tilt_deg: float = 40.0,
    max_roll_deg: float = 30.0,
    distance_jitter: float = 0.1,
    aim_offset: float = 0.5,
    board_half_size: tuple[float, float] = (0.1, 0.1),
    K: ArrayLike | None = None,
    image_size: tuple[int, int] | None = None,
    board_outline: ArrayLike | None = None,
    fit_margin_px: float = 10.0,
) -> list[PlannedPose]:
    """Camera poses around the board for calibration, and the TCP poses that realise them.

    ``base_T_board`` is where the board lies in the robot base frame, ``center_board`` the
    point to keep in the image centre (board frame), ``tcp_T_cam_guess`` the rough camera
    mounting. The first pose is frontal; the rest are tilted and rolled as described in the
    module docstring, with distances varied by +-``distance_jitter`` (fraction).

    When ``K``, ``image_size`` and ``board_outline`` ((N, 3) board-frame points, e.g. the
    four outer corners) are given, a view whose board does not fit in the image with
    ``fit_margin_px`` to spare is moved back until it does (raises if 3x is not enough).
    """
    if n_poses < 3:
        raise DegenerateGeometryError(f"calibration plan: {n_poses} poses requested, hand-eye needs at least 3")
    if not (0.0 < max_tilt_deg < 80.0):
        raise DegenerateGeometryError(f"calibration plan: max_tilt_deg must be in (0, 80), got {max_tilt_deg}")
    if distance_m <= 0:
        raise DegenerateGeometryError(f"calibration plan: distance_m must be positive, got {distance_m}")
    W = check_rigid(base_T_board, "base_T_board")
    tcp_T_cam = check_rigid(tcp_T_cam_guess, "tcp_T_cam_guess")
    cam_T_tcp = invert(tcp_T_cam)
    fit = K is not None and image_size is not None and board_outline is not None
    if fit:
        K_arr = np.asarray(K, dtype=np.float64).reshape(3, 3)
        outline = np.asarray(board_outline, dtype=np.float64).reshape(-1, 3)
    tilt_cycle = (1.0, 0.6, 0.8)
    roll_cycle = (1.0, -1.0, 0.5, -0.5)
    dist_cycle = (0.0, -1.0, 1.0)
    center = np.asarray(center_board, dtype=np.float64).reshape(3)
    poses: list[PlannedPose] = []
    for k in range(n_poses):
        aim = center.copy()
        if k == 0:
            tilt, az, roll, d = 0.0, 0.0, 0.0, distance_m
        else:
            tilt = max_tilt_deg * tilt_cycle[(k - 1) % 3]
            az = (k - 1) * GOLDEN_ANGLE_DEG % 360.0
            roll = max_roll_deg * roll_cycle[(k - 1) % 4]
            d = distance_m * (1.0 + distance_jitter * dist_cycle[(k - 1) % 3])
            phi = np.radians(k * 97.0)  # aim direction, uncorrelated with the tilt azimuth
            aim[:2] += aim_offset * np.array([board_half_size[0] * np.cos(phi), board_half_size[1] * np.sin(phi)])
        board_T_cam = board_T_cam_view(aim, d, tilt, az, roll)
        if fit:
            for _ in range(24):
                if _board_fits(invert(board_T_cam), outline, K_arr, image_size, fit_margin_px):  # type: ignore[arg-type]
                    break
                d *= 1.05
                board_T_cam = board_T_cam_view(aim, d, tilt, az, roll)
            else:
                raise DegenerateGeometryError(
                    f"calibration plan: the board does not fit in the image even at {d:.2f} m "
                    f"(pose {k}: tilt {tilt:.0f} deg, roll {roll:.0f} deg); use a smaller board or wider lens"
                )
        base_T_cam = W @ board_T_cam
        poses.append(PlannedPose(f"calib_{k:03d}", base_T_cam, base_T_cam @ cam_T_tcp, tilt, az, roll, d))
    return poses


def plan_for_board(
    spec: BoardSpec,
    distance_m: float,
    tcp_T_cam_guess: ArrayLike,
    n_poses: int = 30,
    *,
    K: ArrayLike | None = None,
    image_size: tuple[int, int] | None = None,
    **kwargs: Any,
) -> list[PlannedPose]:
    """:func:`plan_calibration_poses` for a spec's board: centre = pattern centre, pose from
    ``spec.pose`` (``world_T_board`` = ``base_T_board``), outline = the pattern's outer corners."""
    w, h = board_size_m(spec)
    outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], dtype=np.float64)
    return plan_calibration_poses(
        spec.pose.matrix(), (w / 2, h / 2, 0.0), distance_m, tcp_T_cam_guess, n_poses,
        board_half_size=(w / 2, h / 2), K=K, image_size=image_size,
        board_outline=outline if K is not None else None, **kwargs,
    )


def plan_pairs(poses: Sequence[PlannedPose], base_T_board: ArrayLike) -> tuple[list[NDArray[np.float64]], list[NDArray[np.float64]]]:
    """(base_T_tcp list, cam_T_board list) of a plan, e.g. for the conditioning check."""
    W = np.asarray(base_T_board, dtype=np.float64)
    return [p.base_T_tcp for p in poses], [invert(p.base_T_cam) @ W for p in poses]

"""Is a set of robot/camera poses good enough for eye-in-hand calibration? Check before solving.

``A X = X B`` with ``A`` the robot (TCP) motions and ``B`` the camera motions between views
determines ``X = tcp_T_cam`` only if the motions rotate about at least two non-parallel axes:

* pure translations leave the rotation of ``X`` undetermined;
* rotations about one axis leave the translation of ``X`` along that axis undetermined;
* small rotations amplify measurement noise (roughly as 1 / rotation span);
* motions whose axes spread only a little (or spread only through small rotations) leave one
  direction weakly determined: the noise of the motions reaches the translation of ``X``
  along it, and its rotation about it, amplified by ``1 / weakest rotation`` (rad), where the
  weakest rotation is the RMS over view pairs of the rotation perpendicular to that direction
  (:func:`weakest_rotation`);
* duplicated poses add no information and usually mean a capture or bookkeeping error.

:func:`check_handeye_conditioning` raises :class:`DegenerateGeometryError` naming the cause,
the measured value and the threshold, and returns soft warnings otherwise. The thresholds
(:class:`ConditioningThresholds`) are parameters; the defaults are:

=========================  ==========  ===================================================
threshold                  default     meaning
=========================  ==========  ===================================================
min_poses                  3           fewest poses (two independent motions)
duplicate_translation_m    0.0005      two TCP poses closer than this *and* ...
duplicate_rotation_deg     0.1         ... rotated less than this are duplicates
pure_translation_deg       1.0         all relative rotations below: pure translations
min_rotation_span_deg      15.0        largest rotation between two poses must reach this
axis_min_rotation_deg      5.0         motions rotating less do not define an axis
min_axis_angle_deg         10.0        largest angle between two motion axes must reach this
min_weakest_rotation_deg   3.0         RMS rotation about the worst direction must reach this
max_angle_mismatch_deg     3.0         median |angle(A) - angle(B)| (robot vs camera motion)
recommended_poses          10          fewer: warning
recommended_span_deg       30.0        smaller span: warning
recommended_axis_angle_deg 30.0        smaller axis spread: warning
recommended_weakest_deg    10.0        smaller weakest rotation: warning
=========================  ==========  ===================================================

With the defaults, a pose set that passes amplifies the motion noise into ``tcp_T_cam`` by at
most about 20x (1 / 3 deg in rad); the plans of :mod:`brave6d.calibration.plan` reach 30-40 deg.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.transforms import check_rigid

__all__ = [
    "ConditioningReport",
    "ConditioningThresholds",
    "check_handeye_conditioning",
    "relative_motions",
    "weakest_rotation",
]

_MAX_AXES = 1500  # pairwise axis comparison is O(n^2): keep the largest-rotation motions


@dataclass(frozen=True)
class ConditioningThresholds:
    """Limits of :func:`check_handeye_conditioning` (see the module docstring)."""

    min_poses: int = 3
    duplicate_translation_m: float = 0.0005
    duplicate_rotation_deg: float = 0.1
    pure_translation_deg: float = 1.0
    min_rotation_span_deg: float = 15.0
    axis_min_rotation_deg: float = 5.0
    min_axis_angle_deg: float = 10.0
    min_weakest_rotation_deg: float = 3.0
    max_angle_mismatch_deg: float = 3.0
    recommended_poses: int = 10
    recommended_span_deg: float = 30.0
    recommended_axis_angle_deg: float = 30.0
    recommended_weakest_deg: float = 10.0

    @staticmethod
    def relaxed() -> ConditioningThresholds:
        """Only the mathematically necessary checks (for studies that measure bad geometry)."""
        return ConditioningThresholds(
            pure_translation_deg=0.05, min_rotation_span_deg=0.1, axis_min_rotation_deg=0.05,
            min_axis_angle_deg=0.5, min_weakest_rotation_deg=0.05, max_angle_mismatch_deg=180.0, duplicate_translation_m=0.0,
            duplicate_rotation_deg=0.0,
        )


@dataclass(frozen=True)
class ConditioningReport:
    """What the check measured; ``warnings`` are soft (the solve goes on)."""

    n_poses: int
    rotation_span_deg: float
    max_axis_angle_deg: float
    median_angle_mismatch_deg: float | None
    warnings: tuple[str, ...] = field(default_factory=tuple)
    weakest_rotation_deg: float | None = None

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["warnings"] = list(self.warnings)
        return d

    @staticmethod
    def from_json(data: dict[str, Any]) -> ConditioningReport:
        return ConditioningReport(
            int(data["n_poses"]), float(data["rotation_span_deg"]), float(data["max_axis_angle_deg"]),
            None if data.get("median_angle_mismatch_deg") is None else float(data["median_angle_mismatch_deg"]),
            tuple(data.get("warnings", ())),
            None if data.get("weakest_rotation_deg") is None else float(data["weakest_rotation_deg"]),
        )


def relative_motions(
    a_T_b: Sequence[ArrayLike] | NDArray[np.float64], inverse_side: bool = False
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """All pairs ``i < j`` and their relative rotations.

    With ``inverse_side=False`` (robot poses ``base_T_tcp``) the motion is
    ``inv(T_j) @ T_i`` (``tcp_j_T_tcp_i``); with ``True`` (camera ``cam_T_board``) it is
    ``T_j @ inv(T_i)`` (``cam_j_T_cam_i``). Returns ``(pairs (P, 2), rotations (P, 3, 3))``.
    """
    T = np.asarray(a_T_b, dtype=np.float64).reshape(-1, 4, 4)
    i, j = np.triu_indices(len(T), k=1)
    R = T[:, :3, :3]
    if inverse_side:
        rel = np.einsum("pab,pcb->pac", R[j], R[i])  # R_j R_i^T
    else:
        rel = np.einsum("pba,pbc->pac", R[j], R[i])  # R_j^T R_i
    return np.stack([i, j], axis=1), rel


def weakest_rotation(rotvecs: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
    """``(angle rad, unit direction u)``: the direction that the motions (rotation vectors, (P, 3))
    turn least, i.e. the one they mostly rotate about, and the RMS over motions of their rotation
    perpendicular to it, ``sqrt(min_u sum_p |r_p x u|^2 / P)``. Zero for pure translations or a
    single axis; to first order the smallest singular value (over sqrt(P)) of the linear systems
    of ``A X = X B``, so ``1 / angle`` is how much they amplify the motions' noise."""
    r = np.asarray(rotvecs, dtype=np.float64).reshape(-1, 3)
    if not len(r):
        return 0.0, np.array([0.0, 0.0, 1.0])
    S = np.sum(r * r) * np.eye(3) - r.T @ r
    ev, evec = np.linalg.eigh(S)
    return float(np.sqrt(max(ev[0], 0.0) / len(r))), evec[:, 0]


def _max_axis_angle_deg(axes: NDArray[np.float64]) -> float:
    if len(axes) < 2:
        return 0.0
    cos = np.clip(np.abs(axes @ axes.T), 0.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


#: Per set-up: the frame the robot motions' axes are expressed in, and how the camera is mounted.
SETUPS = {
    "eye-in-hand": ("TCP frame", "that the camera is mounted on the tool (eye-in-hand; a static camera looking at "
                                 "a board on the tool is eye-to-hand)"),
    "eye-to-hand": ("base frame", "that the camera is static and the board is on the tool (eye-to-hand; a camera "
                                  "on the tool is eye-in-hand)"),
}


def check_handeye_conditioning(
    base_T_tcp: Sequence[ArrayLike],
    cam_T_board: Sequence[ArrayLike] | None = None,
    thresholds: ConditioningThresholds | None = None,
    names: Sequence[str] | None = None,
    setup: str = "eye-in-hand",
) -> ConditioningReport:
    """Raise :class:`DegenerateGeometryError` naming the cause if the poses cannot determine
    ``tcp_T_cam`` reliably; otherwise return the measured figures and soft warnings.

    ``base_T_tcp``: the robot poses of the usable views; ``cam_T_board``: the board poses
    seen by the camera in the same views (optional; enables the robot-vs-camera check);
    ``names``: view names used in messages (default: the indices); ``setup``: the words of the
    messages (``"eye-to-hand"``: the poses are the inverted robot poses of a static camera,
    their motion axes lie in the base frame).
    """
    th = thresholds or ConditioningThresholds()
    if setup not in SETUPS:
        raise ValueError(f"setup must be one of {sorted(SETUPS)}, got {setup!r}")
    frame, mounting = SETUPS[setup]
    n = len(base_T_tcp)
    label = list(names) if names is not None else [str(k) for k in range(n)]
    if n < th.min_poses:
        raise DegenerateGeometryError(
            f"too few poses for hand-eye calibration: {n} usable pose(s), at least {th.min_poses} needed "
            f"(recommended {th.recommended_poses}+ with rotations about different axes)"
        )
    T = np.stack([check_rigid(t, f"base_T_tcp of view {label[k]}") for k, t in enumerate(base_T_tcp)])
    pairs, rel = relative_motions(T)
    angles = Rotation.from_matrix(rel).magnitude()
    angles_deg = np.degrees(angles)
    dist = np.linalg.norm(T[pairs[:, 0], :3, 3] - T[pairs[:, 1], :3, 3], axis=1)

    dup = (dist <= th.duplicate_translation_m) & (angles_deg <= th.duplicate_rotation_deg)
    if np.any(dup):
        shown = [f"{label[a]} and {label[b]}" for a, b in pairs[dup][:5]]
        more = f" (and {int(dup.sum()) - 5} more pairs)" if dup.sum() > 5 else ""
        raise DegenerateGeometryError(
            f"duplicated poses: views {'; '.join(shown)}{more} have the same robot pose (within "
            f"{th.duplicate_translation_m * 1000:g} mm and {th.duplicate_rotation_deg:g} deg); drop the repeats"
        )

    span = float(angles_deg.max())
    if span < th.pure_translation_deg:
        raise DegenerateGeometryError(
            f"pure translations: the robot poses differ only by translation (largest rotation between "
            f"two poses {span:.2f} deg < {th.pure_translation_deg:g} deg), so the camera's rotation on the "
            "flange is undetermined; add poses rotated about at least two different axes"
        )
    if span < th.min_rotation_span_deg:
        raise DegenerateGeometryError(
            f"rotation span too small: the largest rotation between two poses is {span:.1f} deg "
            f"< {th.min_rotation_span_deg:g} deg; tilt the camera by +-30 deg or more about different axes"
        )

    keep = angles_deg >= th.axis_min_rotation_deg
    order = np.argsort(-angles_deg[keep])[:_MAX_AXES]
    rotvecs = Rotation.from_matrix(rel[keep][order]).as_rotvec()
    axes = rotvecs / np.linalg.norm(rotvecs, axis=1, keepdims=True) if len(rotvecs) else rotvecs
    axis_angle = _max_axis_angle_deg(axes)
    if axis_angle < th.min_axis_angle_deg:
        raise DegenerateGeometryError(
            f"near-parallel rotation axes: the largest angle between the rotation axes of the robot motions is "
            f"{axis_angle:.1f} deg < {th.min_axis_angle_deg:g} deg (rotations about a single axis leave the "
            "camera offset along that axis undetermined); add rotations about a second, different axis"
        )
    weak_rad, weak_dir = weakest_rotation(Rotation.from_matrix(rel).as_rotvec())
    weak = math.degrees(weak_rad)
    if weak < th.min_weakest_rotation_deg:
        raise DegenerateGeometryError(
            f"near-parallel rotation axes: the robot motions turn the direction {np.round(weak_dir, 2).tolist()} "
            f"({frame}) by only {weak:.2f} deg (RMS over view pairs) < {th.min_weakest_rotation_deg:g} deg, nearly "
            "all rotations are about it, so the camera offset along it is poorly determined (noise amplified "
            f"{1.0 / max(weak_rad, 1e-12):.0f}x); add rotations about an axis perpendicular to it"
        )

    mismatch: float | None = None
    warnings: list[str] = []
    if cam_T_board is not None:
        if len(cam_T_board) != n:
            raise DegenerateGeometryError(f"{n} robot poses but {len(cam_T_board)} board poses")
        C = np.stack([check_rigid(c, f"cam_T_board of view {label[k]}") for k, c in enumerate(cam_T_board)])
        _, rel_c = relative_motions(C, inverse_side=True)
        diff = np.abs(angles_deg - np.degrees(Rotation.from_matrix(rel_c).magnitude()))
        mismatch = float(np.median(diff))
        if mismatch > th.max_angle_mismatch_deg:
            raise DegenerateGeometryError(
                f"robot and camera motions disagree: the median difference between the rotation angles of "
                f"robot and camera motions is {mismatch:.1f} deg > {th.max_angle_mismatch_deg:g} deg; check that "
                f"images and robot poses are paired correctly, the pose units (m, rad) and {mounting}"
            )
        worst = int(np.argmax(diff))
        if diff[worst] > th.max_angle_mismatch_deg:
            a, b = pairs[worst]
            warnings.append(
                f"views {label[a]} and {label[b]}: robot and camera rotation angles differ by {diff[worst]:.1f} deg "
                "(bad detection or robot pose?)"
            )
    if n < th.recommended_poses:
        warnings.append(f"only {n} poses; {th.recommended_poses} or more are recommended")
    if span < th.recommended_span_deg:
        warnings.append(f"rotation span {span:.1f} deg is below the recommended {th.recommended_span_deg:g} deg")
    if axis_angle < th.recommended_axis_angle_deg:
        warnings.append(
            f"rotation axes spread only {axis_angle:.1f} deg (recommended {th.recommended_axis_angle_deg:g} deg+)"
        )
    if weak < th.recommended_weakest_deg:
        warnings.append(
            f"the motions turn the direction {np.round(weak_dir, 2).tolist()} ({frame}) by only {weak:.1f} deg "
            f"(RMS; recommended {th.recommended_weakest_deg:g} deg+): rotate more about axes perpendicular to it"
        )
    return ConditioningReport(n, span, axis_angle, mismatch, tuple(warnings), weak)

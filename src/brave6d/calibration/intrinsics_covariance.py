"""The full covariance of calibrated intrinsics, correlations included.

OpenCV's ``calibrateCameraExtended`` reports only the 1-sigma of each intrinsic parameter. Those
parameters are strongly correlated (on a real 16-view ChArUco set: fx/fy 0.98, k1/k2 -0.95, k2/k3
-0.97), so propagating the 1-sigmas as if independent overstates what the intrinsics' uncertainty
does to a hand-eye result (the radial terms largely cancel each other) or understates it (fx and
fy move together). :func:`intrinsics_covariance` computes the covariance from the same model as
OpenCV: the Jacobians of ``cv2.projectPoints`` at the calibrated intrinsics and per-view poses,
the per-view poses eliminated (Schur complement), scaled by the residual variance over the
degrees of freedom. Its diagonal equals OpenCV's reported variances (``tests/test_handeye_folder.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["INTRINSIC_NAMES", "IntrinsicsCovariance", "intrinsics_covariance"]

Array = NDArray[np.float64]

#: OpenCV's order: fx fy cx cy, then the distortion coefficients.
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
                   "tx", "ty")


@dataclass(frozen=True)
class IntrinsicsCovariance:
    """Covariance of the named intrinsic parameters (px for fx..cy, unitless for distortion)."""

    names: tuple[str, ...]
    matrix: Array

    def __post_init__(self) -> None:
        m = np.asarray(self.matrix, dtype=np.float64)
        if m.shape != (len(self.names), len(self.names)) or not np.all(np.isfinite(m)):
            raise ValueError(f"intrinsics covariance: expected a finite {len(self.names)}x{len(self.names)} matrix, "
                             f"got shape {m.shape}")
        unknown = [n for n in self.names if n not in INTRINSIC_NAMES]
        if unknown:
            raise ValueError(f"intrinsics covariance: unknown parameter names {unknown}")
        object.__setattr__(self, "matrix", 0.5 * (m + m.T))

    def std(self) -> dict[str, float]:
        """1-sigma of each parameter."""
        return {n: float(np.sqrt(max(v, 0.0))) for n, v in zip(self.names, np.diag(self.matrix), strict=True)}

    @staticmethod
    def from_std(std: dict[str, float]) -> IntrinsicsCovariance:
        """A diagonal covariance (correlations unknown) from 1-sigmas; zero and non-finite ones dropped."""
        kept = [(n, float(s)) for n, s in std.items() if n in INTRINSIC_NAMES and s and np.isfinite(s)]
        return IntrinsicsCovariance(tuple(n for n, _ in kept), np.diag([s * s for _, s in kept]))

    def to_json(self) -> dict[str, Any]:
        return {"names": list(self.names), "matrix": self.matrix.tolist()}

    @staticmethod
    def from_json(d: dict[str, Any]) -> IntrinsicsCovariance:
        return IntrinsicsCovariance(tuple(str(n) for n in d["names"]), np.asarray(d["matrix"], dtype=np.float64))


def intrinsics_covariance(
    object_points: Sequence[ArrayLike],
    image_points: Sequence[ArrayLike],
    K: ArrayLike,
    dist: ArrayLike,
    rvecs: Sequence[ArrayLike],
    tvecs: Sequence[ArrayLike],
    free: Sequence[str],
) -> IntrinsicsCovariance:
    """Covariance of the intrinsic parameters ``free`` (names of :data:`INTRINSIC_NAMES`) of a
    calibration: per view the board points, their pixels and the calibrated pose (``rvec``,
    ``tvec``); ``K``, ``dist`` the calibrated intrinsics. Raises ``np.linalg.LinAlgError`` when
    the views do not determine them."""
    K_arr = np.asarray(K, dtype=np.float64).reshape(3, 3)
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    cols = [INTRINSIC_NAMES.index(n) for n in free]
    if any(c >= 4 + len(d) for c in cols):
        raise ValueError(f"intrinsics covariance: {list(free)} needs {max(cols) - 3} distortion coefficients, "
                         f"got {len(d)}")
    n = len(cols)
    H = np.zeros((n, n))
    rss, rows = 0.0, 0
    for obj, img, rvec, tvec in zip(object_points, image_points, rvecs, tvecs, strict=True):
        o = np.asarray(obj, dtype=np.float64).reshape(-1, 3)
        proj, J = cv2.projectPoints(o, np.asarray(rvec, np.float64).reshape(3), np.asarray(tvec, np.float64).reshape(3),
                                    K_arr, d)
        r = proj.reshape(-1) - np.asarray(img, dtype=np.float64).reshape(-1)
        rss += float(r @ r)
        rows += len(r)
        J_pose, J_intr = J[:, :6], J[:, 6:][:, cols]  # columns: rvec, tvec, fx fy, cx cy, distortion
        B = J_intr.T @ J_pose
        H += J_intr.T @ J_intr - B @ np.linalg.solve(J_pose.T @ J_pose, B.T)
    dof = max(rows - n - 6 * len(rvecs), 1)
    return IntrinsicsCovariance(tuple(free), rss / dof * np.linalg.inv(H))

"""Pinhole camera with OpenCV lens distortion (project, unproject, undistort, resize, crop).

Distortion coefficients follow OpenCV's order ``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]``
(4, 5, 8, 12 or 14 values; depthai reports 14). OpenCV does the distortion maths so that results
match what ``cv2.calibrateCamera`` estimated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.errors import BraveError

_VALID_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)


class Projection(NamedTuple):
    """Pixel coordinates ``uv`` (N, 2) and ``valid`` (N,) = in front of the camera (z > min_depth).

    ``uv`` of invalid points is set to 0 and must not be used: check ``valid``.
    """

    uv: NDArray[np.float64]
    valid: NDArray[np.bool_]


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of one camera: image size in pixels, focal lengths and principal point in
    pixels (pixel centres at integer coordinates, OpenCV convention) and distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy, *self.dist)
        if self.width < 1 or self.height < 1:
            raise BraveError(f"camera: image size must be positive, got {self.width}x{self.height}")
        if not all(math.isfinite(v) for v in values):
            raise BraveError("camera: intrinsics and distortion must be finite")
        if self.fx <= 0 or self.fy <= 0:
            raise BraveError(f"camera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if len(self.dist) not in _VALID_DIST_LENGTHS:
            raise BraveError(f"camera: distortion needs 4, 5, 8, 12 or 14 coefficients, got {len(self.dist)}")
        object.__setattr__(self, "dist", tuple(float(d) for d in self.dist))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float, dist: ArrayLike = ()) -> PinholeCamera:
        """Square pixels, principal point at the image centre, focal length from the horizontal FOV."""
        if not 0.0 < hfov_deg < 180.0:
            raise BraveError(f"camera: horizontal field of view must be in (0, 180) deg, got {hfov_deg}")
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0, tuple(np.asarray(dist, float).ravel()))

    @classmethod
    def from_K(cls, K: ArrayLike, width: int, height: int, dist: ArrayLike = ()) -> PinholeCamera:
        """From a 3x3 camera matrix (skew must be 0)."""
        k = np.asarray(K, dtype=np.float64).reshape(3, 3)
        if abs(k[0, 1]) > 1e-9 or not np.allclose(k[2], (0, 0, 1)):
            raise BraveError(f"camera: K must be [[fx,0,cx],[0,fy,cy],[0,0,1]], got {k.tolist()}")
        return cls(int(width), int(height), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                   tuple(np.asarray(dist, float).ravel()))

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PinholeCamera:
        """Inverse of :meth:`to_json`."""
        return cls.from_K(data["K"], data["width"], data["height"], data.get("dist", ()))

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict: width, height, K (3x3 nested list), dist (list)."""
        return {"width": self.width, "height": self.height, "K": self.K.tolist(), "dist": list(self.dist)}

    # ------------------------------------------------------------------ properties
    @property
    def K(self) -> NDArray[np.float64]:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> NDArray[np.float64]:
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan2(self.width / 2.0, self.fx))

    def without_distortion(self) -> PinholeCamera:
        return PinholeCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, ())

    # ------------------------------------------------------------------ geometry
    def project(self, points_cam: ArrayLike, min_depth: float = 1e-6) -> Projection:
        """Project (N, 3) camera-frame points to pixels, applying distortion."""
        pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        valid = np.isfinite(pts).all(axis=1) & (pts[:, 2] > min_depth)
        uv = np.zeros((len(pts), 2))
        if valid.any():
            good = pts[valid]
            if self.has_distortion:
                projected, _ = cv2.projectPoints(good, np.zeros(3), np.zeros(3), self.K, self.dist_array)
                uv[valid] = projected.reshape(-1, 2)
            else:
                uv[valid, 0] = self.fx * good[:, 0] / good[:, 2] + self.cx
                uv[valid, 1] = self.fy * good[:, 1] / good[:, 2] + self.cy
        return Projection(uv, valid)

    def normalized_rays(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Undistorted normalised coordinates ``(x/z, y/z)`` of (N, 2) pixels (iterative, tight)."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion or len(px) == 0:
            return np.stack([(px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy], axis=1)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        und = cv2.undistortPointsIter(px.reshape(-1, 1, 2), self.K, self.dist_array, None, None, criteria)
        return und.reshape(-1, 2)

    def unproject(self, pixels: ArrayLike, depth: ArrayLike) -> NDArray[np.float64]:
        """Camera-frame 3D points of (N, 2) pixels at z-depths ``depth`` (N,) metres."""
        xy = self.normalized_rays(pixels)
        z = np.broadcast_to(np.asarray(depth, dtype=np.float64).reshape(-1), (len(xy),))
        return np.stack([xy[:, 0] * z, xy[:, 1] * z, z], axis=1)

    def pixel_grid(self) -> NDArray[np.float64]:
        """(H*W, 2) pixel-centre coordinates in row-major order (u fastest)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return np.stack([u.ravel(), v.ravel()], axis=1)

    # ------------------------------------------------------------------ images
    def undistort_image(self, image: NDArray[Any], interpolation: int = cv2.INTER_LINEAR) -> NDArray[Any]:
        """Remove distortion; the result is the image of :meth:`without_distortion` (same K).

        Use ``cv2.INTER_NEAREST`` for depth or label images so that values are not blended.
        """
        if image.shape[0] != self.height or image.shape[1] != self.width:
            raise BraveError(f"camera: image is {image.shape[1]}x{image.shape[0]}, camera is {self.width}x{self.height}")
        if not self.has_distortion:
            return image.copy()
        map1, map2 = cv2.initUndistortRectifyMap(self.K, self.dist_array, None, self.K, (self.width, self.height), cv2.CV_32FC1)
        return cv2.remap(image, map1, map2, interpolation, borderMode=cv2.BORDER_CONSTANT)

    def scaled(self, width: int, height: int) -> PinholeCamera:
        """The same camera resampled to ``width`` x ``height`` (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(width, height, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                             (self.cy + 0.5) * sy - 0.5, self.dist)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> PinholeCamera:
        """The camera of the sub-image ``[y0:y0+height, x0:x0+width]``."""
        if x0 < 0 or y0 < 0 or x0 + width > self.width or y0 + height > self.height or width < 1 or height < 1:
            raise BraveError(f"camera: crop ({x0}, {y0}, {width}, {height}) lies outside {self.width}x{self.height}")
        return PinholeCamera(width, height, self.fx, self.fy, self.cx - x0, self.cy - y0, self.dist)

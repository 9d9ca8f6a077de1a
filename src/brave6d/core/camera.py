"""Pinhole camera with OpenCV lens distortion (project, unproject, undistort, resize, crop).

Distortion coefficients follow OpenCV's order ``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]``
(4, 5, 8, 12 or 14 values; depthai reports 14). OpenCV does the distortion maths so that results
match what ``cv2.calibrateCamera`` estimated.

Pixel convention (the project's K everywhere): OpenCV's, pixel ``(u, v)`` (column, row) is
centred at the integer coordinates ``(u, v)``, so its ray is ``((u - cx) / fx, (v - cy) / fy, 1)``
and a centred principal point is ``((W - 1) / 2, (H - 1) / 2)``. OpenCV calibration and OAK
factory intrinsics are in this convention. COLMAP, gsplat and OpenGL renderers (bop_toolkit's
among them) centre pixel ``(0, 0)`` at ``(0.5, 0.5)`` instead (corner origin): their K is ours with
the principal point moved by :data:`CORNER_ORIGIN_OFFSET` (:func:`corner_origin_K`), converted
once where an image or a K crosses to them.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import BraveError

_VALID_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
#: The fixed entries of a zero-skew camera matrix: (row, column) -> value.
_K_CONSTANTS = {(0, 1): 0.0, (1, 0): 0.0, (2, 0): 0.0, (2, 1): 0.0, (2, 2): 1.0}


#: Corner-origin pixel coordinates minus OpenCV's (px, both axes): pixel (0, 0) is centred at
#: (0.5, 0.5) in COLMAP, gsplat and OpenGL, at (0, 0) in OpenCV and in this project.
CORNER_ORIGIN_OFFSET = 0.5


def corner_origin_K(K: ArrayLike) -> NDArray[np.float64]:
    """The project's (OpenCV) 3x3 ``K`` in the corner-origin convention: ``cx, cy`` + 0.5 px."""
    k = np.array(K, dtype=np.float64).reshape(3, 3)
    k[0, 2] += CORNER_ORIGIN_OFFSET
    k[1, 2] += CORNER_ORIGIN_OFFSET
    return k


def opencv_K(corner_K: ArrayLike) -> NDArray[np.float64]:
    """Inverse of :func:`corner_origin_K`: a corner-origin 3x3 ``K`` in the project's convention."""
    k = np.array(corner_K, dtype=np.float64).reshape(3, 3)
    k[0, 2] -= CORNER_ORIGIN_OFFSET
    k[1, 2] -= CORNER_ORIGIN_OFFSET
    return k


class CameraError(BraveError, ValueError):
    """A bad intrinsic value; ``field`` names it (``fx``, ``K[0][2]``, ``dist[3]``, ``width``).

    File readers prefix the file and the key the camera sits under, e.g.
    ``intrinsics.json: field 'camera.K[0][2]': must be finite, got nan``.
    """

    def __init__(self, field: str, problem: str) -> None:
        self.field, self.problem = field, problem
        super().__init__(f"camera: field '{field}': {problem}" if field else f"camera: {problem}")


def _check_finite(name: str, value: float) -> None:
    """Refuse NaN and inf, naming the field."""
    if not math.isfinite(value):
        raise CameraError(name, f"must be finite, got {value}")


def _check_size(name: str, value: Any) -> int:
    """A positive whole number of pixels (an int, or a float without fraction as JSON may hold)."""
    whole = isinstance(value, numbers.Integral) or (isinstance(value, float) and value.is_integer())
    if isinstance(value, bool) or not whole or value < 1:
        raise CameraError(name, f"the image size must be a positive whole number of pixels, got {value!r}")
    return int(value)


def _float_array(name: str, values: ArrayLike) -> NDArray[np.float64]:
    """``values`` as a float64 array; something that is not numbers raises :class:`CameraError`."""
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraError(name, f"must hold numbers only, got {values!r}") from None


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
        for name in ("width", "height"):
            _check_size(name, getattr(self, name))
        for name, value in (("fx", self.fx), ("fy", self.fy), ("cx", self.cx), ("cy", self.cy),
                            *((f"dist[{i}]", d) for i, d in enumerate(self.dist))):
            _check_finite(name, value)
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                raise CameraError(name, f"the focal length must be positive, got {getattr(self, name)}")
        if len(self.dist) not in _VALID_DIST_LENGTHS:
            raise CameraError("dist", f"needs 0, 4, 5, 8, 12 or 14 coefficients, got {len(self.dist)}")
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
        """From a 3x3 camera matrix (skew must be 0); errors name the entry, e.g. ``K[0][2]``."""
        k = _float_array("K", K)
        if k.shape != (3, 3):
            raise CameraError("K", f"must be a 3x3 matrix, got shape {k.shape}")
        for i, j in zip(*np.nonzero(~np.isfinite(k)), strict=True):
            _check_finite(f"K[{i}][{j}]", k[i, j])
        for (i, j), want in _K_CONSTANTS.items():
            if not np.isclose(k[i, j], want, rtol=1e-5, atol=1e-9):
                raise CameraError(f"K[{i}][{j}]", f"must be {want:g} (K = [[fx,0,cx],[0,fy,cy],[0,0,1]]), got {k[i, j]}")
        d = _float_array("dist", dist).ravel()
        return cls(_check_size("width", width), _check_size("height", height), float(k[0, 0]), float(k[1, 1]),
                   float(k[0, 2]), float(k[1, 2]), tuple(d))

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PinholeCamera:
        """Inverse of :meth:`to_json`; a missing or bad value raises :class:`CameraError` naming it."""
        if not isinstance(data, dict):
            raise CameraError("", f"must be an object with width, height, K and dist, got {type(data).__name__}")
        for key in ("width", "height", "K"):
            if key not in data:
                raise CameraError(key, "is missing")
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

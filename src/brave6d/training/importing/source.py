"""A capture made elsewhere, as read from its files, before it becomes a scene directory.

Both readers (:mod:`.colmap_source`, :mod:`.transforms_source`) return an :class:`ImportedCapture`:
frames with their image file, camera and pose, the source's sparse points if it has any, and what
the source says about its world. Conventions are settled here, once:

- poses are ``world_T_cam`` with OpenCV camera axes (x right, y down, z forward), in the source's
  world and units (the readers convert OpenGL axes);
- cameras are in COLMAP's terms (:class:`SourceCamera`: a COLMAP model name and its parameters,
  pixel (0, 0) centred at (0.5, 0.5)), so that pycolmap projects every model, fisheye included.

Every number that becomes a pose or a point is finite and within :data:`MAX_COORDINATE`
(:func:`check_pose`): a frame whose pose is not is refused, naming it; such points are dropped and
counted (``details["points_dropped"]``), as structure from motion leaves a few stray ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import CORNER_ORIGIN_OFFSET, PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.png_check import MAX_PIXELS

#: The largest coordinate of a camera position or a point, in the source's units when read and in
#: metres after the world change (a float32 PLY holds it exactly enough; a tabletop is a metre).
MAX_COORDINATE = 1e6

#: The whole factors a folder of resampled copies may have (nerfstudio writes images_2, _4, _8).
DOWNSCALE_FACTORS = (2, 3, 4, 8, 16)

#: COLMAP camera models -> their parameter names (COLMAP's order).
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "SIMPLE_RADIAL_FISHEYE": ("f", "cx", "cy", "k"),
    "RADIAL_FISHEYE": ("f", "cx", "cy", "k1", "k2"),
    "THIN_PRISM_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1"),
    "FOV": ("fx", "fy", "cx", "cy", "omega"),
}


@dataclass(frozen=True)
class SourceCamera:
    """One camera as COLMAP describes it: ``model`` (a :data:`CAMERA_MODELS` name), image size and
    ``params`` in COLMAP's order and pixel convention (pixel (0, 0) centred at (0.5, 0.5))."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        names = CAMERA_MODELS.get(self.model)
        if names is None:
            raise DataError(f"camera model {self.model!r} is not supported (known: {', '.join(CAMERA_MODELS)})")
        if len(self.params) != len(names):
            raise DataError(f"camera model {self.model} needs {len(names)} parameters ({', '.join(names)}), "
                            f"got {len(self.params)}")
        for name, value in zip(names, self.params):
            if not np.isfinite(value):
                raise DataError(f"camera {self.model}: parameter {name} must be finite, got {value}")
        for name, value in zip(names, self.params):
            if name in ("f", "fx", "fy") and value <= 0:
                raise DataError(f"camera {self.model}: focal length {name} must be positive, got {value}")
        if self.width < 1 or self.height < 1:
            raise DataError(f"camera {self.model}: image size must be positive, got {self.width}x{self.height}")
        if self.width * self.height > MAX_PIXELS:  # the images' own limit: the resampling maps are this size
            raise DataError(f"camera {self.model}: image size {self.width}x{self.height} is more than the "
                            f"{MAX_PIXELS} pixels an image may have (MAX_PIXELS)")

    @property
    def named(self) -> dict[str, float]:
        return dict(zip(CAMERA_MODELS[self.model], self.params))

    def opencv(self) -> PinholeCamera | None:
        """The same camera as the project's :class:`PinholeCamera` (OpenCV's K and distortion), or
        None when OpenCV's radial-tangential model cannot express it (fisheye models)."""
        p = self.named
        fx = p.get("fx", p.get("f"))
        fy = p.get("fy", p.get("f"))
        assert fx is not None and fy is not None
        if self.model in ("SIMPLE_PINHOLE", "PINHOLE"):
            dist: tuple[float, ...] = ()
        elif self.model == "SIMPLE_RADIAL":
            dist = (p["k"], 0.0, 0.0, 0.0)
        elif self.model == "RADIAL":
            dist = (p["k1"], p["k2"], 0.0, 0.0)
        elif self.model == "OPENCV":
            dist = (p["k1"], p["k2"], p["p1"], p["p2"])
        elif self.model == "FULL_OPENCV":
            dist = tuple(p[k] for k in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"))
        else:
            return None
        if dist and not any(dist):
            dist = ()
        return PinholeCamera(self.width, self.height, float(fx), float(fy), p["cx"] - CORNER_ORIGIN_OFFSET,
                             p["cy"] - CORNER_ORIGIN_OFFSET, dist)

    def pinhole(self) -> PinholeCamera:
        """The pinhole part (focal lengths and principal point, OpenCV convention), no distortion."""
        p = self.named
        fx = p.get("fx", p.get("f"))
        fy = p.get("fy", p.get("f"))
        assert fx is not None and fy is not None
        return PinholeCamera(self.width, self.height, float(fx), float(fy), p["cx"] - CORNER_ORIGIN_OFFSET,
                             p["cy"] - CORNER_ORIGIN_OFFSET)

    def scaled_to(self, width: int, height: int) -> SourceCamera:
        """The same camera for images resampled to ``width`` x ``height``: focal lengths and principal
        point scale with the size (exact in COLMAP's corner-origin convention), distortion does not."""
        sx, sy = width / self.width, height / self.height
        factor = {"f": sx, "fx": sx, "cx": sx, "fy": sy, "cy": sy}
        params = tuple(v * factor.get(name, 1.0) for name, v in zip(CAMERA_MODELS[self.model], self.params))
        return SourceCamera(self.model, width, height, params)

    def same_as(self, other: SourceCamera, rtol: float = 1e-6) -> bool:
        return (self.model == other.model and (self.width, self.height) == (other.width, other.height)
                and np.allclose(self.params, other.params, rtol=rtol, atol=1e-9))

    def to_json(self) -> dict[str, Any]:
        return {"model": self.model, "width": self.width, "height": self.height, "params": self.named,
                "pixel_convention": "COLMAP (pixel (0, 0) centred at (0.5, 0.5))"}


@dataclass(frozen=True)
class SourceFrame:
    """One frame: its name in the source, its image file, its camera and ``world_T_cam`` (OpenCV axes,
    its rotation projected onto the nearest rotation; ``rotation_correction`` = ``max |R' - R|``, what
    that moved, :func:`brave6d.core.transforms.nearest_rotation`)."""

    name: str
    image: Path
    camera: SourceCamera
    world_T_cam: NDArray[np.float64]
    rotation_correction: float = 0.0


@dataclass
class ImportedCapture:
    """Everything a reader found: frames in source order, frames listed without an image file
    (``missing``), sparse points and colours (may be empty) and notes about the source."""

    format: str  # "colmap" | "transforms.json"
    source: Path
    frames: list[SourceFrame]
    missing: list[str] = field(default_factory=list)
    points: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    colors: NDArray[np.uint8] = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    points_from: str | None = None  # where the points came from (a file), None without points
    scene_box: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None  # a box the source says holds the scene
    details: dict[str, Any] = field(default_factory=dict)  # format-specific keys kept for the record

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, np.float64).reshape(-1, 3)
        self.colors = np.asarray(self.colors, np.uint8).reshape(-1, 3)
        if len(self.colors) != len(self.points):  # no (or mismatched) colours: grey
            self.colors = np.full((len(self.points), 3), 128, np.uint8)
        for frame in self.frames:
            check_pose(frame.world_T_cam, f"{self.source}: frame {frame.name!r}", "source units")
        keep = bounded_rows(self.points)
        if not keep.all():
            self.details["points_dropped"] = (f"{int((~keep).sum())} points not finite or beyond "
                                              f"{MAX_COORDINATE:g} source units (MAX_COORDINATE)")
            self.points, self.colors = self.points[keep], self.colors[keep]


def bounded_rows(values: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which rows of ``values`` are finite and within :data:`MAX_COORDINATE` in every column."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(values).all(axis=1) & (np.abs(values) <= MAX_COORDINATE).all(axis=1)


def check_pose(pose: NDArray[np.float64], where: str, units: str) -> None:
    """A 4x4 pose whose numbers are finite and whose position is within :data:`MAX_COORDINATE`
    ``units``; else :class:`DataError` naming ``where`` and the bound."""
    m = np.asarray(pose, np.float64)
    if not np.isfinite(m).all():
        raise DataError(f"{where}: the pose holds a number that is not finite")
    if not bounded_rows(m[None, :3, 3]).all():
        shown = ", ".join(f"{v:.6g}" for v in m[:3, 3])
        raise DataError(f"{where}: the camera position ({shown}) has a coordinate beyond +-{MAX_COORDINATE:g} "
                        f"{units} (MAX_COORDINATE)")


def downscale_factor(camera: SourceCamera, image_size: tuple[int, int]) -> int | None:
    """The whole factor ``k`` that makes ``image_size`` (width, height) the camera's size divided by
    ``k`` (rounded, or floored as ffmpeg and ns-process-data do), 1 for the camera's own size, None
    when neither: copies resampled by another amount or another camera's images."""
    if tuple(image_size) == (camera.width, camera.height):
        return 1
    for k in DOWNSCALE_FACTORS:
        sizes = {(round(camera.width / k), round(camera.height / k)), (camera.width // k, camera.height // k)}
        if tuple(image_size) in sizes:
            return k
    return None

"""The imported scene's world: metric scale, "up" along +z, the scene's centre at the origin.

A COLMAP model or a ``transforms.json`` is in arbitrary units (structure from motion fixes the scale
only up to a factor) and an arbitrary orientation; the render server needs metres (collision radii,
the agents' step sizes, depth in mm) and a world whose +z is up (agents look at the scene with "up"
= +z, as the robot base frame is). Neither format records either, so both come from the user and
the import says which:

- scale: ``--scale FACTOR`` (metres per source unit; 1 when the source is metric, e.g. ARKit
  poses) or ``--scale-from-distance FRAME_A FRAME_B METRES`` (the distance between two camera
  centres, measured in the real world); neither: :data:`DEFAULT_SCALE` (the source's units are
  kept and called metres). Training does not depend on the choice (it trains in the scene's own
  frame, :mod:`brave6d.training.scene_frame`); what does is everything metric downstream: the
  render server's camera radius and the agents' steps and distances, annotated objects' sizes,
  BOP's millimetre thresholds;
- up: ``--up x,y,z`` (a direction in the source's world) or ``--up auto`` (the default): for photos
  taken upright, the direction perpendicular to every camera's image rows, on the side of their up
  vectors (:func:`resolve_up`); how far the rows are from level is recorded, and cameras rolled
  different ways are refused (then ``--up x,y,z`` is needed).

The new world is ``p_new = scale * R_up @ (p_source - centre)``: rotated so that "up" is +z (the
smallest rotation that does so), scaled to metres and moved so that the scene's centre (where the
cameras' optical axes meet, else the median of the points, else the mean camera centre) is the
origin. :class:`WorldChange` keeps the similarity, so the import record can map anything back.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.errors import DataError
from brave6d.training.pose_check import axes_meeting_point

#: ``--up auto`` refuses when the cameras' up vectors cancel out (their mean is shorter than this).
MIN_UP_AGREEMENT = 0.15
#: ``--up auto`` refuses cameras whose image rows are this far from level (median, degrees).
MAX_ROLL_DEG = 20.0


#: Metres per source unit when the import is given no scale: the source's units are kept.
DEFAULT_SCALE = 1.0
#: What the default scale means, for the import's output and record.
DEFAULT_SCALE_NOTE = ("the default, 1 (no --scale or --scale-from-distance given: the source's units are kept and "
                      "called metres; training does not depend on it, but the server's camera radius, the agents' "
                      "steps and distances and annotated objects are metric: give --scale-from-distance FRAME_A "
                      "FRAME_B METRES for a metric scene)")


@dataclass(frozen=True)
class ScaleChoice:
    """Metres per source unit, or how to measure it; :meth:`default`: none was given."""

    factor: float | None = None
    distance: tuple[str, str, float] | None = None  # (frame a, frame b, metres)
    is_default: bool = False

    @classmethod
    def default(cls) -> ScaleChoice:
        """The scale of an import given none: :data:`DEFAULT_SCALE` (module docstring)."""
        return cls(factor=DEFAULT_SCALE, is_default=True)

    def describe(self) -> str:
        if self.is_default:
            return DEFAULT_SCALE_NOTE
        if self.factor is not None:
            return f"--scale {self.factor:g} (given)"
        assert self.distance is not None
        a, b, metres = self.distance
        return f"--scale-from-distance {a} {b} {metres:g} m (camera centres)"


@dataclass(frozen=True)
class UpChoice:
    """The source's "up" direction, or ``auto``."""

    vector: tuple[float, float, float] | None = None  # None: auto


@dataclass(frozen=True)
class WorldChange:
    """``p_new = scale * R @ (p_source - centre)`` and how each part was chosen."""

    scale: float
    R: NDArray[np.float64]
    centre: NDArray[np.float64]
    scale_from: str
    up_source: NDArray[np.float64]  # the "up" direction in the source's world (unit)
    up_from: str
    centre_from: str

    def points(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.scale * (np.asarray(p, np.float64).reshape(-1, 3) - self.centre) @ self.R.T

    def pose(self, world_T_cam: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.eye(4)
        out[:3, :3] = self.R @ world_T_cam[:3, :3]
        out[:3, 3] = self.points(world_T_cam[:3, 3])[0]
        return out

    @property
    def new_T_source(self) -> NDArray[np.float64]:
        """The similarity as a 4x4 matrix (scaled rotation): ``p_new = M @ [p_source, 1]``."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = -self.scale * self.R @ self.centre
        return M

    def to_json(self) -> dict[str, Any]:
        return {"metres_per_source_unit": self.scale, "scale_from": self.scale_from,
                "up_in_source": self.up_source.tolist(), "up_from": self.up_from,
                "centre_in_source": self.centre.tolist(), "centre_from": self.centre_from,
                "new_T_source": self.new_T_source.tolist(),
                "convention": "p_new = new_T_source @ [p_source, 1]: metres, +z up, the scene's centre at the origin"}


def parse_up(text: str) -> UpChoice:
    """``auto`` or ``x,y,z`` (not all zero, finite)."""
    if text.strip().lower() == "auto":
        return UpChoice(None)
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise DataError(f"--up: 'auto' or three numbers x,y,z are required, got {text!r}") from None
    if len(values) != 3 or not all(np.isfinite(values)) or np.linalg.norm(values) < 1e-12:
        raise DataError(f"--up: a finite, non-zero direction x,y,z is required, got {text!r}")
    return UpChoice((values[0], values[1], values[2]))


def camera_centres(poses: Sequence[NDArray[np.float64]]) -> NDArray[np.float64]:
    return np.array([np.asarray(T)[:3, 3] for T in poses], np.float64).reshape(-1, 3)


def resolve_scale(choice: ScaleChoice, poses: dict[str, NDArray[np.float64]]) -> tuple[float, str]:
    """Metres per source unit and how it was found; ``--scale-from-distance`` errors name a frame
    that is not there."""
    if choice.factor is not None:
        if not (np.isfinite(choice.factor) and choice.factor > 0):
            raise DataError(f"--scale: a positive number of metres per source unit is required, got {choice.factor}")
        return float(choice.factor), choice.describe()
    assert choice.distance is not None
    a, b, metres = choice.distance
    a, b = _frame_named(a, poses), _frame_named(b, poses)
    if not (np.isfinite(metres) and metres > 0):
        raise DataError(f"--scale-from-distance: the distance must be a positive number of metres, got {metres}")
    d = float(np.linalg.norm(poses[a][:3, 3] - poses[b][:3, 3]))
    if not np.isfinite(d) or d < 1e-9:
        raise DataError(f"--scale-from-distance: frames {a} and {b} have the same camera centre in the source; "
                        "pick two frames taken apart")
    return metres / d, ScaleChoice(distance=(a, b, metres)).describe()


def _frame_named(name: str, poses: dict[str, NDArray[np.float64]]) -> str:
    """The frame ``name`` names: its name in the source, else its file name or the file name
    without extension when exactly one frame has it."""
    from pathlib import PurePosixPath

    if name in poses:
        return name
    for key in (lambda n: PurePosixPath(n).name, lambda n: PurePosixPath(n).stem):
        hits = [n for n in poses if key(n) == name]
        if len(hits) == 1:
            return hits[0]
    raise DataError(f"--scale-from-distance: no imported frame named {name!r} (frames are named as in the source, "
                    f"e.g. {next(iter(poses))!r}, or by its file name)")


def resolve_up(choice: UpChoice, poses: Sequence[NDArray[np.float64]]) -> tuple[NDArray[np.float64], str]:
    """The unit "up" in the source's world and how it was found.

    ``auto``: photos taken upright have their x axes (image rows) horizontal, whatever their
    elevation, so "up" is the direction most nearly perpendicular to every camera's x axis (the
    smallest eigenvector of their scatter), signed to agree with the cameras' mean up vector (-y).
    When the x axes are all nearly parallel (a straight-line capture) that plane is undetermined and
    the mean up vector is used itself. Cameras rolled different ways are refused.
    """
    if choice.vector is not None:
        v = np.asarray(choice.vector, np.float64)
        return v / np.linalg.norm(v), f"--up {','.join(f'{x:g}' for x in choice.vector)} (given)"
    R = np.array([np.asarray(T)[:3, :3] for T in poses], np.float64).reshape(-1, 3, 3)
    R = R[np.isfinite(R).all(axis=(1, 2))]
    if len(R) == 0:
        raise DataError("--up auto: no camera pose to take 'up' from")
    xs, ups = R[:, :, 0], -R[:, :, 1]
    mean_up = ups.mean(axis=0)
    eigval, eigvec = np.linalg.eigh(xs.T @ xs / len(xs))
    if eigval[1] < 0.05:  # every x axis nearly parallel: the plane they span is undetermined
        agreement = float(np.linalg.norm(mean_up))
        if agreement < MIN_UP_AGREEMENT:
            raise DataError("--up auto: the cameras all face one way and their up vectors disagree; give the up "
                            "direction with --up x,y,z")
        up, how = mean_up / agreement, "the mean of the cameras' up vectors (their x axes are all parallel)"
    else:
        up = eigvec[:, 0]
        side = float(up @ mean_up) / max(float(np.linalg.norm(mean_up)), 1e-12)
        if abs(side) < MIN_UP_AGREEMENT / 2 or float(np.linalg.norm(mean_up)) < 1e-6:
            raise DataError("--up auto: the cameras' up vectors do not tell which side is up (photos turned upside "
                            "down or both ways); give the up direction with --up x,y,z")
        up = up if side > 0 else -up
        how = "perpendicular to the cameras' x axes (image rows), on the side of their up vectors"
    tilt = np.degrees(np.arcsin(np.clip(np.abs(xs @ up), 0.0, 1.0)))
    if float(np.median(tilt)) > MAX_ROLL_DEG:
        raise DataError(f"--up auto: the cameras are rolled different ways (image rows {float(np.median(tilt)):.0f} deg "
                        f"from level, median; more than {MAX_ROLL_DEG:g}): photos not taken upright; give the up "
                        "direction with --up x,y,z")
    return up, (f"--up auto: {how}, over {len(R)} cameras (image rows off level: median "
                f"{float(np.median(tilt)):.1f} deg, largest {float(tilt.max()):.1f} deg)")


def scene_centre(poses: Sequence[NDArray[np.float64]], points: NDArray[np.float64]) -> tuple[NDArray[np.float64], str]:
    """Where the optical axes meet, else the median of the points, else the mean camera centre."""
    meet = axes_meeting_point(poses)
    if meet is not None:
        return meet, "where the cameras' optical axes meet (least squares)"
    if len(points):
        return np.median(points, axis=0), f"the median of the {len(points)} sparse points"
    return camera_centres(poses).mean(axis=0), "the mean camera centre (the optical axes do not meet)"


def world_change(poses: dict[str, NDArray[np.float64]], points: NDArray[np.float64], scale: ScaleChoice,
                 up: UpChoice) -> WorldChange:
    """The similarity that makes the imported world metric, z-up and centred (module docstring)."""
    factor, scale_from = resolve_scale(scale, poses)
    up_source, up_from = resolve_up(up, list(poses.values()))
    R = _rotation_onto_z(up_source)
    centre, centre_from = scene_centre(list(poses.values()), points)
    return WorldChange(factor, R, centre, scale_from, up_source, up_from, centre_from)


def _rotation_onto_z(up: NDArray[np.float64]) -> NDArray[np.float64]:
    """The smallest rotation taking ``up`` (unit) to +z; a half turn about x when ``up`` is -z."""
    z = np.array([0.0, 0.0, 1.0])
    if float(up @ z) < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    axis = np.cross(up, z)
    s, c = float(np.linalg.norm(axis)), float(up @ z)
    if s < 1e-15:
        return np.eye(3)
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()

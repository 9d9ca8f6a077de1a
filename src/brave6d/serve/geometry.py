"""Camera collision checks and twist integration for the render server.

The camera is a **sphere** of radius ``camera_radius`` (metres) around its optical centre.
A pose is *free* when

* the camera centre lies inside the workspace (axis-aligned box in the world frame, bounds
  inclusive), and
* the sphere does not intersect any collision box (oriented boxes in the world frame: the
  distance from the centre to the box, computed in the box frame, is at least the radius;
  touching is allowed).

Twists (:func:`integrate_twist`) are constant over the move's duration, in one of two frames:

* ``"camera"`` (default, a body twist): ``linear`` (m/s) and ``angular`` (rad/s) are expressed
  in the camera frame at every instant (OpenCV axes: +x right, +y down, +z forward), i.e.
  ``d/dt world_T_cam = world_T_cam @ hat(xi)``. The exact solution is the SE(3) exponential
  ``world_T_cam(t) = world_T_cam(0) @ exp(t * hat(xi))`` (a screw motion: "fly forward while
  turning").
* ``"world"``: ``linear`` is the velocity of the camera centre in the world frame and
  ``angular`` is a world-frame angular velocity about the camera centre (the camera turns in
  place while its centre moves in a straight line): ``p(t) = p0 + t v``,
  ``R(t) = exp(t hat(w)) R0``.

Both are evaluated in closed form at the ends of small substeps (at most ``max_step_m`` of
travel and ``max_step_rad`` of rotation each, scipy ``Rotation`` exponentials). Every substep
end is checked, and so is the sphere swept along the straight chord between consecutive ends
(the path deviates from the chord by far less than a millimetre at these step sizes), so even a
box thinner than a substep is never crossed. The motion stops at the last free substep end.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.transforms import invert, make_transform

Matrix4 = NDArray[np.float64]

#: Default camera radius (metres): a small sphere around the optical centre.
DEFAULT_CAMERA_RADIUS = 0.02
#: Largest translation of one integration substep (metres).
MAX_STEP_M = 0.005
#: Largest rotation of one integration substep (radians).
MAX_STEP_RAD = np.deg2rad(2.0)
#: Upper bound on the number of substeps of one move (a move that needs more is refused upstream).
MAX_SUBSTEPS = 20_000


@dataclass(frozen=True)
class OrientedBox:
    """A box in the world frame: ``world_T_box`` (centre, axes along the edges) and full ``size``."""

    name: str
    world_T_box: Matrix4
    size: tuple[float, float, float]

    def __post_init__(self) -> None:
        object.__setattr__(self, "world_T_box", np.asarray(self.world_T_box, dtype=np.float64))
        object.__setattr__(self, "size", tuple(float(s) for s in self.size))
        object.__setattr__(self, "_box_T_world", invert(self.world_T_box))

    def distance(self, point_world: ArrayLike) -> float:
        """Euclidean distance from a world point to the box (0 inside)."""
        p = np.asarray(point_world, dtype=np.float64).reshape(3)
        T = self._box_T_world  # type: ignore[attr-defined]
        q = T[:3, :3] @ p + T[:3, 3]
        half = 0.5 * np.asarray(self.size)
        outside = np.maximum(np.abs(q) - half, 0.0)
        return float(np.linalg.norm(outside))

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "world_T_box": self.world_T_box.tolist(), "size": list(self.size)}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> OrientedBox:
        return cls(str(data["name"]), np.asarray(data["world_T_box"], dtype=np.float64), tuple(data["size"]))


@dataclass(frozen=True)
class Workspace:
    """Axis-aligned bounds (world frame) that the camera centre must stay inside (inclusive)."""

    min: tuple[float, float, float]
    max: tuple[float, float, float]

    def violation(self, point_world: ArrayLike) -> str | None:
        """None when inside, else a message naming the axis and the bound."""
        p = np.asarray(point_world, dtype=np.float64).reshape(3)
        for axis, name in enumerate("xyz"):
            if p[axis] < self.min[axis]:
                return f"camera centre {name}={p[axis]:.4f} m is below the workspace minimum {self.min[axis]:.4f} m"
            if p[axis] > self.max[axis]:
                return f"camera centre {name}={p[axis]:.4f} m is above the workspace maximum {self.max[axis]:.4f} m"
        return None

    def to_json(self) -> dict[str, Any]:
        return {"min": list(self.min), "max": list(self.max)}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Workspace:
        return cls(tuple(float(v) for v in data["min"]), tuple(float(v) for v in data["max"]))  # type: ignore[arg-type]


@dataclass(frozen=True)
class Refusal:
    """Why a pose is not free: ``reason`` is ``"collision"`` or ``"workspace"``."""

    reason: str
    message: str
    box: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {"reason": self.reason, "message": self.message, "box": self.box}


@dataclass(frozen=True)
class CollisionWorld:
    """The collision boxes, the workspace and the camera's collision sphere."""

    boxes: tuple[OrientedBox, ...]
    workspace: Workspace
    camera_radius: float = DEFAULT_CAMERA_RADIUS

    def check(self, world_T_cam: ArrayLike) -> Refusal | None:
        """None when the pose is free, else the first reason it is not (workspace first)."""
        centre = np.asarray(world_T_cam, dtype=np.float64)[:3, 3]
        message = self.workspace.violation(centre)
        if message is not None:
            return Refusal("workspace", f"outside the workspace: {message}")
        for box in self.boxes:
            d = box.distance(centre)
            if d < self.camera_radius or d == 0.0:  # (d == 0: the centre is inside, for radius 0)
                return Refusal("collision", f"the camera (sphere of radius {self.camera_radius:.3f} m) would "
                               f"collide with box '{box.name}' (distance {d:.4f} m)", box.name)
        return None

    def check_segment(self, p0: ArrayLike, p1: ArrayLike) -> Refusal | None:
        """Whether the sphere swept along the straight segment ``p0 -> p1`` hits a box.

        The endpoints must be free (see :meth:`check`); the workspace is convex, so the segment
        stays inside it. The distance to a box is convex along a segment, so a cheap bound
        (``(d0 + d1 - L) / 2``) clears most segments and a golden-section search finds the
        minimum of the others.
        """
        a = np.asarray(p0, dtype=np.float64).reshape(3)
        b = np.asarray(p1, dtype=np.float64).reshape(3)
        length = float(np.linalg.norm(b - a))
        for box in self.boxes:
            d0, d1 = box.distance(a), box.distance(b)
            if 0.5 * (d0 + d1 - length) >= self.camera_radius:
                continue
            lo, hi = 0.0, 1.0
            g = 0.5 * (np.sqrt(5.0) - 1.0)
            x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
            f1, f2 = box.distance(a + x1 * (b - a)), box.distance(a + x2 * (b - a))
            best = min(d0, d1, f1, f2)
            for _ in range(60):
                if f1 < f2:
                    hi, x2, f2 = x2, x1, f1
                    x1 = hi - g * (hi - lo)
                    f1 = box.distance(a + x1 * (b - a))
                else:
                    lo, x1, f1 = x1, x2, f2
                    x2 = lo + g * (hi - lo)
                    f2 = box.distance(a + x2 * (b - a))
                best = min(best, f1, f2)
                if best < self.camera_radius or best == 0.0 or hi - lo < 1e-9:
                    break
            if best < self.camera_radius or best == 0.0:
                return Refusal("collision", f"the camera (sphere of radius {self.camera_radius:.3f} m) would "
                               f"pass through box '{box.name}' (closest {best:.4f} m)", box.name)
        return None


# ----------------------------------------------------------------------------- twists
def _hat(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def se3_exp(linear: ArrayLike, angular: ArrayLike) -> Matrix4:
    """``exp(hat(xi))`` of a twist ``xi = (linear, angular)`` (closed form, exact)."""
    v = np.asarray(linear, dtype=np.float64).reshape(3)
    w = np.asarray(angular, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(w))
    R = Rotation.from_rotvec(w).as_matrix()
    W = _hat(w)
    if theta < 1e-6:  # series of (1 - cos)/t^2 and (t - sin)/t^3
        a, b = 0.5 - theta**2 / 24.0, 1.0 / 6.0 - theta**2 / 120.0
    else:
        a = (1.0 - np.cos(theta)) / theta**2
        b = (theta - np.sin(theta)) / theta**3
    V = np.eye(3) + a * W + b * (W @ W)
    return make_transform(R, V @ v)


def pose_after(world_T_cam: Matrix4, linear: ArrayLike, angular: ArrayLike, t: float, frame: str) -> Matrix4:
    """The pose after moving with the constant twist for ``t`` seconds (see the module docstring)."""
    v = np.asarray(linear, dtype=np.float64).reshape(3) * t
    w = np.asarray(angular, dtype=np.float64).reshape(3) * t
    if frame == "camera":
        return world_T_cam @ se3_exp(v, w)
    if frame == "world":
        R = Rotation.from_rotvec(w).as_matrix() @ world_T_cam[:3, :3]
        return make_transform(R, world_T_cam[:3, 3] + v)
    raise ValueError(f"twist frame must be 'camera' or 'world', got {frame!r}")


def substep_count(linear: ArrayLike, angular: ArrayLike, duration: float,
                  max_step_m: float = MAX_STEP_M, max_step_rad: float = MAX_STEP_RAD) -> int:
    """Number of substeps so that none moves more than ``max_step_m`` or turns more than ``max_step_rad``.

    For a camera-frame screw the centre's path length is ``|v| t`` (the body velocity's norm
    is the speed of the centre), so the bound holds in both frames.

    Raises ``ValueError`` when the count is not finite (a NaN, or a twist so large that its
    length overflows), instead of failing to convert it to an integer.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        dist = float(np.linalg.norm(np.asarray(linear, dtype=np.float64))) * duration
        angle = float(np.linalg.norm(np.asarray(angular, dtype=np.float64))) * duration
    need = max(dist / max_step_m, angle / max_step_rad)
    if not np.isfinite(need) or np.isnan(dist) or np.isnan(angle):
        raise ValueError(f"the move's length is not a finite number (|linear| t = {dist:g} m, "
                         f"|angular| t = {angle:g} rad): velocities and duration must be finite and bounded")
    return max(1, int(np.ceil(need)))


@dataclass(frozen=True)
class MoveResult:
    """Outcome of :func:`integrate_twist`.

    ``world_T_cam``: the final pose (the start pose when the very first substep is blocked);
    ``refusal``: why the motion stopped early (None when it ran the whole ``duration``);
    ``fraction``: the share of the duration travelled; ``path_m``: distance travelled by the centre.
    """

    world_T_cam: Matrix4
    refusal: Refusal | None
    fraction: float
    substeps: int
    path_m: float
    trajectory: list[Matrix4] = field(default_factory=list, repr=False)

    @property
    def moved(self) -> bool:
        return self.fraction > 0.0

    @property
    def collided(self) -> bool:
        return self.refusal is not None


def integrate_twist(world: CollisionWorld, world_T_cam: ArrayLike, linear: Sequence[float] | ArrayLike,
                    angular: Sequence[float] | ArrayLike, duration: float, frame: str = "camera",
                    max_step_m: float = MAX_STEP_M, max_step_rad: float = MAX_STEP_RAD,
                    keep_trajectory: bool = False) -> MoveResult:
    """Move with a constant twist for ``duration`` s, stopping at the last free substep.

    Raises ``ValueError`` for a negative/non-finite duration, an unknown frame, or a move that
    would need more than :data:`MAX_SUBSTEPS` substeps.
    """
    T0 = np.asarray(world_T_cam, dtype=np.float64)
    if not np.isfinite(duration) or duration < 0:
        raise ValueError(f"duration must be a finite number >= 0, got {duration}")
    if frame not in ("camera", "world"):
        raise ValueError(f"twist frame must be 'camera' or 'world', got {frame!r}")
    n = substep_count(linear, angular, duration, max_step_m, max_step_rad)
    if n > MAX_SUBSTEPS:
        raise ValueError(f"the move is too long: it needs {n} substeps of at most {max_step_m * 1000:.1f} mm / "
                         f"{np.rad2deg(max_step_rad):.1f} deg (limit {MAX_SUBSTEPS})")
    last = T0
    path = 0.0
    traj: list[Matrix4] = [T0] if keep_trajectory else []
    for k in range(1, n + 1):
        T = pose_after(T0, linear, angular, duration * k / n, frame)
        refusal = world.check(T)
        if refusal is None:
            refusal = world.check_segment(last[:3, 3], T[:3, 3])
        if refusal is not None:
            return MoveResult(last, refusal, (k - 1) / n, k - 1, path, traj)
        path += float(np.linalg.norm(T[:3, 3] - last[:3, 3]))
        last = T
        if keep_trajectory:
            traj.append(T)
    return MoveResult(last, None, 1.0 if duration > 0 else 0.0, n, path, traj)

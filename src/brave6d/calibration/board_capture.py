"""The ChArUco board capture of a scene directory: plan the views the robot can reach, capture them.

:func:`plan_board_capture` turns :func:`~brave6d.calibration.plan.plan_for_board` poses into views for
the capture runner (:class:`BoardView` satisfies ``brave6d.capture.runner.PlannedView``). Every view
is checked on the robot itself (its ``inverse_kinematics``, so a real UR answers for its own
limits) and kept only if

* the camera stays inside the spec's ``workspace`` box;
* the TCP pose has an IK solution;
* that solution, the one closest to the frontal view's joints, turns no joint by more than
  ``max_joint_step_deg`` from there: a larger turn means another arm configuration (shoulder
  or elbow flipped), and a calibration capture must not swing the arm over the table.

Views dropped for these reasons are replaced by the next ones of the plan's sequence, so the
plan keeps the requested number whenever it can. The kept views are visited in a greedy
nearest-neighbour order in joint space (shorter robot time, no effect on the calibration).

:func:`capture_board` runs ``capture.run_capture`` into ``calibration/board_capture/``: it is
resumable (``resume``) and refuses to touch an existing capture without ``resume`` or
``force`` BEFORE any robot or camera is opened; ``force`` moves the old capture aside.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.distance import cdist

from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.core.board import board_size_m
from brave6d.core.errors import BraveError, DataError, DegenerateGeometryError
from brave6d.core.layout import CaptureLayout
from brave6d.core.spec import SceneSpec
from brave6d.core.transforms import check_rigid
from brave6d.calibration.plan import PlannedPose, plan_for_board

if TYPE_CHECKING:
    from brave6d.capture import Robot

__all__ = [
    "BoardCaptureExistsError",
    "BoardCaptureResult",
    "BoardPlan",
    "BoardView",
    "capture_board",
    "check_capture_state",
    "default_distance",
    "plan_board_capture",
    "plan_only",
]

SCHEMA = "brave6d.board_plan/1"
Array = NDArray[np.float64]

#: The board's width takes this fraction of the image width in the frontal view.
BOARD_FILL = 0.6
#: Views of a full board capture (see the synthetic study in brave6d.calibration.plan).
DEFAULT_VIEWS = 30
#: Largest joint turn (deg) from the frontal view's joints within one arm configuration.
MAX_JOINT_STEP_DEG = 120.0


class BoardCaptureExistsError(BraveError):
    """The board capture folder holds frames and neither resume nor force was asked for."""


@dataclass(frozen=True)
class BoardView:
    """One planned board view (the capture runner's ``PlannedView``) and how it was made."""

    view_id: str
    distance_level: int
    distance_m: float
    base_T_tcp: Array
    joints: Array
    base_T_cam: Array
    tilt_deg: float
    azimuth_deg: float
    roll_deg: float

    def to_json(self) -> dict[str, Any]:
        return {"view_id": self.view_id, "distance_level": self.distance_level, "distance_m": self.distance_m,
                "base_T_tcp": self.base_T_tcp.tolist(), "joints": self.joints.tolist(),
                "base_T_cam": self.base_T_cam.tolist(), "tilt_deg": self.tilt_deg,
                "azimuth_deg": self.azimuth_deg, "roll_deg": self.roll_deg}

    @staticmethod
    def from_json(d: dict[str, Any], where: str) -> BoardView:
        joints = np.asarray(d["joints"], dtype=np.float64).reshape(-1)
        if joints.shape != (6,) or not np.all(np.isfinite(joints)):
            raise ValueError(f"{where}.joints: expected 6 finite joint angles")
        return BoardView(str(d["view_id"]), int(d["distance_level"]), float(d["distance_m"]),
                         check_rigid(d["base_T_tcp"], f"{where}.base_T_tcp"), joints,
                         check_rigid(d["base_T_cam"], f"{where}.base_T_cam"), float(d["tilt_deg"]),
                         float(d["azimuth_deg"]), float(d["roll_deg"]))


@dataclass(frozen=True)
class BoardPlan:
    """Views to capture (in visiting order), views left out with the reason, and the settings."""

    views: list[BoardView]
    dropped: list[dict[str, str]]
    requested: int
    distance_m: float
    tcp_T_cam_guess: Array
    meta: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "requested": self.requested, "distance_m": self.distance_m,
                "tcp_T_cam_guess": self.tcp_T_cam_guess.tolist(), "meta": self.meta,
                "views": [v.to_json() for v in self.views], "dropped": self.dropped}

    def save(self, path: Path | str) -> Path:
        """Write the plan JSON atomically."""
        return atomic_write_json(path, self.to_json())

    @staticmethod
    def load(path: Path | str) -> BoardPlan:
        """Read a plan written by :meth:`save`; errors name the file and the field."""
        d = read_json(path)
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise DataError(f"{path}: not a board capture plan (expected schema {SCHEMA!r})")
        try:
            views = [BoardView.from_json(v, f"views[{i}]") for i, v in enumerate(d["views"])]
            return BoardPlan(views, [dict(x) for x in d.get("dropped", [])], int(d["requested"]),
                             float(d["distance_m"]), check_rigid(d["tcp_T_cam_guess"], "tcp_T_cam_guess"),
                             dict(d.get("meta", {})))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{path}: malformed board plan ({type(exc).__name__}: {exc})") from None


def default_distance(spec: SceneSpec) -> float:
    """Camera-to-board distance (m) at which the frontal board fills :data:`BOARD_FILL` of the width."""
    cam = spec.camera.pinhole()
    return board_size_m(spec.board)[0] * cam.fx / (BOARD_FILL * cam.width)


def _mounting_guess(spec: SceneSpec) -> Array:
    if spec.robot.tcp_T_camera_guess is None:
        raise DataError(f"{spec.source}: field 'robot.tcp_T_camera_guess' is needed to plan the board capture "
                        "(the rough camera mounting, e.g. from the CAD drawing)")
    return spec.robot.tcp_T_camera_guess.matrix()


def _outside_workspace(spec: SceneSpec, position: Array) -> str:
    lo, hi = np.asarray(spec.workspace.min), np.asarray(spec.workspace.max)
    for k, axis in enumerate("xyz"):
        if not lo[k] <= position[k] <= hi[k]:
            return (f"camera {axis} = {position[k]:.3f} m outside the workspace "
                    f"[{lo[k]:.3f}, {hi[k]:.3f}] m")
    return ""


def _visit_order(joints: Array, start: Array) -> list[int]:
    """Greedy nearest neighbour from ``start``; distance = largest joint turn (moveJ time)."""
    cost = cdist(joints, joints, metric="chebyshev")
    left = set(range(len(joints)))
    current = int(np.argmin(cdist(start[None], joints, metric="chebyshev")[0]))
    order = [current]
    left.remove(current)
    while left:
        current = min(left, key=lambda j: cost[current, j])
        order.append(current)
        left.remove(current)
    return order


def plan_board_capture(
    spec: SceneSpec,
    robot: Robot,
    n_views: int = DEFAULT_VIEWS,
    distance_m: float | None = None,
    max_joint_step_deg: float = MAX_JOINT_STEP_DEG,
) -> BoardPlan:
    """Plan ``n_views`` board views that ``robot`` can reach (its IK and joints only; nothing moves).

    Raises :class:`DegenerateGeometryError` when the frontal view is unreachable or fewer than
    three views remain (hand-eye calibration needs at least three poses).
    """
    guess = _mounting_guess(spec)
    distance = default_distance(spec) if distance_m is None else float(distance_m)
    cam = spec.camera.pinhole()
    candidates: list[PlannedPose] = plan_for_board(spec.board, distance, guess, n_views + max(6, n_views // 2),
                                                   K=cam.K, image_size=(cam.width, cam.height))
    start = np.asarray(robot.joints(), dtype=np.float64)
    seed = robot.inverse_kinematics(candidates[0].base_T_tcp, start)
    if seed is None:
        raise DegenerateGeometryError(
            f"{spec.source}: the frontal board view (camera {distance:.2f} m above the board at "
            f"{list(spec.board.pose.xyz)}) is out of the robot's reach; move the board (field 'board.pose') "
            "closer to the robot")
    kept: list[tuple[PlannedPose, Array]] = []
    dropped: list[dict[str, str]] = []
    for pose in candidates:
        if len(kept) == n_views:
            break
        reason = _outside_workspace(spec, pose.base_T_cam[:3, 3])
        q = None if reason else robot.inverse_kinematics(pose.base_T_tcp, seed)
        if not reason and q is None:
            reason = "unreachable: no inverse kinematics solution"
        elif q is not None:
            step = np.degrees(np.abs(np.asarray(q) - seed))
            if step.max() > max_joint_step_deg:
                reason = (f"needs another arm configuration: joint {int(step.argmax()) + 1} would turn "
                          f"{step.max():.0f} deg from the frontal view (> {max_joint_step_deg:g})")
        if reason:
            dropped.append({"view_id": pose.name, "reason": reason})
        else:
            kept.append((pose, np.asarray(q, dtype=np.float64)))
    if len(kept) < 3:
        shown = "; ".join(f"{d['view_id']}: {d['reason']}" for d in dropped[:3])
        raise DegenerateGeometryError(f"{spec.source}: only {len(kept)} board views are reachable, at least 3 "
                                      f"needed ({shown})")
    order = _visit_order(np.stack([q for _, q in kept]), start)
    views = [BoardView(p.name, 0, p.distance_m, p.base_T_tcp, q, p.base_T_cam, p.tilt_deg, p.azimuth_deg,
                       p.roll_deg) for p, q in (kept[i] for i in order)]
    meta = {"board": spec.board.model_dump(mode="json"), "max_joint_step_deg": max_joint_step_deg,
            "max_tilt_deg": max(p.tilt_deg for p, _ in kept), "max_roll_deg": max(abs(p.roll_deg) for p, _ in kept)}
    return BoardPlan(views, dropped, n_views, distance, guess, meta)


def check_capture_state(layout: CaptureLayout, resume: bool, force: bool) -> int:
    """Frames already in ``layout``; refuses (before any device is opened) when there are some and
    neither ``resume`` nor ``force`` is given."""
    done = len(layout.frames())
    if done and not (resume or force):
        raise BoardCaptureExistsError(
            f"{layout.frames_path}: a board capture with {done} frames exists; pass --resume to continue "
            "(and recalibrate) or --force to move it aside and capture again")
    return done



@dataclass(frozen=True)
class BoardCaptureResult:
    """What :func:`capture_board` did: the plan used, frames written now and in all, robot time."""

    plan: BoardPlan
    written: int
    total: int
    robot_seconds: float


def plan_only(layout: CaptureLayout, spec: SceneSpec, robot: str, camera: str, n_views: int,
              distance_m: float | None = None) -> BoardPlan:
    """Plan the board capture with the named robot and write ``plan.json``; refuses when frames
    exist (their plan must stay: re-plan with a forced capture, which moves them aside)."""
    from brave6d.capture import open_rig

    if layout.frames():
        raise BoardCaptureExistsError(
            f"{layout.frames_path}: a board capture exists, so its plan stays as it is; capture again with "
            "'brave6d calibrate capture --force' (moves the old capture aside and plans anew)")
    with open_rig(spec, robot, camera, board=True) as rig:
        plan = plan_board_capture(spec, rig.robot, n_views, distance_m)
    plan.save(layout.plan_path)
    return plan


def capture_board(layout: CaptureLayout, spec: SceneSpec, robot: str, camera: str, n_views: int, *,
                  resume: bool = False, force: bool = False, distance_m: float | None = None) -> BoardCaptureResult:
    """Plan (unless a plan exists and ``force`` is not given) and capture the board views.

    A complete capture resumed opens no device. With ``force`` an existing capture, with its
    plan, is moved aside by the runner and the new plan is written next to the new frames.
    """
    from brave6d.capture import CaptureOptions, open_rig, run_capture

    done = check_capture_state(layout, resume, force)
    plan = BoardPlan.load(layout.plan_path) if layout.plan_path.exists() and not force else None
    if plan is not None and done >= len(plan.views):
        return BoardCaptureResult(plan, 0, done, 0.0)
    options = CaptureOptions(settle_time_s=spec.capture.settle_time_s, save_depth=False, resume=resume, force=force)
    moves_aside = force and done > 0
    with open_rig(spec, robot, camera, board=True) as rig:
        if plan is None:
            plan = plan_board_capture(spec, rig.robot, n_views, distance_m)
            if not moves_aside:
                plan.save(layout.plan_path)
        try:
            summary = run_capture(layout, plan.views, rig.robot, rig.camera, options, desc="board capture")
        finally:
            if moves_aside and layout.root.exists():
                plan.save(layout.plan_path)
    return BoardCaptureResult(plan, summary.written, summary.total, summary.robot_seconds)

"""View planning: viewpoints on spherical caps around the target, checked and ordered for the arm.

1. Sampling: at each distance in ``spec.capture.distances_m``, ``views_per_distance`` viewpoints on
   the spherical cap between ``min_elevation_deg`` and ``max_elevation_deg`` (elevation above the
   horizontal plane through the target) and within ``azimuth_range_deg`` (about world +z from
   world +x). A golden-ratio (Fibonacci) spiral stratified in ``sin(elevation)``: equal area per
   view (Archimedes: cap area is linear in the height), NOT uniform in the elevation angle.
   Rings are rotated against each other by a golden-ratio fraction of the azimuth span.
2. Camera pose: the optical axis (+z, OpenCV) passes through the target; roll convention: the
   image "up" (-y) is the projection of world +z (``brave6d.core.transforms.look_at`` with up = +z;
   straight-down views use look_at's documented fallback). ``base_T_tcp = base_T_cam @ cam_T_tcp``.
3. Checks per view, first failure recorded as the reason: camera inside the workspace bounds,
   camera body / flange / last link free of the collision boxes, IK within the joint limits, arm
   link capsules free, and reachable in the plan's single arm configuration (shoulder, elbow,
   wrist signs fixed for the whole plan: no flips).
4. Joint values: each joint's representative (mod 2 pi) is fixed once for all views (cut at the
   largest gap of its angles, shifted next to the start joints), so no move winds a joint by a turn.
5. Order: greedy nearest neighbour from the start joints in joint space (cost = the SimRobot
   moveJ time of the leading joint), improved by 2-opt and Or-opt (open path, fixed start).
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.atomic import atomic_write_bytes, atomic_write_json, read_json
from brave6d.core.errors import DataError
from brave6d.core.spec import CaptureSpec, SceneSpec, WorkspaceSpec
from brave6d.core.transforms import check_rigid, invert, look_at
from brave6d.capture.collision import BoxSet, ToolModel, arm_collisions, tool_collisions
from brave6d.capture.kinematics import TWO_PI, URKinematics, nearest_representative, wrap_to_pi
from brave6d.capture.sim_robot import joint_move_time, trapezoid_time

PLAN_VERSION = 1
GOLDEN = (1.0 + math.sqrt(5.0)) / 2.0
Branch = tuple[int, int, int]


# ----------------------------------------------------------------------------- sampling
def fibonacci_cap(
    n: int,
    min_elevation: float,
    max_elevation: float,
    azimuth_range: tuple[float, float] = (-math.pi, math.pi),
    offset: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(azimuth, elevation)`` (radians) of ``n`` points uniform by area on a spherical band.

    Point i sits at ``sin(elevation) = lo + (i + 0.5) / n * (hi - lo)`` (equal-area strata) and at
    azimuth fraction ``frac(i / phi + offset)`` of the range (golden-ratio spiral).
    """
    if n < 1:
        raise ValueError("need at least one view")
    z_lo, z_hi = math.sin(min_elevation), math.sin(max_elevation)
    i = np.arange(n, dtype=np.float64)
    z = z_lo + (i + 0.5) / n * (z_hi - z_lo)
    elevation = np.arcsin(np.clip(z, -1.0, 1.0))
    lo, hi = azimuth_range
    frac = np.mod(i / GOLDEN + offset, 1.0)
    azimuth = lo + frac * (hi - lo)
    return azimuth, elevation


def camera_pose(target: ArrayLike, azimuth: float, elevation: float, distance: float) -> NDArray[np.float64]:
    """``base_T_cam`` at (azimuth, elevation, distance) from ``target``, looking at it (image up =
    world +z projected)."""
    t = np.asarray(target, dtype=np.float64).reshape(3)
    ce = math.cos(elevation)
    eye = t + distance * np.array([ce * math.cos(azimuth), ce * math.sin(azimuth), math.sin(elevation)])
    return look_at(eye, t, up=(0.0, 0.0, 1.0))


@dataclass(frozen=True)
class Viewpoint:
    """A sampled viewpoint (before checks). Angles in radians."""

    view_id: int
    distance_level: int
    distance_m: float
    azimuth: float
    elevation: float
    base_T_cam: NDArray[np.float64]


def sample_viewpoints(capture: CaptureSpec, stagger_rings: bool = True) -> list[Viewpoint]:
    """All viewpoints of the capture spec; ``view_id = level * views_per_distance + i``."""
    n = capture.views_per_distance
    az_range = (math.radians(capture.azimuth_range_deg[0]), math.radians(capture.azimuth_range_deg[1]))
    out: list[Viewpoint] = []
    for level, dist in enumerate(capture.distances_m):
        offset = math.fmod(level / GOLDEN**2, 1.0) if stagger_rings else 0.0
        az, el = fibonacci_cap(n, math.radians(capture.min_elevation_deg), math.radians(capture.max_elevation_deg),
                               az_range, offset)
        for i in range(n):
            out.append(Viewpoint(level * n + i, level, float(dist), float(az[i]), float(el[i]),
                                 camera_pose(capture.target, float(az[i]), float(el[i]), float(dist))))
    return out


# ----------------------------------------------------------------------------- plan data
@dataclass(frozen=True)
class PlannedView:
    """A view in capture order. Angles in radians; poses 4x4 in the robot base frame.

    ``joints`` are the planned joint angles (the plan's arm configuration and joint turns): drive
    the arm with ``robot.move_joints(view.joints)`` to get exactly the planned motion and time.
    """

    view_id: int
    distance_level: int
    distance_m: float
    azimuth: float
    elevation: float
    base_T_cam: NDArray[np.float64]
    base_T_tcp: NDArray[np.float64]
    joints: NDArray[np.float64]


@dataclass(frozen=True)
class DroppedView:
    """A viewpoint left out of the plan, with the reason."""

    view_id: int
    distance_level: int
    distance_m: float
    azimuth: float
    elevation: float
    base_T_cam: NDArray[np.float64]
    reason: str


@dataclass
class Plan:
    """Ordered views, dropped views with reasons, and the plan's timing estimates (seconds)."""

    views: list[PlannedView]
    dropped: list[DroppedView]
    target: tuple[float, float, float]
    tcp_T_cam: NDArray[np.float64]
    robot_model: str
    configuration: Branch
    start_joints: NDArray[np.float64]
    joint_speed: float
    joint_acceleration: float
    settle_time_s: float
    travel_time_s: float
    naive_travel_time_s: float
    max_joint_step_rad: float
    planning_time_s: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def estimated_time_s(self) -> float:
        """Motion time plus the settle time at every view."""
        return self.travel_time_s + self.settle_time_s * len(self.views)

    def views_per_ring(self) -> dict[int, int]:
        """Number of planned views per distance level."""
        counts: dict[int, int] = {}
        for v in self.views:
            counts[v.distance_level] = counts.get(v.distance_level, 0) + 1
        return dict(sorted(counts.items()))

    def joint_path(self) -> NDArray[np.float64]:
        """(N + 1, 6): the start joints followed by each view's joints, in order."""
        return np.vstack([self.start_joints[None], *[v.joints[None] for v in self.views]])

    # ------------------------------------------------------------------ JSON
    def to_dict(self) -> dict[str, Any]:
        return {
            "version": PLAN_VERSION,
            "robot_model": self.robot_model,
            "target": list(self.target),
            "tcp_T_cam": self.tcp_T_cam.tolist(),
            "configuration": list(self.configuration),
            "start_joints": self.start_joints.tolist(),
            "joint_speed": self.joint_speed,
            "joint_acceleration": self.joint_acceleration,
            "settle_time_s": self.settle_time_s,
            "travel_time_s": self.travel_time_s,
            "naive_travel_time_s": self.naive_travel_time_s,
            "estimated_time_s": self.estimated_time_s,
            "max_joint_step_rad": self.max_joint_step_rad,
            "planning_time_s": self.planning_time_s,
            "views_per_ring": {str(k): v for k, v in self.views_per_ring().items()},
            "meta": self.meta,
            "views": [
                {"view_id": v.view_id, "distance_level": v.distance_level, "distance_m": v.distance_m,
                 "azimuth": v.azimuth, "elevation": v.elevation, "base_T_cam": v.base_T_cam.tolist(),
                 "base_T_tcp": v.base_T_tcp.tolist(), "joints": v.joints.tolist()}
                for v in self.views
            ],
            "dropped": [
                {"view_id": d.view_id, "distance_level": d.distance_level, "distance_m": d.distance_m,
                 "azimuth": d.azimuth, "elevation": d.elevation, "base_T_cam": d.base_T_cam.tolist(),
                 "reason": d.reason}
                for d in self.dropped
            ],
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "plan") -> Plan:
        try:
            if data.get("version") != PLAN_VERSION:
                raise DataError(f"{source}: unsupported plan version {data.get('version')!r}")
            views = [
                PlannedView(int(v["view_id"]), int(v["distance_level"]), float(v["distance_m"]),
                            float(v["azimuth"]), float(v["elevation"]),
                            check_rigid(v["base_T_cam"], f"{source}: views[{i}].base_T_cam"),
                            check_rigid(v["base_T_tcp"], f"{source}: views[{i}].base_T_tcp"),
                            _joints(v["joints"], f"{source}: views[{i}].joints"))
                for i, v in enumerate(data["views"])
            ]
            dropped = [
                DroppedView(int(d["view_id"]), int(d["distance_level"]), float(d["distance_m"]),
                            float(d["azimuth"]), float(d["elevation"]),
                            check_rigid(d["base_T_cam"], f"{source}: dropped[{i}].base_T_cam"), str(d["reason"]))
                for i, d in enumerate(data["dropped"])
            ]
            cfg = tuple(int(c) for c in data["configuration"])
            return cls(
                views=views, dropped=dropped, target=tuple(float(x) for x in data["target"]),  # type: ignore[arg-type]
                tcp_T_cam=check_rigid(data["tcp_T_cam"], f"{source}: tcp_T_cam"),
                robot_model=str(data["robot_model"]), configuration=cfg,  # type: ignore[arg-type]
                start_joints=_joints(data["start_joints"], f"{source}: start_joints"),
                joint_speed=float(data["joint_speed"]), joint_acceleration=float(data["joint_acceleration"]),
                settle_time_s=float(data["settle_time_s"]), travel_time_s=float(data["travel_time_s"]),
                naive_travel_time_s=float(data["naive_travel_time_s"]),
                max_joint_step_rad=float(data["max_joint_step_rad"]),
                planning_time_s=float(data.get("planning_time_s", 0.0)), meta=dict(data.get("meta", {})),
            )
        except DataError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{source}: malformed plan ({type(exc).__name__}: {exc})") from None


def _joints(values: Any, name: str) -> NDArray[np.float64]:
    q = np.asarray(values, dtype=np.float64).reshape(-1)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise DataError(f"{name}: expected 6 finite joint angles")
    return q


def save_plan(plan: Plan, path: Path | str) -> Path:
    """Write ``plan.json`` atomically."""
    return atomic_write_json(path, plan.to_dict())


def load_plan(path: Path | str) -> Plan:
    """Read a ``plan.json``; a missing or malformed file raises DataError naming it."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise DataError(f"{path}: a plan must be a JSON object")
    return Plan.from_dict(data, str(path))


# ----------------------------------------------------------------------------- options
@dataclass(frozen=True)
class PlannerOptions:
    """How to plan. ``configuration``: ``"auto"`` (the (shoulder, elbow, wrist) signs that keep
    the most views; ties go to the start joints' configuration), ``"start"`` (that of the start
    joints) or explicit signs. ``order``: ``"global"`` (all rings in one tour), ``"rings"`` (ring by
    ring, nearest first) or ``"none"`` (sampling order). ``start_joints`` default: robot home."""

    tool: ToolModel = ToolModel()
    check_workspace: bool = True
    check_arm_links: bool = True
    configuration: Literal["auto", "start"] | Branch = "auto"
    order: Literal["global", "rings", "none"] = "global"
    two_opt: bool = True
    max_two_opt_passes: int = 100
    stagger_rings: bool = True
    start_joints: tuple[float, ...] | None = None
    joint_limits: tuple[tuple[float, float], ...] | None = None


def resolve_tcp_T_cam(spec: SceneSpec, tcp_T_cam: ArrayLike | None = None) -> NDArray[np.float64]:
    """The camera mounting to plan with: the given one (e.g. calibrated), else the spec's
    ``robot.tcp_T_camera_guess``, else ``simulation.true_tcp_T_camera``."""
    if tcp_T_cam is not None:
        return check_rigid(tcp_T_cam, "tcp_T_cam")
    if spec.robot.tcp_T_camera_guess is not None:
        return spec.robot.tcp_T_camera_guess.matrix()
    if spec.simulation is not None:
        return spec.simulation.true_tcp_T_camera.matrix()
    raise DataError("no camera mounting to plan with: pass tcp_T_cam or set robot.tcp_T_camera_guess in the spec")


# ----------------------------------------------------------------------------- checks
def _workspace_violation(p: NDArray[np.float64], ws: WorkspaceSpec) -> str:
    for k, axis in enumerate("xyz"):
        if p[k] < ws.min[k]:
            return f"camera {axis} = {p[k]:.3f} m below the workspace minimum {ws.min[k]:.3f} m"
        if p[k] > ws.max[k]:
            return f"camera {axis} = {p[k]:.3f} m above the workspace maximum {ws.max[k]:.3f} m"
    return ""


@dataclass
class _Candidate:
    vp: Viewpoint
    base_T_tcp: NDArray[np.float64]
    solutions: dict[Branch, NDArray[np.float64]]  # collision-free IK solution per configuration
    reason: str  # why no configuration works ("" when some does)


def _check_view(
    vp: Viewpoint, cam_T_tcp: NDArray[np.float64], kin: URKinematics, boxes: BoxSet,
    workspace: WorkspaceSpec | None, opts: PlannerOptions,
) -> _Candidate:
    base_T_tcp = vp.base_T_cam @ cam_T_tcp
    cand = _Candidate(vp, base_T_tcp, {}, "")
    if workspace is not None:
        why = _workspace_violation(vp.base_T_cam[:3, 3], workspace)
        if why:
            cand.reason = f"outside the workspace: {why}"
            return cand
    base_T_flange = base_T_tcp @ kin.tcp_T_flange
    hits = tool_collisions(base_T_flange, vp.base_T_cam, boxes, opts.tool, wrist_length=kin.dh.d6)
    if hits:
        cand.reason = "collision: " + ", ".join(hits)
        return cand
    res = kin.ik(base_T_tcp)
    if not res.reachable:
        cand.reason = f"unreachable: {res.reason}"
        return cand
    link_hits: list[str] = []
    for q, br in zip(res.solutions, res.branches):
        branch = tuple(int(b) for b in br)
        if opts.check_arm_links:
            h = arm_collisions(kin.link_frames(q), boxes, opts.tool)
            if h:
                link_hits.append(f"{_branch_name(branch)}: " + ", ".join(h))  # type: ignore[arg-type]
                continue
        cand.solutions[branch] = q  # type: ignore[index]
    if not cand.solutions:
        cand.reason = "arm collision in every IK configuration (" + "; ".join(link_hits) + ")"
    return cand


def _branch_name(branch: Branch) -> str:
    s, e, w = branch
    return f"shoulder {'+' if s > 0 else '-'}, elbow {'+' if e > 0 else '-'}, wrist {'+' if w > 0 else '-'}"


# ----------------------------------------------------------------------------- ordering
def _cost_matrix(q: NDArray[np.float64], speed: float, accel: float) -> NDArray[np.float64]:
    """(N, N) moveJ times between joint vectors (the SimRobot model)."""
    diff = np.abs(q[:, None, :] - q[None, :, :])
    return np.asarray(trapezoid_time(diff.max(axis=2), speed, accel), dtype=np.float64)


def _nearest_neighbour(cost: NDArray[np.float64], start: int) -> list[int]:
    n = len(cost)
    visited = np.zeros(n, dtype=bool)
    visited[start] = True
    path = [start]
    for _ in range(n - 1):
        row = np.where(visited, np.inf, cost[path[-1]])
        nxt = int(np.argmin(row))
        visited[nxt] = True
        path.append(nxt)
    return path


def _two_opt(path: list[int], cost: NDArray[np.float64], max_passes: int) -> list[int]:
    """2-opt on an open path with a fixed first node (best move per position, until no gain)."""
    p = np.array(path)
    n = len(p)
    if n < 4:
        return list(p)
    for _ in range(max_passes):
        improved = False
        for i in range(1, n - 1):
            a, b = p[i - 1], p[i]
            js = np.arange(i + 1, n)
            c = p[js]
            nxt = np.where(js + 1 < n, p[np.minimum(js + 1, n - 1)], -1)
            has_next = nxt >= 0
            d_next_new = np.where(has_next, cost[b, np.maximum(nxt, 0)], 0.0)
            d_next_old = np.where(has_next, cost[c, np.maximum(nxt, 0)], 0.0)
            delta = cost[a, c] + d_next_new - cost[a, b] - d_next_old
            k = int(np.argmin(delta))
            if delta[k] < -1e-9:
                j = int(js[k])
                p[i:j + 1] = p[i:j + 1][::-1]
                improved = True
        if not improved:
            break
    return [int(x) for x in p]


def _or_opt(path: list[int], cost: NDArray[np.float64], max_len: int = 3) -> tuple[list[int], bool]:
    """One pass of Or-opt: move chains of 1..max_len nodes (either direction) to their best place."""
    p = list(path)
    improved = False
    for L in range(1, max_len + 1):
        i = 1
        while i + L <= len(p):
            seg = p[i:i + L]
            prev = p[i - 1]
            nxt = p[i + L] if i + L < len(p) else None
            gain = cost[prev, seg[0]] + (cost[seg[-1], nxt] - cost[prev, nxt] if nxt is not None else 0.0)
            rest = np.array(p[:i] + p[i + L:])
            u = rest
            v = np.append(rest[1:], -1)
            has_v = v >= 0
            vv = np.maximum(v, 0)
            base = np.where(has_v, cost[u, vv], 0.0)
            fwd = cost[u, seg[0]] + np.where(has_v, cost[seg[-1], vv], 0.0) - base
            rev = cost[u, seg[-1]] + np.where(has_v, cost[seg[0], vv], 0.0) - base
            best_f, best_r = int(np.argmin(fwd)), int(np.argmin(rev))
            use_rev = rev[best_r] < fwd[best_f]
            k = best_r if use_rev else best_f
            added = rev[k] if use_rev else fwd[k]
            if added - gain < -1e-9:
                chain = seg[::-1] if use_rev else seg
                rl = list(rest)
                p = rl[:k + 1] + chain + rl[k + 1:]
                improved = True
            else:
                i += 1
    return p, improved


def order_views(
    joints: NDArray[np.float64], start_joints: NDArray[np.float64], speed: float, accel: float,
    two_opt: bool = True, max_passes: int = 100,
) -> list[int]:
    """Visit order (indices into ``joints``) minimising the summed moveJ time from ``start_joints``:
    greedy nearest neighbour, then 2-opt and Or-opt (chains of 1-3 views) until neither improves."""
    if len(joints) == 0:
        return []
    q = np.vstack([start_joints[None], joints])
    cost = _cost_matrix(q, speed, accel)
    path = _nearest_neighbour(cost, 0)
    if two_opt:
        for _ in range(max_passes):
            path = _two_opt(path, cost, max_passes)
            path, moved = _or_opt(path, cost)
            if not moved:
                break
    return [i - 1 for i in path[1:]]


def choose_representatives(
    joints: NDArray[np.float64], start_joints: NDArray[np.float64], limits: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Fix, once for the whole plan, which representative (mod 2 pi) each view's joints take.

    Per joint, the angles of all views are cut at their largest circular gap, so that the values
    lie in one window shorter than 2 pi, and the window is shifted by whole turns to lie within
    ``limits`` as close to the start joints as possible. Moving between any two views then never
    winds a joint by a full turn, and the plain joint differences are the real moves. A joint
    whose window fits no shift falls back to the representative closest to the start, per view.
    """
    q = np.asarray(joints, dtype=np.float64).reshape(-1, 6)
    if len(q) == 0:
        return q.copy()
    out = np.empty_like(q)
    for j in range(6):
        a = wrap_to_pi(q[:, j])
        srt = np.sort(a)
        gaps = np.diff(np.concatenate([srt, srt[:1] + TWO_PI]))
        k = int(np.argmax(gaps))
        w0 = srt[(k + 1) % len(srt)]
        vals = w0 + np.mod(a - w0, TWO_PI)
        lo, hi = float(vals.min()), float(vals.max())
        lim_lo, lim_hi = limits[j]
        best: tuple[float, float, int] | None = None
        for m in range(-3, 4):
            if lo + TWO_PI * m < lim_lo - 1e-12 or hi + TWO_PI * m > lim_hi + 1e-12:
                continue
            s0 = float(start_joints[j])
            gap = max(0.0, lo + TWO_PI * m - s0, s0 - hi - TWO_PI * m)
            key = (gap, abs(0.5 * (lo + hi) + TWO_PI * m - s0), m)
            best = key if best is None or key < best else best
        if best is not None:
            out[:, j] = vals + TWO_PI * best[2]
        else:
            for i in range(len(q)):
                rep = nearest_representative(q[i], start_joints, limits)
                if rep is None:
                    raise ValueError(f"joints {q[i].tolist()} have no representative within the joint limits")
                out[i, j] = rep[j]
    return out


def path_travel_time(joint_path: NDArray[np.float64], speed: float, accel: float) -> float:
    """Summed moveJ time along consecutive rows of ``joint_path`` (the SimRobot motion model)."""
    return float(sum(joint_move_time(a, b, speed, accel) for a, b in zip(joint_path[:-1], joint_path[1:])))


# ----------------------------------------------------------------------------- the planner
def plan_views(
    spec: SceneSpec, tcp_T_cam: ArrayLike | None = None, options: PlannerOptions | None = None
) -> Plan:
    """Sample, check and order the capture views of ``spec`` (see the module docstring)."""
    t_start = time.perf_counter()
    opts = options or PlannerOptions()
    tcp_T = resolve_tcp_T_cam(spec, tcp_T_cam)
    cam_T_tcp = invert(tcp_T)
    kin = URKinematics(spec.robot.model, joint_limits=opts.joint_limits)
    boxes = BoxSet.from_specs(spec.collision_boxes)
    start = (np.deg2rad(np.asarray(spec.robot.home_joints_deg, dtype=np.float64)) if opts.start_joints is None
             else np.asarray(opts.start_joints, dtype=np.float64).reshape(6))
    start_branch: Branch = kin.branch_of(start)
    workspace = spec.workspace if opts.check_workspace else None

    cands = [_check_view(vp, cam_T_tcp, kin, boxes, workspace, opts)
             for vp in sample_viewpoints(spec.capture, opts.stagger_rings)]

    # one configuration for the whole plan
    if opts.configuration == "start":
        config = start_branch
    elif opts.configuration == "auto":
        counts: dict[Branch, int] = {}
        for c in cands:
            for br in c.solutions:
                counts[br] = counts.get(br, 0) + 1
        config = max(counts, key=lambda br: (counts[br], br == start_branch)) if counts else start_branch
    else:
        config = tuple(int(x) for x in opts.configuration)  # type: ignore[assignment]

    kept: list[_Candidate] = []
    dropped: list[DroppedView] = []
    for c in cands:
        reason = c.reason
        if not reason and config not in c.solutions:
            others = ", ".join(f"({_branch_name(b)})" for b in c.solutions)
            reason = (f"reachable only in another arm configuration {others}; the plan keeps "
                      f"({_branch_name(config)}) to avoid flips")
        if reason:
            vp = c.vp
            dropped.append(DroppedView(vp.view_id, vp.distance_level, vp.distance_m, vp.azimuth, vp.elevation,
                                       vp.base_T_cam, reason))
        else:
            kept.append(c)

    speed, accel = spec.robot.joint_speed, spec.robot.joint_acceleration
    joints = choose_representatives(np.array([c.solutions[config] for c in kept]).reshape(-1, 6), start,
                                    kin.joint_limits)
    order = _order(kept, joints, start, speed, accel, opts)
    seq = joints[order].reshape(-1, 6)
    path = np.vstack([start[None], seq])
    steps = np.abs(np.diff(path, axis=0)).max(axis=1) if len(seq) else np.zeros(0)
    naive_idx = sorted(range(len(kept)), key=lambda i: kept[i].vp.view_id)
    naive_seq = joints[naive_idx].reshape(-1, 6)
    views = [
        PlannedView(kept[i].vp.view_id, kept[i].vp.distance_level, kept[i].vp.distance_m, kept[i].vp.azimuth,
                    kept[i].vp.elevation, kept[i].vp.base_T_cam, kept[i].base_T_tcp, seq[k])
        for k, i in enumerate(order)
    ]
    plan = Plan(
        views=views, dropped=sorted(dropped, key=lambda d: d.view_id),
        target=tuple(float(x) for x in spec.capture.target),  # type: ignore[arg-type]
        tcp_T_cam=tcp_T, robot_model=spec.robot.model, configuration=config, start_joints=start,
        joint_speed=speed, joint_acceleration=accel, settle_time_s=spec.capture.settle_time_s,
        travel_time_s=path_travel_time(path, speed, accel),
        naive_travel_time_s=path_travel_time(np.vstack([start[None], naive_seq]), speed, accel),
        max_joint_step_rad=float(steps[1:].max()) if len(steps) > 1 else 0.0,
        meta={"order": opts.order, "two_opt": opts.two_opt, "sampled": len(cands),
              "first_move_max_joint_step_rad": float(steps[0]) if len(steps) else 0.0},
    )
    plan.planning_time_s = time.perf_counter() - t_start
    return plan


def _order(
    kept: Sequence[_Candidate], joints: NDArray[np.float64], start: NDArray[np.float64],
    speed: float, accel: float, opts: PlannerOptions,
) -> list[int]:
    if opts.order == "none":
        return sorted(range(len(kept)), key=lambda i: kept[i].vp.view_id)
    if opts.order == "global":
        return order_views(joints, start, speed, accel, opts.two_opt, opts.max_two_opt_passes)
    if opts.order != "rings":
        raise ValueError(f"unknown order {opts.order!r}: use 'global', 'rings' or 'none'")
    out: list[int] = []
    prev = start
    for level in sorted({c.vp.distance_level for c in kept}):
        idx = [i for i, c in enumerate(kept) if c.vp.distance_level == level]
        sub = order_views(joints[idx], prev, speed, accel, opts.two_opt, opts.max_two_opt_passes)
        out += [idx[k] for k in sub]
        prev = joints[out[-1]]
    return out


# ----------------------------------------------------------------------------- plot
def _box_edges(boxes: BoxSet) -> list[NDArray[np.float64]]:
    corners = boxes.corners()  # corner index = 4*sx + 2*sy + sz
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return [np.stack([c[a], c[b]]) for c in corners for a, b in pairs]


def plot_plan(
    plan: Plan, path: Path | str, boxes: BoxSet | None = None, workspace: WorkspaceSpec | None = None
) -> Path:
    """PNG: 3D view and top view of the planned views (coloured by ring, joined in capture
    order), the dropped ones (grey x), the target, the robot base and the collision boxes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 6))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    cmap = plt.get_cmap("tab10")
    pos = np.array([v.base_T_cam[:3, 3] for v in plan.views]).reshape(-1, 3)
    levels = np.array([v.distance_level for v in plan.views], dtype=int)
    if len(pos):
        ax3.plot(pos[:, 0], pos[:, 1], pos[:, 2], color="0.5", lw=0.6, label="capture order")
        ax2.plot(pos[:, 0], pos[:, 1], color="0.5", lw=0.6)
    dist_by_level = {v.distance_level: v.distance_m for v in plan.views}
    for lvl in sorted(set(levels.tolist())):
        m = levels == lvl
        lab = f"ring {lvl} ({dist_by_level[lvl]:.2f} m): {int(m.sum())}"
        ax3.scatter(pos[m, 0], pos[m, 1], pos[m, 2], s=10, color=cmap(lvl % 10), label=lab, depthshade=False)
        ax2.scatter(pos[m, 0], pos[m, 1], s=10, color=cmap(lvl % 10))
    if plan.dropped:
        dp = np.array([d.base_T_cam[:3, 3] for d in plan.dropped])
        ax3.scatter(dp[:, 0], dp[:, 1], dp[:, 2], marker="x", s=14, color="0.3",
                    label=f"dropped: {len(plan.dropped)}", depthshade=False)
        ax2.scatter(dp[:, 0], dp[:, 1], marker="x", s=14, color="0.3")
    if len(pos):
        ax3.scatter(*pos[0], marker="o", s=60, facecolors="none", edgecolors="k", label="first view")
        ax2.scatter(pos[0, 0], pos[0, 1], marker="o", s=60, facecolors="none", edgecolors="k")
    tgt = np.asarray(plan.target)
    for ax in (ax3, ax2):
        kw: dict[str, Any] = {"marker": "*", "s": 120, "color": "red"}
        if ax is ax3:
            ax.scatter(*tgt, label="target", **kw)
            ax.scatter(0, 0, 0, marker="^", s=80, color="k", label="robot base")
        else:
            ax.scatter(tgt[0], tgt[1], **kw)
            ax.scatter(0, 0, marker="^", s=80, color="k")
    if boxes is not None and len(boxes):
        for e in _box_edges(boxes):
            ax3.plot(e[:, 0], e[:, 1], e[:, 2], color="tab:brown", lw=0.8)
            ax2.plot(e[:, 0], e[:, 1], color="tab:brown", lw=0.8)
    if workspace is not None:
        lo, hi = workspace.min, workspace.max
        ax2.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]], "k--", lw=0.6)
    spans = [np.ptp(lim) for lim in (ax3.get_xlim3d(), ax3.get_ylim3d(), ax3.get_zlim3d())]
    ax3.set_box_aspect(tuple(max(float(sp), 0.05) for sp in spans))  # metres look like metres
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("y [m]")
    ax3.set_zlabel("z [m]")
    ax3.legend(loc="upper left", fontsize=7)
    ax3.set_title(f"{len(plan.views)} views, travel {plan.travel_time_s:.0f} s "
                  f"(naive {plan.naive_travel_time_s:.0f} s)")
    ax2.set_aspect("equal")
    ax2.set_xlabel("x [m]")
    ax2.set_ylabel("y [m]")
    ax2.set_title("top view")
    ax2.grid(True, lw=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())

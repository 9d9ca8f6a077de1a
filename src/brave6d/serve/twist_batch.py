"""Many twists integrated at once: :func:`brave6d.serve.geometry.integrate_twist` for N cameras in array code.

Why: N agents stepping together (the vector env) would otherwise integrate their moves one
Python loop at a time. Every substep pose of every move is computed in one pass, the collision and
workspace checks screen them all in arrays, and only the few substeps the screen cannot clear (a
refusal, or a swept segment near a box) go through the scalar checks of
:class:`brave6d.serve.geometry.CollisionWorld`, which decide and word the refusal.

Each :class:`MoveResult` equals ``integrate_twist``'s for the same arguments bit for bit: the poses
are computed by the same operations per row (stacked ``matmul`` runs the same BLAS call per matrix
as a single one; a norm is ``sqrt(dot)`` as ``numpy.linalg.norm``'s; the screw coefficients use
Python's float power, as the scalar code does), and every decision near a boundary is the scalar one.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.serve.geometry import (
    MAX_STEP_M,
    MAX_STEP_RAD,
    MAX_SUBSTEPS,
    CollisionWorld,
    MoveResult,
    integrate_twist,
)

#: Relative margin of the array screens: a distance within it of the camera radius is decided by the scalar check.
SCREEN_MARGIN = 1e-9


def _norms(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row norms of ``x`` (M, 3), each ``numpy.linalg.norm`` of the row bit for bit (``sqrt(dot)``)."""
    return np.sqrt(np.vecdot(x, x))


def _hats(w: NDArray[np.float64]) -> NDArray[np.float64]:
    W = np.zeros((len(w), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    return W


def se3_exps(v: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, 4, 4) ``geometry.se3_exp`` of each row of ``v``, ``w`` (M, 3)."""
    theta = _norms(w)
    R = Rotation.from_rotvec(w).as_matrix()
    W = _hats(w)
    thetas, cos, sin = theta.tolist(), np.cos(theta).tolist(), np.sin(theta).tolist()
    # Python's float power, as the scalar code's (numpy's differs in the last bit)
    a = np.array([0.5 - t**2 / 24.0 if t < 1e-6 else (1.0 - c) / t**2 for t, c in zip(thetas, cos)],
                 dtype=np.float64)
    b = np.array([1.0 / 6.0 - t**2 / 120.0 if t < 1e-6 else (t - s) / t**3 for t, s in zip(thetas, sin)],
                 dtype=np.float64)
    V = np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)
    T = np.zeros((len(w), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = (V @ v[:, :, None])[:, :, 0]
    T[:, 3, 3] = 1.0
    return T


def poses_after(starts: NDArray[np.float64], linear: NDArray[np.float64], angular: NDArray[np.float64],
                t: NDArray[np.float64], camera_frame: NDArray[np.bool_]) -> NDArray[np.float64]:
    """(M, 4, 4) ``geometry.pose_after`` of each row (``camera_frame``: the row's frame is ``"camera"``, else ``"world"``)."""
    v = linear * t[:, None]
    w = angular * t[:, None]
    out = np.empty_like(starts)
    cam = np.flatnonzero(camera_frame)
    if len(cam):
        out[cam] = np.ascontiguousarray(starts[cam]) @ se3_exps(v[cam], w[cam])
    world = np.flatnonzero(~camera_frame)
    if len(world):
        out[world] = 0.0
        out[world, :3, :3] = Rotation.from_rotvec(w[world]).as_matrix() @ np.ascontiguousarray(starts[world, :3, :3])
        out[world, :3, 3] = starts[world, :3, 3] + v[world]
        out[world, 3, 3] = 1.0
    return out


def _box_distances(world: CollisionWorld, points: NDArray[np.float64]) -> NDArray[np.float64]:
    """(B, M) distance of each point to each box (``OrientedBox.distance`` per row)."""
    out = np.empty((len(world.boxes), len(points)))
    for j, box in enumerate(world.boxes):
        T = box._box_T_world  # type: ignore[attr-defined]
        R = np.ascontiguousarray(np.broadcast_to(T[:3, :3], (len(points), 3, 3)))
        q = (R @ points[:, :, None])[:, :, 0] + T[:3, 3]
        outside = np.maximum(np.abs(q) - 0.5 * np.asarray(box.size), 0.0)
        out[j] = _norms(outside)
    return out


def integrate_twists(world: CollisionWorld, starts: ArrayLike, linear: ArrayLike, angular: ArrayLike,
                     durations: ArrayLike, frames: Sequence[str] | str = "camera",
                     max_step_m: float = MAX_STEP_M, max_step_rad: float = MAX_STEP_RAD) -> list[MoveResult]:
    """``integrate_twist`` of each camera: ``starts`` (N, 4, 4), ``linear`` and ``angular`` (N, 3),
    ``durations`` (N,), ``frames`` one per camera or one for all. A move ``integrate_twist`` refuses
    with ``ValueError`` raises the same error here (the first such move's). No trajectories are kept."""
    T0 = np.asarray(starts, dtype=np.float64).reshape(-1, 4, 4)
    n_cams = len(T0)
    lin = np.asarray(linear, dtype=np.float64).reshape(n_cams, 3)
    ang = np.asarray(angular, dtype=np.float64).reshape(n_cams, 3)
    dur = np.asarray(durations, dtype=np.float64).reshape(n_cams)
    frame_list = [frames] * n_cams if isinstance(frames, str) else list(frames)
    if n_cams == 0:
        return []
    with np.errstate(over="ignore", invalid="ignore"):
        need = np.maximum(_norms(lin) * dur / max_step_m, _norms(ang) * dur / max_step_rad)
        ok = np.isfinite(dur) & (dur >= 0) & np.isfinite(need) & (np.ceil(need) <= MAX_SUBSTEPS)
    ok &= np.array([f in ("camera", "world") for f in frame_list])
    for i in np.flatnonzero(~ok):  # the scalar code words the error
        integrate_twist(world, T0[i], lin[i], ang[i], float(dur[i]), frame_list[i], max_step_m, max_step_rad)
        raise ValueError(f"move {i}: not a finite move of at most {MAX_SUBSTEPS} substeps")
    counts = np.maximum(1, np.ceil(need)).astype(np.int64)
    owner = np.repeat(np.arange(n_cams), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    k = np.arange(len(owner)) - first[owner] + 1
    t = dur[owner] * k / counts[owner]
    camera_frame = np.array([f == "camera" for f in frame_list])[owner]
    poses = poses_after(T0[owner], lin[owner], ang[owner], t, camera_frame)
    centres = poses[:, :3, 3]
    previous = np.where((k == 1)[:, None], T0[owner, :3, 3], np.roll(centres, 1, axis=0))
    steps = _norms(centres - previous)
    flagged = _screen(world, centres, previous, steps)
    results: list[MoveResult] = []
    flagged_rows = np.flatnonzero(flagged)
    flagged_from = np.searchsorted(flagged_rows, first).tolist()  # each camera's first flagged substep
    flagged_rows = flagged_rows.tolist()
    step_lengths = steps.tolist()
    for i, (lo, n) in enumerate(zip(first.tolist(), counts.tolist())):
        stop, refusal = n, None
        f = flagged_from[i]
        while f < len(flagged_rows) and flagged_rows[f] < lo + n:  # in substep order: the first real refusal stops
            at = flagged_rows[f]
            refusal = world.check(poses[at])
            if refusal is None:
                refusal = world.check_segment(previous[at], centres[at])
            if refusal is not None:
                stop = at - lo
                break
            f += 1
        path = 0.0
        for length in step_lengths[lo:lo + stop]:  # sequential, as the scalar loop adds them
            path += length
        if refusal is not None:
            last = T0[i] if stop == 0 else poses[lo + stop - 1]
            results.append(MoveResult(last.copy(), refusal, stop / n, stop, path))
        else:
            results.append(MoveResult(poses[lo + n - 1].copy(), None, 1.0 if dur[i] > 0 else 0.0, n, path))
    return results


def _screen(world: CollisionWorld, centres: NDArray[np.float64], previous: NDArray[np.float64],
            steps: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(M,) True where a substep may be refused (outside the workspace, near a box, or a swept
    segment the cheap bound of ``check_segment`` does not clear): the scalar checks decide those."""
    lo, hi = np.asarray(world.workspace.min), np.asarray(world.workspace.max)
    flagged = np.any((centres < lo) | (centres > hi), axis=1)
    if world.boxes:
        r = world.camera_radius * (1.0 + SCREEN_MARGIN) + SCREEN_MARGIN
        d1 = _box_distances(world, centres)
        d0 = _box_distances(world, previous)
        flagged |= np.any(d1 <= r, axis=0)
        flagged |= np.any(0.5 * (d0 + d1 - steps) <= r, axis=0)
    return flagged


"""An agent that searches everything a server sent it for the target's true pose.

:func:`truth_found` walks any reply (JSON text and objects, pydantic models, dataclasses, NumPy
arrays, rospy and rclpy messages, ``.npz`` contents) and reads every pose it could hold: a 4x4
matrix (nested or 16 numbers), a rotation (3x3 or 9 numbers) beside a translation, a position
beside a quaternion (ROS's x, y, z, w and the API's w, x, y, z), a tf transform. A pose within 1 mm
and 1 degree of one of the truths (the target's world_T_obj, its cam_T_obj in every view of the
episode) is a find. Images (byte strings, arrays of more than 16 numbers) are not read."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

MM = 1e-3
DEG = 1.0


def _number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def _array(v: Any, size: int) -> np.ndarray | None:
    """``v`` as a float array of ``size`` numbers (nested or flat), else None."""
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return a.reshape(-1) if a.size == size and np.all(np.isfinite(a)) else None


def _vector(v: Any, keys: str) -> np.ndarray | None:
    """A dict with exactly the keys ``keys`` (``"xyz"``, ``"xyzw"``) as a vector, or a list of that length."""
    if isinstance(v, dict) and set(v) == set(keys) and all(_number(v[k]) for k in keys):
        return np.array([float(v[k]) for k in keys])
    return _array(v, len(keys)) if isinstance(v, (list, tuple, np.ndarray)) else None


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _from_quaternion(p: np.ndarray, q: np.ndarray) -> Iterator[np.ndarray]:
    if abs(np.linalg.norm(q) - 1.0) < 1e-3:
        yield _pose(Rotation.from_quat(q).as_matrix(), p)  # x, y, z, w
        yield _pose(Rotation.from_quat(np.roll(q, -1)).as_matrix(), p)  # w, x, y, z


def _plain(value: Any) -> Any:
    """A message, model or dataclass as a dict; anything else as it is."""
    if hasattr(value, "model_dump"):
        return value.model_dump()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if hasattr(value, "get_fields_and_field_types"):  # rclpy message
        return {k: getattr(value, k) for k in value.get_fields_and_field_types()}
    if hasattr(value, "__slots__") and hasattr(value, "_type"):  # rospy message
        return {k: getattr(value, k) for k in value.__slots__}
    return value


def candidate_poses(value: Any, depth: int = 0) -> Iterator[np.ndarray]:
    """Every 4x4 pose ``value`` could hold (see the module docstring)."""
    if depth > 40 or isinstance(value, (bytes, bytearray, memoryview)):
        return
    if isinstance(value, str):
        text = value.strip()
        if text[:1] in "[{":
            try:
                yield from candidate_poses(json.loads(text), depth + 1)
            except ValueError:
                pass
        return
    value = _plain(value)
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "fiu" and value.size <= 16 * 64:  # poses, stacks of poses; not images
            if value.size % 16 == 0:
                yield from (m for m in value.reshape(-1, 4, 4))
            flat = value.reshape(-1)
            if flat.size in (9, 12, 16):
                yield from candidate_poses(flat.tolist(), depth + 1)
        return
    if isinstance(value, dict):
        pairs = [(value.get(r), value.get(t)) for r in ("R", "rotation", "cam_R_m2c")
                 for t in ("t", "t_m", "translation", "cam_t_m2c", "position")]
        for r, t in pairs:
            R, tv = _array(r, 9), _vector(t, "xyz")
            if R is not None and tv is not None:
                yield _pose(R.reshape(3, 3), tv)
                yield _pose(R.reshape(3, 3), tv / 1000.0)  # BOP's millimetres
        for pk, qk in (("position", "orientation"), ("translation", "rotation"), ("position", "quaternion_wxyz"),
                       ("position", "quaternion")):
            p, q = _vector(value.get(pk), "xyz"), _vector(value.get(qk), "xyzw")
            if p is not None and q is not None:
                yield from _from_quaternion(p, q)
        for v in value.values():
            yield from candidate_poses(v, depth + 1)
        return
    if isinstance(value, (list, tuple)):
        flat = _array(value, 16)
        if flat is not None:
            yield flat.reshape(4, 4)
        for v in value:
            if not _number(v):
                yield from candidate_poses(v, depth + 1)


def _near(a: np.ndarray, b: np.ndarray, mm: float, deg: float) -> bool:
    if np.linalg.norm(a[:3, 3] - b[:3, 3]) > mm * MM:
        return False
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))) <= deg


def truth_found(replies: Sequence[Any], truths: Sequence[np.ndarray], mm: float = 1.0, deg: float = DEG) -> list[str]:
    """``"reply k"`` for every reply holding a pose within ``mm`` / ``deg`` of one of ``truths``."""
    found = []
    for k, reply in enumerate(replies):
        if any(_near(np.asarray(c, dtype=np.float64), T, mm, deg) for c in candidate_poses(reply) for T in truths):
            found.append(f"reply {k}")
    return found


def target_truths(world_T_obj: np.ndarray, cameras: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The target's true poses an agent could be given: in the world, and in every camera of the episode."""
    return [np.asarray(world_T_obj, dtype=np.float64)] + [np.linalg.inv(T) @ world_T_obj for T in cameras]

"""Open3D for the baseline agent: the import, point clouds, and one thread while it computes."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError


def open3d() -> Any:
    """The ``open3d`` module (a dependency; a clear error if it is missing)."""
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - open3d is a dependency
        raise BraveError(f"the baseline agent needs Open3D ({exc})") from None
    return o3d


_ONE_THREAD_LOCK = threading.Lock()
_one_thread_holders = 0
_threads_before: int | None = None


@contextmanager
def one_thread() -> Iterator[None]:
    """Open3D on one thread for the duration: its seeded RANSAC and its parallel sums (ICP,
    plane fits) are reproducible only then; the agent's clouds are small, so it costs little.
    Open3D's thread count is one setting for the whole process, so overlapping sections (threads of
    one server, nested calls) share it: the first to enter sets one thread, the last to leave
    restores the count from before, under a lock (one section's exit never undoes another's)."""
    global _one_thread_holders, _threads_before
    o3d = open3d()
    with _ONE_THREAD_LOCK:
        if _one_thread_holders == 0:
            _threads_before = o3d.utility.get_max_threads()
            o3d.utility.set_max_threads(1)
        _one_thread_holders += 1
    try:
        yield
    finally:
        with _ONE_THREAD_LOCK:
            _one_thread_holders -= 1
            if _one_thread_holders == 0 and _threads_before is not None:
                o3d.utility.set_max_threads(_threads_before)
                _threads_before = None


def point_cloud(points: NDArray[np.floating], normals: NDArray[np.floating] | None = None) -> Any:
    """An Open3D point cloud of ``points`` (N, 3), with ``normals`` if given."""
    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals, dtype=np.float64))
    return pcd

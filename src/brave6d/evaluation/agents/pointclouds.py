"""Open3D for the baseline agent: the import, point clouds, and one thread while it computes."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.core.process_setting import HeldSetting


def open3d() -> Any:
    """The ``open3d`` module (a dependency; a clear error if it is missing)."""
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - open3d is a dependency
        raise BraveError(f"the baseline agent needs Open3D ({exc})") from None
    return o3d


_OPEN3D_THREADS: HeldSetting | None = None  # made at first use: Open3D is imported lazily
_OPEN3D_THREADS_MADE = threading.Lock()


@contextmanager
def one_thread() -> Iterator[None]:
    """Open3D on one thread for the duration: its seeded RANSAC and its parallel sums (ICP,
    plane fits) are reproducible only then; the agent's clouds are small, so it costs little.
    Open3D's thread count is one setting for the whole process, so overlapping sections (threads of
    one server, nested calls) share it (:class:`~brave6d.core.process_setting.HeldSetting`): the
    first to enter sets one thread, the last to leave restores the count from before."""
    global _OPEN3D_THREADS
    with _OPEN3D_THREADS_MADE:
        if _OPEN3D_THREADS is None:
            o3d = open3d()
            _OPEN3D_THREADS = HeldSetting(o3d.utility.get_max_threads, o3d.utility.set_max_threads, 1)
    with _OPEN3D_THREADS.held():
        yield


def point_cloud(points: NDArray[np.floating], normals: NDArray[np.floating] | None = None) -> Any:
    """An Open3D point cloud of ``points`` (N, 3), with ``normals`` if given."""
    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals, dtype=np.float64))
    return pcd

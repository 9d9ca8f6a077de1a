"""The two files an import adds to a scene directory (their one reader and writer).

- ``capture/import.json`` (``brave6d-import/1``): where the capture came from and what was done to
  it: the source's format, frames imported and missing, the camera and how the images were
  written, the world change (scale, up, centre; :class:`~.world.WorldChange`) and how each was
  chosen, the pose check's result, and ``rotations``: the largest correction the projection of the
  source's rotations onto the nearest rotation made, and its frame.
- ``capture/imported_points.ply``: the source's sparse points in the scene's world (metres),
  binary little-endian PLY with ``x y z`` (float32) and ``red green blue`` (uint8): the pose
  check's reference at the start of every training of the scene.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import atomic_write_bytes, atomic_write_json, read_json
from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir
from brave6d.core.ply_check import check_ply_header

IMPORT_FORMAT = "brave6d-import/1"


def write_import_record(scene: SceneDir, record: dict[str, Any]) -> None:
    """Write ``capture/import.json`` (atomically)."""
    atomic_write_json(scene.import_record_path, {"format": IMPORT_FORMAT, **record})


def read_import_record(scene: SceneDir) -> dict[str, Any] | None:
    """``capture/import.json``, or None for a scene the project captured itself."""
    path = scene.import_record_path
    if not path.is_file():
        return None
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != IMPORT_FORMAT:
        raise DataError(f"{path}: not an import record (expected format {IMPORT_FORMAT!r})")
    return data


def write_imported_points(scene: SceneDir, xyz: NDArray[np.float64], rgb: NDArray[np.uint8]) -> None:
    """Write ``capture/imported_points.ply`` (atomically)."""
    from plyfile import PlyData, PlyElement

    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    rgb = np.asarray(rgb, np.uint8).reshape(-1, 3)
    # float64: the points keep the world change's precision, so the same capture imported at two scales
    # gives the same points in the training frame (brave6d.training.scene_frame); a float32 file reads too
    vertex = np.empty(len(xyz), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, c in enumerate("xyz"):
        vertex[c] = xyz[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        vertex[c] = rgb[:, i]
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(buffer)
    atomic_write_bytes(scene.imported_points_path, buffer.getvalue())


def read_imported_points(scene: SceneDir) -> tuple[NDArray[np.float64], NDArray[np.uint8]] | None:
    """``(xyz, rgb)`` of ``capture/imported_points.ply``, or None when the scene has none."""
    from plyfile import PlyData

    path = scene.imported_points_path
    if not path.is_file():
        return None
    check_ply_header(path)
    try:
        vertex = PlyData.read(str(path))["vertex"]
        xyz = np.stack([np.asarray(vertex[c], np.float64) for c in "xyz"], axis=1)
        rgb = np.stack([np.asarray(vertex[c], np.uint8) for c in ("red", "green", "blue")], axis=1)
    except (KeyError, ValueError, OSError, IndexError) as exc:
        raise DataError(f"{path}: not the import's point file ({type(exc).__name__}: {exc})") from None
    return xyz, rgb

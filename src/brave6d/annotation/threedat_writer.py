"""Write a 3D-DAT folder: exactly the files a lab gets from the tool (see :mod:`brave6d.annotation.threedat`).

The demo uses it to hand its true object poses to the importer the way a human annotator would;
tests use it for round trips. Layout (3D-DAT README)::

    <out>/dataset.yaml                         General: paths relative to this file
    <out>/objects/object_library.yaml          id, name, mesh, class, description, color, scale
    <out>/objects/<id>/<mesh file>
    <out>/scenes/<scene>/camera.yaml           pinhole camera, no distortion
    <out>/scenes/<scene>/groundtruth_handeye.txt   id tx ty tz qx qy qz qw (camera-to-world)
    <out>/scenes/<scene>/rgb/, depth/          optional: the (undistorted) images, by frame id
    <out>/annotations/<scene>/poses.yaml       [{id, pose: 16 numbers}] model-to-world

With ``defaults_only`` the config holds only the two keys 3D-DAT has no default for and every
file sits where 3D-DAT looks by default (``objects/objects.yaml``, ``poses.yaml``). A library
entry without a mesh is written without the ``mesh`` key.

The folder is built beside ``out`` and renamed into place, so it is complete or absent.
"""

from __future__ import annotations

import re
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike

from brave6d.annotation.staging import link_or_copy
from brave6d.annotation.threedat import LibraryEntry, ThreeDatCamera, ThreeDatId, id_key, id_sort_key
from brave6d.core.atomic import atomic_write_text, staged_folder
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.names import check_folder_name
from brave6d.core.transforms import check_rigid, format_tum_line

_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def _safe_name(value: ThreeDatId) -> str:
    return _SAFE.sub("_", id_key(value)).strip("._") or "object"


def _frame_sort_key(frame_id: ThreeDatId) -> tuple[int, int, str]:
    text = id_key(frame_id)
    return id_sort_key(int(text)) if text.isdigit() else id_sort_key(text)


def _image_name(frame_id: ThreeDatId, suffix: str) -> str:
    text = id_key(frame_id)
    return f"{int(text):06d}{suffix}" if text.isdigit() else f"{text}{suffix}"


def _dump(data: Any) -> str:
    return yaml.safe_dump(data, default_flow_style=False, sort_keys=False)


def write_threedat_folder(
    out_dir: Path | str,
    scene_name: str,
    objects: Sequence[tuple[LibraryEntry, ArrayLike]],
    camera: PinholeCamera,
    camera_poses: Mapping[ThreeDatId, ArrayLike],
    *,
    library: Sequence[LibraryEntry] | None = None,
    images: Mapping[ThreeDatId, tuple[Path, Path | None]] | None = None,
    pose_file_name: str = "poses.yaml",
    camera_name: str | None = None,
    defaults_only: bool = False,
) -> Path:
    """Write a 3D-DAT folder and return the path of its ``dataset.yaml``.

    ``objects``: annotated instances as (library entry, ``world_T_model`` in metres).
    ``camera_poses``: ``world_T_cam`` per frame id. ``library``: all library entries (default:
    the distinct entries of ``objects``). ``images``: optional (rgb, depth) files per frame id,
    hard-linked (or copied) into ``scenes/<scene>/rgb`` and ``depth``. An existing ``out_dir`` is
    replaced only when it is a 3D-DAT folder (has ``dataset.yaml``) or empty. ``defaults_only``:
    see the module docstring (``pose_file_name`` must then be 3D-DAT's default).
    """
    out = Path(out_dir)
    check_folder_name(scene_name, "3D-DAT writer: scene name")  # scenes/<scene>/, annotations/<scene>/
    if defaults_only and pose_file_name != "poses.yaml":
        raise BraveError("3D-DAT writer: with defaults_only the pose file is 3D-DAT's default 'poses.yaml'")
    if out.exists() and any(out.iterdir()) and not (out / "dataset.yaml").is_file():
        raise BraveError(f"{out}: exists and is not a 3D-DAT folder (no dataset.yaml); refusing to replace it")
    cam = ThreeDatCamera.from_pinhole(camera, camera_name)
    entries = _library_entries(objects, library)
    instances = [(entry, check_rigid(T, f"object {entry.key!r}: world_T_model")) for entry, T in objects]
    frames = sorted(camera_poses.items(), key=lambda kv: _frame_sort_key(kv[0]))
    if not frames:
        raise BraveError("3D-DAT writer: no camera poses")
    for frame_id, _ in frames:
        if not id_key(frame_id) or re.search(r"[\s,]", id_key(frame_id)):
            raise BraveError(f"3D-DAT writer: frame id {frame_id!r} must be non-empty without spaces or commas")

    library_file = "objects/objects.yaml" if defaults_only else "objects/object_library.yaml"
    with staged_folder(out) as root:
        general = {"camera_intrinsics_file": "camera.yaml", "camera_pose_file": "groundtruth_handeye.txt"}
        if not defaults_only:
            general = {"scenes_dir": "scenes", "rgb_dir": "rgb", "depth_dir": "depth", **general,
                       "object_library_file": library_file, "annotation_dir": "annotations",
                       "object_pose_file": pose_file_name, "reconstruction_dir": "reconstructions"}
        atomic_write_text(root / "dataset.yaml", "---\n" + _dump({"General": general}))
        atomic_write_text(root / library_file, _dump(
            [_library_item(entry, root / "objects") for entry in entries]))
        scene = root / "scenes" / scene_name
        atomic_write_text(scene / "camera.yaml", _dump(_camera_item(cam)))
        lines = [format_tum_line(id_key(fid), check_rigid(T, f"frame {fid!r}: world_T_cam")) for fid, T in frames]
        atomic_write_text(scene / "groundtruth_handeye.txt", "\n".join(lines) + "\n")
        if images:
            _write_images(scene, images)
        poses = [{"id": entry.id, "pose": [float(x) for x in np.asarray(T).reshape(-1)]} for entry, T in instances]
        atomic_write_text(root / "annotations" / scene_name / pose_file_name, _dump(poses))
    return out / "dataset.yaml"


def _library_entries(objects: Sequence[tuple[LibraryEntry, ArrayLike]],
                     library: Sequence[LibraryEntry] | None) -> list[LibraryEntry]:
    entries: dict[str, LibraryEntry] = {}
    for entry in (library if library is not None else [e for e, _ in objects]):
        if entry.key in entries and entries[entry.key] != entry:
            raise BraveError(f"3D-DAT writer: two different library entries with id {entry.id!r}")
        entries[entry.key] = entry
    for entry, _ in objects:
        if entry.key not in entries:
            raise BraveError(f"3D-DAT writer: object {entry.id!r} is not in the library")
        if entry.mesh is None:
            raise BraveError(f"3D-DAT writer: object {entry.id!r} has no mesh, so it cannot be annotated")
    return list(entries.values())


def _library_item(entry: LibraryEntry, objects_dir: Path) -> dict[str, Any]:
    """Copy the mesh (and same-stem sidecars such as .mtl) and describe the entry."""
    item: dict[str, Any] = {"id": entry.id, "name": entry.display_name}
    if entry.mesh is not None:
        item["mesh"] = _copy_mesh(entry, Path(entry.mesh), objects_dir)
    if entry.class_name is not None:
        item["class"] = entry.class_name
    if entry.description is not None:
        item["description"] = entry.description
    if entry.color is not None:
        item["color"] = [int(c) for c in entry.color]
    item["scale"] = float(entry.scale)
    if entry.symmetries_discrete:
        item["symmetries_discrete"] = [[float(x) for x in np.asarray(m).reshape(-1)] for m in entry.symmetries_discrete]
    if entry.symmetries_continuous:
        item["symmetries_continuous"] = [{"axis": [float(a) for a in s.axis], "offset": [float(o) for o in s.offset]}
                                         for s in entry.symmetries_continuous]
    return item


def _copy_mesh(entry: LibraryEntry, src: Path, objects_dir: Path) -> str:
    """Copy ``src`` and its same-stem sidecars into ``objects/<id>/``; the path 3D-DAT reads."""
    if not src.is_file():
        raise BraveError(f"3D-DAT writer: mesh of {entry.id!r} not found: {src}")
    folder = objects_dir / _safe_name(entry.id)
    folder.mkdir(parents=True, exist_ok=True)
    for sibling in src.parent.glob(src.stem + ".*"):
        if sibling.is_file():
            shutil.copy2(sibling, folder / sibling.name)
    return f"{folder.name}/{src.name}"


def _camera_item(cam: ThreeDatCamera) -> dict[str, Any]:
    item: dict[str, Any] = {}
    if cam.name is not None:
        item["name"] = cam.name
    item.update({"image_width": int(cam.width), "image_height": int(cam.height),
                 "camera_matrix": [float(cam.fx), 0.0, float(cam.cx), 0.0, float(cam.fy), float(cam.cy),
                                   0.0, 0.0, 1.0]})
    if cam.sensor_width is not None:
        item["sensor_width"] = float(cam.sensor_width)
    return item


def _write_images(scene: Path, images: Mapping[ThreeDatId, tuple[Path, Path | None]]) -> None:
    for frame_id, (rgb, depth) in images.items():
        rgb = Path(rgb)
        link_or_copy(rgb, scene / "rgb" / _image_name(frame_id, rgb.suffix))
        if depth is not None:
            depth = Path(depth)
            link_or_copy(depth, scene / "depth" / _image_name(frame_id, depth.suffix))

"""Read 3D-DAT annotation folders (markus-suchi/3D-DAT) into typed, validated objects.

What 3D-DAT's own reader does (markus-suchi/3D-DAT at 57e1af8, read, not copied), point by point:

* Config, ``v4r_dataset_toolkit/io.py``, ``SceneFileReader.create`` and ``__init__``: only the
  ``General:`` mapping is read. ``root_dir`` defaults to the folder of the config file; when given
  it is used as written (a relative one is therefore relative to the working directory of the
  process). ``annotation_dir`` (default ``annotations``), ``object_library_file`` (default
  ``objects/objects.yaml``) and ``reconstruction_dir`` (default ``reconstructions``) fall back to
  their defaults when missing OR empty; ``scenes_dir`` (``scenes``), ``rgb_dir`` (``rgb``),
  ``depth_dir`` (``depth``) and ``object_pose_file`` (``poses.yaml``) only when the key is
  missing. ``camera_intrinsics_file`` and ``camera_pose_file`` have no default (the reader fails
  on the first path it builds). Every path is joined onto ``root_dir`` unless absolute.
* Scenes, ``get_scene_ids``: the sub-folders of ``<root>/<scenes_dir>``, sorted. Intrinsics,
  ``get_camera_info_scene``: ``<scene>/<camera_intrinsics_file>``, else the shared one in
  ``scenes_dir``.
* Camera poses and views, ``get_camera_poses``: every line of ``<scene>/<camera_pose_file>`` is
  split on whitespace, its first field (the id) is DROPPED and the other seven are
  ``tx ty tz qx qy qz qw``. ``get_images_rgb_path`` (with ``get_file_list``) lists the files
  ending in ``.png``/``.jpg`` anywhere under ``<scene>/<rgb_dir>`` and sorts their paths; the
  Blender tool (``blender/v4r_blender_utils.py``, ``load_cameras``) then gives camera ``i`` the
  pose of line ``i`` and the background image ``i`` of that list, as ``get_pointclouds`` does with
  depth. The ids are never looked at: the pairing is line order with sorted image order (more
  images than lines: the extra ones are unused; fewer: the tool fails).
* Object library, ``v4r_dataset_toolkit/objects.py``, ``ObjectLibrary.create`` and ``Object``:
  a YAML list; ``id`` is required, every other key optional. ``mesh`` is joined onto the library
  file's folder when present and ``Object`` has no mesh when it is missing or empty; a given mesh
  must exist (``meshreader.py``, ``MeshReader.__init__`` raises otherwise) but is parsed only
  when shown. ``scale`` is used as given, and a missing or empty (falsy) one means 1; meshes are
  scaled about their origin before the pose is applied (``MeshReader.as_o3d``/``as_bpy_mesh``).
  A later entry with the same id replaces an earlier one.
* Object poses, ``get_object_poses``: ``<annotation_dir>/<scene>/<object_pose_file>``; a missing
  file gives NO objects without a word; otherwise a YAML list (``[]``: no objects) of
  ``{id, pose}`` where a missing pose means the identity and an unknown id fails. The Blender
  tool (``load_objects``) needs a mesh for every listed object; ``save_pose`` writes ``[]`` when
  the scene has no objects, ids as strings and ``pose`` as the 16 numbers of Blender's
  ``matrix_world`` (row-major, float32 precision).

What this reader does with the same folders:

* Config (:func:`read_config`): the same defaults, the same ``root_dir`` (a relative one against
  the working directory, refused when that is no folder). A null ``scenes_dir``/``rgb_dir``/
  ``depth_dir``/``object_pose_file`` (3D-DAT fails on it) and an empty ``object_pose_file`` are
  refused naming the key; a missing ``camera_intrinsics_file``/``camera_pose_file`` too.
* Views: :func:`rgb_files` lists the images exactly as 3D-DAT does; :mod:`brave6d.annotation.pairing`
  pairs line ``i`` with the captured view image ``i`` names, the ids (captured frame index or
  view id) being the cross-check and the fallback when there are no such images. The camera-pose
  file itself stays stricter than 3D-DAT where that guards the result (unit quaternions, unique
  ids, 8 fields), and more lenient where it costs nothing (commas, blank and ``#`` lines).
* Library (:func:`read_library`): an entry without ``mesh`` is accepted; ``scale`` as in 3D-DAT
  (:func:`parse_scale`) but refused when negative, infinite or NaN; a repeated id is refused.
  Only annotated objects become objects of the import (and BOP models, :mod:`brave6d.annotation.bop`).
* Poses (:func:`read_object_poses`): ``[]`` is a scene without objects (with a warning). A missing
  configured pose file is replaced by the other name 3D-DAT uses (``pose.yaml``/``poses.yaml``)
  with a warning naming both, else refused. Kept stricter: a missing ``pose`` (3D-DAT: identity),
  non-rigid or NaN poses, an object without mesh, an unknown id (3D-DAT fails too).

Files, as 3D-DAT lays them out:

* the dataset config (``dataset.yaml``): a ``General:`` mapping with ``scenes_dir``,
  ``camera_intrinsics_file``, ``camera_pose_file``, ``object_library_file``, ``annotation_dir``,
  ``object_pose_file`` (and optional ``root_dir``, ``rgb_dir``, ``depth_dir``,
  ``reconstruction_dir``); paths are relative to ``root_dir`` (default: the config's folder);
* ``object_library.yaml``: a list of ``{id, name, mesh, class, description, color, scale}``;
  ``mesh`` is relative to the library file, ``scale`` converts mesh units to metres. BRAVE-6D adds
  two optional keys that 3D-DAT ignores: ``symmetries_discrete`` (flattened 4x4, model frame,
  translation in metres) and ``symmetries_continuous`` (``{axis, offset}``, offset in metres);
* ``annotations/<scene>/poses.yaml`` (or ``pose.yaml``, as the 3D-DAT README names it): a list of
  ``{id, pose}`` with ``pose`` a row-major 4x4 (16 numbers) model-to-world transform in metres,
  applied to the mesh AFTER scaling; ids may repeat (several instances of one object);
* ``scenes/<scene>/camera.yaml`` (or shared ``scenes/camera.yaml``): ``name``, ``image_width``,
  ``image_height``, ``camera_matrix`` (9 numbers, row-major), optional ``sensor_width``;
* ``scenes/<scene>/groundtruth_handeye.txt``: ``id tx ty tz qx qy qz qw`` per view, whitespace
  (or comma) separated, camera-to-world, metres, OpenCV camera axes, quaternion scalar LAST.

Every problem raises :class:`ThreeDatError` naming the file and the entry (1-based) or line.
The writer of the same format lives in :mod:`brave6d.annotation.threedat_writer`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, DataError, NonRigidTransformError
from brave6d.core.transforms import check_rigid, nearest_rigid, parse_tum_line, unit_quaternion
from brave6d.core.yaml_io import read_yaml

Matrix4 = NDArray[np.float64]
ThreeDatId = int | str

#: Names 3D-DAT uses for the object pose file (the code writes ``poses.yaml``, the README says ``pose.yaml``).
POSE_FILE_NAMES = ("poses.yaml", "pose.yaml")
#: ``General`` keys without a default in 3D-DAT (``SceneFileReader`` fails without them).
REQUIRED_KEYS = ("camera_intrinsics_file", "camera_pose_file")
#: 3D-DAT's defaults used when the key is missing, null or empty (``SceneFileReader.create``).
DEFAULTS_WHEN_EMPTY = {"annotation_dir": "annotations", "object_library_file": "objects/objects.yaml"}
#: 3D-DAT's defaults used only when the key is missing (``SceneFileReader.__init__``).
DEFAULTS_WHEN_MISSING = {"scenes_dir": "scenes", "rgb_dir": "rgb", "depth_dir": "depth",
                         "object_pose_file": "poses.yaml"}
#: Image files 3D-DAT pairs with the camera poses (``get_images_rgb_path``; case-sensitive).
RGB_SUFFIXES = (".png", ".jpg")
#: Config file names tried, in order, when a folder is given.
CONFIG_NAMES = ("dataset.yaml", "config.yaml", "dataset.yml", "config.yml")


class ThreeDatError(DataError):
    """A 3D-DAT file is missing or malformed; the message names the file and the entry or line."""


# ----------------------------------------------------------------------------- types
@dataclass(frozen=True)
class ThreeDatConfig:
    """The ``General`` section of a dataset config, with paths resolved against ``root_dir``."""

    path: Path
    root_dir: Path
    scenes_dir: Path
    camera_intrinsics_file: str
    camera_pose_file: str
    object_library_file: Path
    annotation_dir: Path
    object_pose_file: str
    rgb_dir: str = "rgb"
    depth_dir: str = "depth"

    @property
    def root(self) -> Path:
        """3D-DAT's ``root_dir``: the config's folder unless ``General: root_dir`` says otherwise."""
        return self.root_dir

    def scene_ids(self) -> list[str]:
        """Scene folders under ``scenes_dir``, sorted (as 3D-DAT lists them)."""
        if not self.scenes_dir.is_dir():
            return []
        return sorted(p.name for p in self.scenes_dir.iterdir() if p.is_dir())

    def annotated_scene_ids(self) -> list[str]:
        """Scenes that have an object pose file (under either name)."""
        return [s for s in self.scene_ids() if _existing_pose_file(self, s)[0] is not None]

    def camera_file(self, scene_id: str) -> Path:
        """``camera.yaml`` of the scene, or the shared one in ``scenes_dir`` (3D-DAT's order)."""
        own = self.scenes_dir / scene_id / self.camera_intrinsics_file
        shared = self.scenes_dir / self.camera_intrinsics_file
        if own.is_file():
            return own
        if shared.is_file():
            return shared
        raise ThreeDatError(f"{_show(own, self.root)}: camera intrinsics file not found "
                            f"(nor the shared {_show(shared, self.root)})")

    def camera_pose_path(self, scene_id: str) -> Path:
        return self.scenes_dir / scene_id / self.camera_pose_file

    def rgb_path(self, scene_id: str) -> Path:
        return self.scenes_dir / scene_id / self.rgb_dir

    def pose_path(self, scene_id: str) -> tuple[Path, str | None]:
        """The object pose file and, when it is not the configured one, a note saying which was used.

        3D-DAT reads only ``object_pose_file`` (a missing one means no objects); here the other
        name 3D-DAT uses (``poses.yaml``/``pose.yaml``) stands in, and the note says so.
        """
        found, note = _existing_pose_file(self, scene_id)
        if found is None:
            named = self.annotation_dir / scene_id / self.object_pose_file
            others = [n for n in POSE_FILE_NAMES if n != self.object_pose_file]
            raise ThreeDatError(f"{_show(named, self.root)}: object pose file not found (the scene is not "
                                f"annotated; also looked for {' and '.join(others)} there)")
        return found, note

    def show(self, path: Path) -> str:
        """``path`` relative to the dataset root when it lies inside it (for messages)."""
        return _show(path, self.root)


@dataclass(frozen=True)
class ContinuousSymmetry:
    """Rotational symmetry about ``axis`` (unit vector) through ``offset`` (metres, model frame)."""

    axis: tuple[float, float, float]
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class LibraryEntry:
    """One object of the library. ``mesh`` is an absolute path (None: the entry has no mesh, which
    3D-DAT allows for objects that are not annotated); ``scale`` maps mesh units to metres.

    ``symmetries_discrete`` are 4x4 model-frame transforms with translation in metres.
    ``entry`` is the 1-based position in the library file (0 when made in code).
    """

    id: ThreeDatId
    mesh: Path | None
    scale: float = 1.0
    name: str = ""
    class_name: str | None = None
    description: str | None = None
    color: tuple[int, int, int] | None = None
    symmetries_discrete: tuple[Matrix4, ...] = ()
    symmetries_continuous: tuple[ContinuousSymmetry, ...] = ()
    entry: int = 0

    @property
    def key(self) -> str:
        """The id as text: how ids from different files are compared."""
        return id_key(self.id)

    @property
    def display_name(self) -> str:
        return self.name or self.key


@dataclass(frozen=True)
class ObjectPose:
    """One annotated instance: library id and ``world_T_model`` (3D-DAT world, metres, rigid)."""

    object_id: ThreeDatId
    world_T_model: Matrix4
    entry: int = 0


@dataclass(frozen=True)
class CameraPose:
    """One view of ``groundtruth_handeye.txt``: frame id and ``world_T_cam`` (OpenCV axes)."""

    frame_id: str
    world_T_cam: Matrix4
    line: int = 0


@dataclass(frozen=True)
class ThreeDatCamera:
    """``camera.yaml``: a pinhole camera without distortion (3D-DAT has none)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    name: str | None = None
    sensor_width: float | None = None

    def pinhole(self) -> PinholeCamera:
        return PinholeCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    @classmethod
    def from_pinhole(cls, camera: PinholeCamera, name: str | None = None) -> ThreeDatCamera:
        if camera.has_distortion:
            raise BraveError("3D-DAT cameras have no distortion: pass the undistorted (pinhole) camera")
        return cls(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, name)


@dataclass(frozen=True)
class ThreeDatScene:
    """Everything the importer needs of one annotated scene."""

    config: ThreeDatConfig
    scene_id: str
    library: tuple[LibraryEntry, ...]
    objects: tuple[ObjectPose, ...]
    camera: ThreeDatCamera
    camera_poses: tuple[CameraPose, ...]
    files: dict[str, Path] = field(default_factory=dict)
    rgb_files: tuple[Path, ...] = ()
    warnings: tuple[str, ...] = ()

    def entry(self, object_id: ThreeDatId) -> LibraryEntry:
        key = id_key(object_id)
        for item in self.library:
            if item.key == key:
                return item
        raise KeyError(key)


# ----------------------------------------------------------------------------- helpers
def id_key(value: ThreeDatId) -> str:
    """Canonical text of a 3D-DAT id (YAML may give ints or strings)."""
    return str(value)


def id_sort_key(value: ThreeDatId) -> tuple[int, int, str]:
    """Sort order of ids: integers numerically first, then strings alphabetically."""
    if isinstance(value, int):
        return (0, value, "")
    return (1, 0, str(value))


def _show(path: Path, root: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(root.resolve()))
    except ValueError:
        return str(path)


def _existing_pose_file(config: ThreeDatConfig, scene_id: str) -> tuple[Path | None, str | None]:
    """The configured pose file if it exists, else the first other 3D-DAT name that does (with a note)."""
    folder = config.annotation_dir / scene_id
    configured = folder / config.object_pose_file
    if configured.is_file():
        return configured, None
    for name in POSE_FILE_NAMES:
        if name != config.object_pose_file and (folder / name).is_file():
            note = (f"{_show(configured, config.root)} (object_pose_file in {config.path.name}) not found; "
                    f"read {_show(folder / name, config.root)} instead")
            return folder / name, note
    return None, None


def _finite_numbers(values: Any, count: int | None, what: str) -> list[float]:
    """A flat list of finite floats (nested lists are flattened); raises ValueError with ``what``."""
    if not isinstance(values, list | tuple):
        raise ValueError(f"{what} must be a list of numbers, got {type(values).__name__}")
    flat: list[Any] = []
    stack = [values]
    while stack:  # depth-first, keeps order
        head = stack.pop()
        if isinstance(head, list | tuple):
            stack.extend(reversed(head))
        else:
            flat.append(head)
    out = []
    for v in flat:
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ValueError(f"{what} must contain only numbers, got {v!r}")
        if not math.isfinite(float(v)):
            raise ValueError(f"{what} contains NaN or inf")
        out.append(float(v))
    if count is not None and len(out) != count:
        raise ValueError(f"{what} must have {count} numbers, got {len(out)}")
    return out


def _valid_id(value: Any) -> bool:
    return (isinstance(value, int) and not isinstance(value, bool)) or (isinstance(value, str) and value != "")


# ----------------------------------------------------------------------------- config
def find_config(dat_dir: Path | str) -> Path:
    """The dataset config of a 3D-DAT folder (or ``dat_dir`` itself when it is a file)."""
    p = Path(dat_dir)
    if p.is_file():
        return p
    if not p.is_dir():
        raise ThreeDatError(f"{p}: no such 3D-DAT folder or config file")
    for name in CONFIG_NAMES:
        if (p / name).is_file():
            return p / name
    candidates = []
    for f in sorted([*p.glob("*.yaml"), *p.glob("*.yml")]):
        try:
            data = read_yaml(f)
        except DataError:
            continue
        if isinstance(data, dict) and "General" in data:
            candidates.append(f)
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise ThreeDatError(f"{p}: no 3D-DAT dataset config (a YAML file with a 'General:' section) in this folder")
    raise ThreeDatError(f"{p}: several dataset configs ({', '.join(c.name for c in candidates)}); pass one of them")


def read_config(path: Path | str) -> ThreeDatConfig:
    """Parse a dataset config (file, or a folder holding one) with 3D-DAT's defaults and ``root_dir``."""
    cfg_path = find_config(path).resolve()
    shown = cfg_path.name
    data = read_yaml(cfg_path, shown, ThreeDatError)
    if not isinstance(data, dict) or not isinstance(data.get("General"), dict):
        raise ThreeDatError(f"{shown}: expected a mapping with a 'General:' section")
    general = data["General"]
    values = {key: _required_key(general, key, shown) for key in REQUIRED_KEYS}
    for key, default in DEFAULTS_WHEN_EMPTY.items():
        values[key] = _path_value(general, key, shown) or default
    for key, default in DEFAULTS_WHEN_MISSING.items():
        values[key] = _key_with_default(general, key, default, shown)
    root = _root_dir(general, cfg_path)

    def resolve(key: str) -> Path:
        q = Path(values[key]).expanduser()
        return q if q.is_absolute() else root / q

    return ThreeDatConfig(
        path=cfg_path,
        root_dir=root,
        scenes_dir=resolve("scenes_dir"),
        camera_intrinsics_file=values["camera_intrinsics_file"],
        camera_pose_file=values["camera_pose_file"],
        object_library_file=resolve("object_library_file"),
        annotation_dir=resolve("annotation_dir"),
        object_pose_file=values["object_pose_file"],
        rgb_dir=values["rgb_dir"],
        depth_dir=values["depth_dir"],
    )


def _path_value(general: dict[str, Any], key: str, shown: str) -> str | None:
    """The key's text, stripped; None when missing, null or empty. Anything but text is an error."""
    value = general.get(key)
    if value is None:
        return None
    if not isinstance(value, str):
        raise ThreeDatError(f"{shown}: General: key '{key}' must be a path, got {value!r}")
    return value.strip() or None


def _required_key(general: dict[str, Any], key: str, shown: str) -> str:
    """A key 3D-DAT has no default for."""
    if key not in general or general[key] is None:
        raise ThreeDatError(f"{shown}: General: missing key '{key}' (3D-DAT has no default for it)")
    value = _path_value(general, key, shown)
    if value is None:
        raise ThreeDatError(f"{shown}: General: key '{key}' must be a non-empty file name, got {general[key]!r}")
    return value


def _key_with_default(general: dict[str, Any], key: str, default: str, shown: str) -> str:
    """3D-DAT's ``dict.get(key, default)``: the default only when the key is missing.

    A null value makes 3D-DAT fail (it joins None onto a path), so it is refused; an empty folder
    name means the parent folder itself, as in 3D-DAT; an empty file name is refused.
    """
    if key not in general:
        return default
    if general[key] is None:
        raise ThreeDatError(f"{shown}: General: key '{key}' is empty (null); leave it out for 3D-DAT's "
                            f"default {default!r}")
    value = _path_value(general, key, shown) or ""
    if not value and key == "object_pose_file":
        raise ThreeDatError(f"{shown}: General: key '{key}' must be a file name, got {general[key]!r}")
    return value


def _root_dir(general: dict[str, Any], cfg_path: Path) -> Path:
    """``General: root_dir`` as 3D-DAT uses it: the config's folder when missing or empty, else the
    path as written (a relative one against the working directory, as 3D-DAT joins it)."""
    value = _path_value(general, "root_dir", cfg_path.name)
    if value is None:
        return cfg_path.parent
    written = Path(value).expanduser()
    root = written if written.is_absolute() else Path.cwd() / written
    if not root.is_dir():
        where = "" if written.is_absolute() else f" (relative to the working directory {Path.cwd()}, as in 3D-DAT)"
        raise ThreeDatError(f"{cfg_path.name}: General: root_dir {value!r} is not a folder{where}")
    return root.resolve()


# ----------------------------------------------------------------------------- object library
def read_library(path: Path | str, root: Path | None = None) -> list[LibraryEntry]:
    """Parse ``object_library.yaml`` (a YAML list, ``[]`` allowed as in 3D-DAT).

    Ids must be unique (3D-DAT would keep the later entry silently). A ``mesh``, when given,
    must exist; an entry without one is accepted (it cannot be annotated). ``scale``: see
    :func:`parse_scale`.
    """
    lib_path = Path(path)
    shown = _show(lib_path, root) if root is not None else str(lib_path)
    data = read_yaml(lib_path, shown, ThreeDatError)
    if not isinstance(data, list):
        raise ThreeDatError(f"{shown}: expected a YAML list of objects ({{id, mesh, scale, ...}})")
    entries: list[LibraryEntry] = []
    seen: dict[str, int] = {}
    for number, item in enumerate(data, start=1):
        where = f"{shown}: entry {number}"
        if not isinstance(item, dict):
            raise ThreeDatError(f"{where}: expected a mapping with 'id' and 'mesh', got {type(item).__name__}")
        oid = item.get("id")
        if not _valid_id(oid):
            raise ThreeDatError(f"{where}: 'id' is missing or not a string/integer (got {oid!r})")
        where = f"{where} (id {oid!r})"
        key = id_key(oid)
        if key in seen:
            raise ThreeDatError(f"{where}: duplicate id (also entry {seen[key]})")
        seen[key] = number
        entries.append(_library_entry(item, oid, number, where, lib_path.parent, root))
    return entries


def _library_entry(item: dict[str, Any], oid: ThreeDatId, number: int, where: str, folder: Path,
                   root: Path | None) -> LibraryEntry:
    mesh_path = _mesh_path(item.get("mesh"), where, folder, root)
    try:
        scale = parse_scale(item.get("scale"))
    except ValueError as exc:
        raise ThreeDatError(f"{where}: {exc}") from None
    color = item.get("color")
    if color is not None:
        try:
            rgb = _finite_numbers(color, 3, "'color'")
        except ValueError as exc:
            raise ThreeDatError(f"{where}: {exc}") from None
        color = tuple(int(round(c)) for c in rgb)
    name = item.get("name")
    cls = item.get("class")
    desc = item.get("description")
    return LibraryEntry(
        id=oid, mesh=mesh_path, scale=scale,
        name=str(name) if name is not None else id_key(oid),
        class_name=str(cls) if cls is not None else None,
        description=str(desc) if desc is not None else None,
        color=color,  # type: ignore[arg-type]
        symmetries_discrete=_discrete_symmetries(item.get("symmetries_discrete"), where),
        symmetries_continuous=_continuous_symmetries(item.get("symmetries_continuous"), where),
        entry=number,
    )


def _mesh_path(value: Any, where: str, folder: Path, root: Path | None) -> Path | None:
    """The entry's mesh, absolute; None when missing or empty (3D-DAT: an object without mesh)."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    if not isinstance(value, str):
        raise ThreeDatError(f"{where}: 'mesh' must be a path relative to the library file, got {value!r}")
    mesh_path = Path(value.strip()).expanduser()
    mesh_path = mesh_path if mesh_path.is_absolute() else folder / mesh_path
    if not mesh_path.is_file():
        shown_mesh = _show(mesh_path, root) if root is not None else str(mesh_path)
        raise ThreeDatError(f"{where}: mesh not found: {shown_mesh}")
    return mesh_path.resolve()


def parse_scale(value: Any) -> float:
    """A library ``scale`` as 3D-DAT uses it: missing or empty (any false value) means 1; a number,
    or text that reads as one (Blender converts it with ``float``), must be finite and positive
    (a negative scale mirrors the mesh). Raises ValueError naming the key."""
    if not value:
        return 1.0
    number: float | None = None
    if isinstance(value, int | float) and not isinstance(value, bool):
        number = float(value)
    elif isinstance(value, str):
        try:
            number = float(value.strip())
        except ValueError:
            number = None
    if number is None or not math.isfinite(number) or number <= 0:
        raise ValueError(f"'scale' must be a positive number (mesh units to metres), got {value!r}")
    return number


def _discrete_symmetries(value: Any, where: str) -> tuple[Matrix4, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise ThreeDatError(f"{where}: 'symmetries_discrete' must be a list of flattened 4x4 matrices")
    out = []
    for i, m in enumerate(value, start=1):
        try:
            nums = _finite_numbers(m, 16, f"'symmetries_discrete' item {i}")
            out.append(check_rigid(np.reshape(nums, (4, 4)), f"'symmetries_discrete' item {i}"))
        except (ValueError, NonRigidTransformError) as exc:
            raise ThreeDatError(f"{where}: {exc}") from None
    return tuple(out)


def _continuous_symmetries(value: Any, where: str) -> tuple[ContinuousSymmetry, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise ThreeDatError(f"{where}: 'symmetries_continuous' must be a list of {{axis, offset}}")
    out = []
    for i, s in enumerate(value, start=1):
        what = f"'symmetries_continuous' item {i}"
        if not isinstance(s, dict) or "axis" not in s:
            raise ThreeDatError(f"{where}: {what} must be a mapping with 'axis' (and optional 'offset')")
        try:
            axis = np.asarray(_finite_numbers(s["axis"], 3, f"{what} axis"))
            offset = _finite_numbers(s.get("offset", [0.0, 0.0, 0.0]), 3, f"{what} offset")
        except ValueError as exc:
            raise ThreeDatError(f"{where}: {exc}") from None
        norm = float(np.linalg.norm(axis))
        if norm < 1e-9:
            raise ThreeDatError(f"{where}: {what} axis has zero length")
        out.append(ContinuousSymmetry(tuple((axis / norm).tolist()), tuple(offset)))  # type: ignore[arg-type]
    return tuple(out)


# ----------------------------------------------------------------------------- object poses
def parse_pose_matrix(value: Any, name: str) -> Matrix4:
    """16 numbers (row-major, or nested 4x4) -> rigid float64 4x4; raises NonRigidTransformError.

    The rotation block is projected onto the nearest rotation when it is one up to rounding (Blender
    stores float32 matrices), the one rule for poses made elsewhere
    (:func:`brave6d.core.transforms.nearest_rotation`).
    """
    try:
        nums = _finite_numbers(value, None, "pose")
    except ValueError as exc:
        raise NonRigidTransformError(f"{name}: {exc}") from None
    if len(nums) != 16:
        raise NonRigidTransformError(f"{name}: expected 16 numbers (row-major 4x4), got {len(nums)}")
    return nearest_rigid(np.reshape(nums, (4, 4)), name)[0]


def read_object_poses(path: Path | str, library: Sequence[LibraryEntry], root: Path | None = None,
                      library_name: str = "the object library") -> list[ObjectPose]:
    """Parse ``poses.yaml``: a YAML list (``[]``, what 3D-DAT saves for a scene without objects, is
    accepted); every id must be in ``library`` with a mesh, every pose rigid."""
    pose_path = Path(path)
    shown = _show(pose_path, root) if root is not None else str(pose_path)
    data = read_yaml(pose_path, shown, ThreeDatError)
    if not isinstance(data, list):
        raise ThreeDatError(f"{shown}: expected a YAML list of {{id, pose}} entries ([] for no objects)")
    known = {e.key: e for e in library}
    poses = []
    for number, item in enumerate(data, start=1):
        where = f"{shown}: entry {number}"
        if not isinstance(item, dict):
            raise ThreeDatError(f"{where}: expected a mapping with 'id' and 'pose', got {type(item).__name__}")
        oid = item.get("id")
        if not _valid_id(oid):
            raise ThreeDatError(f"{where}: 'id' is missing or not a string/integer (got {oid!r})")
        where = f"{where} (id {oid!r})"
        if id_key(oid) not in known:
            listing = (", ".join(repr(e.id) for e in library[:10]) + (", ..." if len(library) > 10 else "")) or "none"
            raise ThreeDatError(f"{where}: unknown object id {oid!r} (not in {library_name}; known: {listing})")
        if known[id_key(oid)].mesh is None:
            raise ThreeDatError(f"{where}: object {oid!r} has no mesh in {library_name} "
                                f"(entry {known[id_key(oid)].entry}); an annotated object needs one")
        if "pose" not in item:
            raise ThreeDatError(f"{where}: 'pose' is missing (16 numbers, row-major 4x4)")
        try:
            T = parse_pose_matrix(item["pose"], f"{where}: pose is not rigid")
        except NonRigidTransformError as exc:
            raise ThreeDatError(str(exc)) from None
        poses.append(ObjectPose(object_id=known[id_key(oid)].id, world_T_model=T, entry=number))
    return poses


# ----------------------------------------------------------------------------- camera
def read_camera(path: Path | str, root: Path | None = None) -> ThreeDatCamera:
    """Parse ``camera.yaml`` (image size and the 9-number camera matrix)."""
    cam_path = Path(path)
    shown = _show(cam_path, root) if root is not None else str(cam_path)
    data = read_yaml(cam_path, shown, ThreeDatError)
    if not isinstance(data, dict):
        raise ThreeDatError(f"{shown}: expected a mapping (name, image_width, image_height, camera_matrix)")
    size = []
    for key in ("image_width", "image_height"):
        v = data.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ThreeDatError(f"{shown}: '{key}' must be a positive integer, got {v!r}")
        size.append(v)
    km = data.get("camera_matrix")
    if isinstance(km, dict) and "data" in km:  # ROS camera_info style
        km = km["data"]
    try:
        k = _finite_numbers(km, 9, "'camera_matrix'")
    except ValueError as exc:
        raise ThreeDatError(f"{shown}: {exc}") from None
    if k[0] <= 0 or k[4] <= 0:
        raise ThreeDatError(f"{shown}: 'camera_matrix' focal lengths must be positive, got fx={k[0]}, fy={k[4]}")
    sensor = data.get("sensor_width")
    name = data.get("name")
    return ThreeDatCamera(width=size[0], height=size[1], fx=k[0], fy=k[4], cx=k[2], cy=k[5],
                          name=str(name) if name is not None else None,
                          sensor_width=float(sensor) if isinstance(sensor, int | float) else None)


# ----------------------------------------------------------------------------- camera poses
def read_camera_poses(path: Path | str, root: Path | None = None) -> list[CameraPose]:
    """Parse ``groundtruth_handeye.txt``: ``id tx ty tz qx qy qz qw`` per line (spaces or commas).

    Blank lines and lines starting with ``#`` are skipped. Quaternions must have unit norm
    (within :data:`brave6d.core.transforms.QUATERNION_TOLERANCE`); frame ids must be unique.
    """
    pose_path = Path(path)
    shown = _show(pose_path, root) if root is not None else str(pose_path)
    if not pose_path.is_file():
        raise ThreeDatError(f"{shown}: file not found")
    try:
        text = pose_path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ThreeDatError(f"{shown}: not UTF-8 text ({exc.reason})") from None
    poses: list[CameraPose] = []
    seen: dict[str, int] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{shown}:{number}"
        try:
            frame_id, T = parse_tum_line(line)
        except NonRigidTransformError as exc:
            raise ThreeDatError(f"{where}: {exc}") from None
        q = np.asarray([float(x) for x in line.replace(",", " ").split()[4:8]])
        try:
            unit_quaternion(q, f"{where}: frame {frame_id!r}", "qx qy qz qw")
        except NonRigidTransformError as exc:
            raise ThreeDatError(str(exc)) from None
        if frame_id in seen:
            raise ThreeDatError(f"{where}: frame {frame_id!r} appears twice (also line {seen[frame_id]})")
        seen[frame_id] = number
        poses.append(CameraPose(frame_id=frame_id, world_T_cam=T, line=number))
    if not poses:
        raise ThreeDatError(f"{shown}: no camera poses")
    return poses


# ----------------------------------------------------------------------------- images
def rgb_files(folder: Path) -> list[Path]:
    """The images 3D-DAT pairs with the camera-pose lines, in its order: every file under
    ``folder`` (sub-folders included) whose name ends in ``.png`` or ``.jpg``, sorted by path
    (none when the folder is missing)."""
    found = []
    for parent, _, names in os.walk(folder):
        found.extend(os.path.join(parent, n) for n in names if n.endswith(RGB_SUFFIXES))
    return [Path(f) for f in sorted(found)]


# ----------------------------------------------------------------------------- everything
def read_threedat(dat_dir: Path | str, scene_id: str | None = None) -> ThreeDatScene:
    """Read one annotated scene of a 3D-DAT folder (``scene_id`` may be left out when there is one)."""
    config = read_config(dat_dir)
    if scene_id is None:
        annotated = config.annotated_scene_ids()
        if len(annotated) != 1:
            listing = ", ".join(annotated) or "none"
            raise ThreeDatError(f"{config.show(config.annotation_dir)}: {len(annotated)} annotated scenes "
                                f"({listing}); choose one with --scene")
        scene_id = annotated[0]
    elif not (config.scenes_dir / scene_id).is_dir():
        raise ThreeDatError(f"{config.show(config.scenes_dir / scene_id)}: scene folder not found "
                            f"(scenes: {', '.join(config.scene_ids()) or 'none'})")
    root = config.root
    library = read_library(config.object_library_file, root)
    lib_name = config.show(config.object_library_file)
    pose_file, note = config.pose_path(scene_id)
    objects = read_object_poses(pose_file, library, root, library_name=lib_name)
    cam_file = config.camera_file(scene_id)
    camera = read_camera(cam_file, root)
    traj_file = config.camera_pose_path(scene_id)
    camera_poses = read_camera_poses(traj_file, root)
    warnings = [note] if note else []
    if not objects:
        warnings.append(f"{config.show(pose_file)}: no annotated objects (an empty list)")
    return ThreeDatScene(config=config, scene_id=scene_id, library=tuple(library), objects=tuple(objects),
                         camera=camera, camera_poses=tuple(camera_poses),
                         files={"config": config.path, "library": config.object_library_file,
                                "poses": pose_file, "camera": cam_file, "camera_poses": traj_file},
                         rgb_files=tuple(rgb_files(config.rgb_path(scene_id))), warnings=tuple(warnings))

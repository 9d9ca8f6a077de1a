"""Robot poses (``base_T_tcp``) from files written elsewhere: the one reader of those formats.

Three pose forms, each in text (``.txt``/``.csv``), NumPy (``.npy``), JSON or YAML files:

* **4x4 matrix** (row-major; 16 numbers, or 12 for the top three rows): recognised by itself;
  the rotation block is projected onto the nearest rotation when it is one up to rounding (printed
  digits), and refused when scaled, sheared or mirrored (the one rule,
  :func:`brave6d.core.transforms.nearest_rotation`, :data:`~brave6d.core.transforms.ROTATION_TOLERANCE`);
* **position + quaternion**: named keys are recognised by themselves: ``x y z qx qy qz qw``
  (ROS-Industrial's calibration files), ``position: {x, y, z}`` + ``orientation: {x, y, z, w}``
  (ROS ``geometry_msgs/Pose``), ``translation`` + ``rotation`` (ROS transforms). Seven bare
  numbers need the quaternion order, ``xyzw`` (ROS, scipy, Eigen's coefficients) or ``wxyz``
  (this project's code, Eigen's constructor, MATLAB): :class:`PoseFormat` ``quaternion_order``.
  A quaternion whose norm is off 1 by more than 1e-3 is refused; a smaller error is normalised
  (:func:`brave6d.core.transforms.unit_quaternion`);
* **UR pose vector** ``[x, y, z, rx, ry, rz]`` (rotation vector, radians; what a UR controller
  and ur-rtde's ``getActualTCPPose`` report): only with ``kind="ur"``, because six numbers (or keys
  ``rx ry rz``) are as often roll-pitch-yaw angles, which are not read.

A file holds one pose (:func:`read_pose_file`) or several (:func:`read_pose_collection`): one per
text line (or four lines of four numbers per matrix; a first column that is not a number is the
image's stem), an ``(N, 4, 4)``/``(N, k)`` array, a JSON/YAML list (or ``{"poses": [...]}``), or a
mapping from image stem to pose. Translations are metres unless ``unit="mm"``. Every problem is
one :class:`PoseFileError` naming the file (and the line or entry): NaN or inf, a missing or
ambiguous form, a bad quaternion or matrix.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.errors import DataError, NonRigidTransformError
from brave6d.core.json_input import read_json_file
from brave6d.core.npy_check import read_npy
from brave6d.core.transforms import nearest_rigid, unit_quaternion
from brave6d.core.yaml_io import read_yaml

__all__ = [
    "POSE_EXTENSIONS",
    "POSE_FORMATS",
    "QUATERNION_ORDERS",
    "PoseFileError",
    "PoseFormat",
    "read_pose_collection",
    "read_pose_file",
]

Array = NDArray[np.float64]
POSE_FORMATS = ("auto", "matrix", "quaternion", "ur")
QUATERNION_ORDERS = ("xyzw", "wxyz")
POSE_EXTENSIONS = (".txt", ".csv", ".npy", ".json", ".yaml", ".yml")
#: Pose files are small; larger ones are refused before they are read.
MAX_FILE_BYTES = 16 << 20
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(nan|inf|infinity)", re.IGNORECASE)


class PoseFileError(DataError):
    """A pose file that cannot be read as robot poses; the message names the file."""


@dataclass(frozen=True)
class PoseFormat:
    """How to read poses (see the module docstring): ``kind`` one of :data:`POSE_FORMATS`,
    ``quaternion_order`` one of :data:`QUATERNION_ORDERS` (needed for bare 7-number poses),
    ``unit`` of the translations, ``"m"`` or ``"mm"``."""

    kind: str = "auto"
    quaternion_order: str | None = None
    unit: str = "m"

    def __post_init__(self) -> None:
        if self.kind not in POSE_FORMATS:
            raise ValueError(f"pose format must be one of {POSE_FORMATS}, got {self.kind!r}")
        if self.quaternion_order is not None and self.quaternion_order not in QUATERNION_ORDERS:
            raise ValueError(f"quaternion order must be one of {QUATERNION_ORDERS}, got {self.quaternion_order!r}")
        if self.unit not in ("m", "mm"):
            raise ValueError(f"pose unit must be 'm' or 'mm', got {self.unit!r}")

    @property
    def scale(self) -> float:
        """Metres per unit of the files' translations."""
        return 1e-3 if self.unit == "mm" else 1.0


# ----------------------------------------------------------------------------- one pose from values
def _numbers(value: Any, where: str) -> Array:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise PoseFileError(f"{where}: expected numbers, got {_shown(value)}") from None
    if not np.all(np.isfinite(arr)):
        raise PoseFileError(f"{where}: contains NaN or inf")
    return arr


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _matrix(values: Array, where: str, fmt: PoseFormat) -> Array:
    T = np.eye(4)
    T[: values.size // 4] = values.reshape(-1, 4)
    try:
        T, _ = nearest_rigid(T, where)
    except NonRigidTransformError as exc:
        raise PoseFileError(f"{exc} (a 4x4 base_T_tcp, row-major, is expected)") from None
    T[:3, 3] *= fmt.scale
    return T


def _quaternion(position: Array, q: Array, order: str, where: str, fmt: PoseFormat) -> Array:
    try:
        unit = unit_quaternion(q, where, order)
    except NonRigidTransformError as exc:
        raise PoseFileError(str(exc)) from None
    xyzw = unit if order == "xyzw" else np.r_[unit[1:], unit[0]]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(xyzw).as_matrix()
    T[:3, 3] = position * fmt.scale
    return T


def _ur(values: Array, where: str, fmt: PoseFormat) -> Array:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(values[3:]).as_matrix()
    if not np.all(np.isfinite(T)):  # an angle so large that scipy's arithmetic overflows
        raise PoseFileError(f"{where}: rotation vector {np.asarray(values[3:]).tolist()} is too large to be read "
                            "as an angle in radians")
    T[:3, 3] = values[:3] * fmt.scale
    return T


def _from_array(values: Array, where: str, fmt: PoseFormat) -> Array:
    n = values.size
    if n in (16, 12) and values.shape in ((4, 4), (3, 4), (16,), (12,)) and fmt.kind in ("auto", "matrix"):
        return _matrix(values, where, fmt)
    if n == 7 and values.ndim == 1 and fmt.kind in ("auto", "quaternion"):
        if fmt.quaternion_order is None:
            raise PoseFileError(f"{where}: 7 numbers are a position and a quaternion, but in which order is the "
                                "quaternion? say it (--quaternion-order xyzw for ROS/scipy, wxyz for w first)")
        return _quaternion(values[:3], values[3:], fmt.quaternion_order, where, fmt)
    if n == 6 and values.ndim == 1:
        if fmt.kind == "ur":
            return _ur(values, where, fmt)
        raise PoseFileError(f"{where}: 6 numbers are ambiguous (UR's [x, y, z, rx, ry, rz] rotation vector, or "
                            "roll-pitch-yaw angles, which are not read); for a UR pose vector say --pose-format ur")
    wanted = {"auto": "16 (a 4x4 matrix), 7 (position + quaternion) or, with --pose-format ur, 6",
              "matrix": "16 (a 4x4 matrix) or 12 (its top three rows)",
              "quaternion": "7 (x y z and a quaternion)", "ur": "6 ([x, y, z, rx, ry, rz])"}[fmt.kind]
    raise PoseFileError(f"{where}: {n} numbers (shape {list(values.shape)}); a pose needs {wanted}")


def _keyed(d: dict[str, Any], keys: Sequence[str], where: str) -> Array:
    return _numbers([d[k] for k in keys], where)


def _vector3(value: Any, where: str) -> Array:
    if isinstance(value, dict):
        lower = {str(k).lower(): v for k, v in value.items()}
        if all(k in lower for k in "xyz"):
            return _keyed(lower, "xyz", where)
    arr = _numbers(value, where)
    if arr.shape != (3,):
        raise PoseFileError(f"{where}: expected a position (x, y, z), got {_shown(value)}")
    return arr


def _orientation(position: Array, value: Any, where: str, fmt: PoseFormat) -> Array:
    if isinstance(value, dict):
        lower = {str(k).lower(): v for k, v in value.items()}
        if all(k in lower for k in "xyzw"):
            return _quaternion(position, _keyed(lower, "xyzw", where), "xyzw", where, fmt)
        raise PoseFileError(f"{where}: orientation needs keys x, y, z, w, got {sorted(lower)}")
    arr = _numbers(value, where)
    if arr.shape == (3, 3):
        T = _matrix(np.r_[np.c_[arr, position], [[0.0, 0.0, 0.0, 1.0]]].reshape(-1), where, PoseFormat())
        T[:3, 3] *= fmt.scale
        return T
    if arr.shape == (4,):
        if fmt.quaternion_order is None:
            raise PoseFileError(f"{where}: a quaternion as a bare list of 4 numbers: say its order "
                                "(--quaternion-order xyzw or wxyz)")
        return _quaternion(position, arr, fmt.quaternion_order, where, fmt)
    raise PoseFileError(f"{where}: orientation must be a quaternion or a 3x3 rotation, got {_shown(value)}")


_WRAPPERS = ("pose", "matrix", "transform", "t", "base_t_tcp", "tcp_pose")


def _from_mapping(d: dict[str, Any], where: str, fmt: PoseFormat) -> Array | None:
    """The pose a mapping describes, or None when it describes none (it may map stems to poses)."""
    lower = {str(k).lower(): v for k, v in d.items()}
    if all(k in lower for k in ("x", "y", "z", "qx", "qy", "qz", "qw")):
        return _quaternion(_keyed(lower, "xyz", where), _keyed(lower, ("qx", "qy", "qz", "qw"), where), "xyzw",
                           where, fmt)
    if all(k in lower for k in ("x", "y", "z", "rx", "ry", "rz")):
        if fmt.kind != "ur":
            raise PoseFileError(f"{where}: keys x y z rx ry rz are ambiguous (UR's rotation vector, or roll-pitch-yaw "
                                "angles, which are not read); for a UR pose vector say --pose-format ur")
        return _ur(_keyed(lower, ("x", "y", "z", "rx", "ry", "rz"), where), where, fmt)
    for pos_key, rot_key in (("position", "orientation"), ("translation", "rotation")):
        if pos_key in lower and rot_key in lower:
            return _orientation(_vector3(lower[pos_key], where), lower[rot_key], where, fmt)
    for key in _WRAPPERS:
        if key in lower and len(lower) <= 3:
            return _pose(lower[key], where, fmt)
    return None


def _pose(value: Any, where: str, fmt: PoseFormat) -> Array:
    if isinstance(value, dict):
        pose = _from_mapping(value, where, fmt)
        if pose is None:
            raise PoseFileError(f"{where}: no pose found (keys {sorted(map(str, value))[:8]}); expected a 4x4 matrix, "
                                "x y z qx qy qz qw, position + orientation, or with --pose-format ur a pose vector")
        return pose
    return _from_array(_numbers(value, where), where, fmt)


# ----------------------------------------------------------------------------- files
def _load(path: Path) -> Any:
    """The parsed content: an array (npy), a JSON/YAML value, or the text's rows ``[(key, numbers)]``."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise PoseFileError(f"{path}: file not found") from None
    except OSError as exc:
        raise PoseFileError(f"{path}: cannot read ({exc.strerror})") from None
    if size > MAX_FILE_BYTES:
        raise PoseFileError(f"{path}: {size} bytes, more than a pose file holds ({MAX_FILE_BYTES} at most)")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            return read_npy(path, MAX_FILE_BYTES)  # the header checked before anything is allocated
        except DataError as exc:
            raise PoseFileError(str(exc)) from None
    if suffix in (".yaml", ".yml"):
        return read_yaml(path, error=PoseFileError)
    if suffix == ".json":
        try:
            return read_json_file(path)  # the one JSON reader: size, depth and number limits
        except DataError as exc:
            raise PoseFileError(str(exc)) from None
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise PoseFileError(f"{path}: cannot read as UTF-8 text ({exc})") from None
    return _text_rows(path, text)


def _text_rows(path: Path, text: str) -> list[tuple[str | None, int, Array]]:
    """``(key or None, line number, numbers)`` of each line with numbers; ``#`` starts a comment,
    a first line without numbers is a header (``x,y,z,qx,qy,qz,qw``), a first column that is not a
    number is the line's key (an image stem)."""
    rows: list[tuple[str | None, int, Array]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        tokens = [t for t in re.split(r"[\s,;\[\]]+", raw.split("#", 1)[0]) if t]
        if not tokens or (not rows and not any(_NUMBER.fullmatch(t) for t in tokens)):
            continue
        key = None
        if not _NUMBER.fullmatch(tokens[0]):
            key, tokens = tokens[0], tokens[1:]
        if not tokens or not all(_NUMBER.fullmatch(t) for t in tokens):
            raise PoseFileError(f"{path}:{lineno}: not a row of numbers: {raw.strip()[:80]!r}")
        rows.append((key, lineno, np.array([float(t) for t in tokens])))
    if not rows:
        raise PoseFileError(f"{path}: no numbers found")
    return rows


def _text_poses(path: Path, rows: list[tuple[str | None, int, Array]], fmt: PoseFormat
                ) -> list[tuple[str | None, str, Array]]:
    """``(key, where, pose)`` per pose of a text file: one per row, or one per four rows of four."""
    sizes = {len(v) for _, _, v in rows}
    if sizes == {4} and len(rows) % 4 == 0:  # matrices written as 4 lines of 4 numbers
        out = []
        for k in range(0, len(rows), 4):
            group = rows[k:k + 4]
            where = f"{path}:{group[0][1]}"
            out.append((group[0][0], where, _pose(np.stack([v for _, _, v in group]), where, fmt)))
        return out
    return [(key, f"{path}:{lineno}", _pose(v, f"{path}:{lineno}", fmt)) for key, lineno, v in rows]


def read_pose_file(path: Path | str, fmt: PoseFormat | None = None) -> Array:
    """The one robot pose ``base_T_tcp`` (metres) in ``path``; raises :class:`PoseFileError`."""
    poses = read_pose_collection(path, fmt)
    if isinstance(poses, dict) or len(poses) != 1:
        raise PoseFileError(f"{path}: {len(poses)} poses, expected one (a file per image)")
    return poses[0]


def read_pose_collection(path: Path | str, fmt: PoseFormat | None = None) -> list[Array] | dict[str, Array]:
    """Every robot pose in ``path``: a list in file order, or a mapping from image stem to pose
    when the file names them (a key column, or a JSON/YAML mapping of poses)."""
    p = Path(path)
    f = fmt or PoseFormat()
    content = _load(p)
    if isinstance(content, list) and content and isinstance(content[0], tuple):  # text rows
        poses = _text_poses(p, content, f)
        keys = [k for k, _, _ in poses]
        if all(k is not None for k in keys):
            return _unique({str(k): T for k, _, T in poses}, [str(k) for k in keys], p)
        if any(k is not None for k in keys):
            raise PoseFileError(f"{p}: some lines start with a name and some do not")
        return [T for _, _, T in poses]
    if isinstance(content, np.ndarray):
        arr = _numbers(content, str(p))
        if arr.ndim == 3 or (arr.ndim == 2 and arr.shape not in ((4, 4), (3, 4))):
            return [_pose(a, f"{p}: pose {k}", f) for k, a in enumerate(arr)]
        return [_pose(arr, str(p), f)]
    if isinstance(content, dict):
        single = _from_mapping(content, str(p), f)
        if single is not None:
            return [single]
        lower = {str(k).lower(): v for k, v in content.items()}
        if "poses" in lower and len(lower) == 1:
            content = lower["poses"]
        else:
            return {str(k): _pose(v, f"{p}: entry {k!r}", f) for k, v in content.items()}
    if isinstance(content, list):
        if content and all(isinstance(v, (int, float)) for v in content):
            return [_pose(content, str(p), f)]
        if len(content) in (3, 4) and all(isinstance(v, list) and len(v) == 4 for v in content):
            return [_pose(content, str(p), f)]  # one matrix as nested lists
        return [_pose(v, f"{p}: entry {k}", f) for k, v in enumerate(content)]
    raise PoseFileError(f"{p}: no poses found (got {type(content).__name__})")


def _unique(mapping: dict[str, Array], keys: list[str], path: Path) -> dict[str, Array]:
    if len(mapping) != len(keys):
        repeated = sorted({k for k in keys if keys.count(k) > 1})
        raise PoseFileError(f"{path}: names given twice: {repeated[:5]}")
    return mapping

"""Read a nerfstudio / instant-ngp ``transforms.json`` (the NeRF "Blender" layout and its descendants).

What the file holds, as those tools write it:

- ``frames``: ``file_path`` (relative to the file; may lack its extension, as the NeRF Blender
  scenes do) and ``transform_matrix``, camera-to-world with **OpenGL** camera axes (x right, y up,
  z backwards). The reader right-multiplies ``diag(1, -1, -1, 1)`` to get OpenCV axes.
- intrinsics shared at the top level or per frame (a frame's key wins): ``fl_x``, ``fl_y`` (else
  ``camera_angle_x`` / ``camera_angle_y``), ``cx``, ``cy`` (default: the image centre), ``w``,
  ``h`` (default: the image's size), distortion ``k1 k2 k3 k4 p1 p2`` and ``camera_model``
  (``OPENCV``, ``OPENCV_FISHEYE``, ``PINHOLE``, ``SIMPLE_PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL``; instant-ngp's
  ``is_fisheye: true`` means ``OPENCV_FISHEYE``). ``cx``/``cy`` are in the corner-origin convention
  (pixel (0, 0) centred at (0.5, 0.5)): nerfstudio copies COLMAP's, instant-ngp and nerfstudio cast
  rays through ``pixel + 0.5``. A perspective camera's radial terms are OpenCV's ``k1 k2 k3``;
  ``k4`` (nerfstudio's r^8 term) has no OpenCV equivalent and is refused.
- optional: ``ply_file_path`` (nerfstudio's sparse points, same world as the poses),
  ``applied_transform`` (nerfstudio's world change from COLMAP's, kept for the record), and
  instant-ngp's ``aabb_scale``, ``scale``, ``offset`` (how it maps the poses into its unit cube:
  ``p_ngp = cycle(p * scale + offset)``, axes cycled x->z, y->x, z->y). With no points, the centre of
  that unit cube is the scene's reference for the pose check.

Images resampled by a whole factor (nerfstudio's ``images_2/4/8`` convention, or photos shrunk in
place) are taken with the intrinsics scaled to them, and ``details["images_downscaled"]`` says so.
A frame whose image file is missing is reported in ``missing`` (by its ``file_path``), not an error.
Every path the file names (``file_path``, ``ply_file_path``) must lie inside the file's folder
(:func:`brave6d.core.names.contained_path`: no absolute path, no ``..``, no symbolic link); the
points file's header is checked before it is read and only its vertex rows are read, in one pass
(:func:`brave6d.core.ply_check.read_ply_vertices`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import read_json
from brave6d.core.errors import DataError, NonRigidTransformError
from brave6d.core.names import contained_path
from brave6d.core.ply_check import read_ply_vertices
from brave6d.core.png_check import check_image_header
from brave6d.core.transforms import nearest_rigid
from brave6d.training.importing.source import ImportedCapture, SourceCamera, SourceFrame, downscale_factor
from brave6d.training.pose_check import GL_TO_CV

_CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "camera_model",
                "camera_angle_x", "camera_angle_y", "is_fisheye")
_PERSPECTIVE = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
_FISHEYE = ("OPENCV_FISHEYE",)
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
#: instant-ngp's defaults for ``scale`` and ``offset``.
NGP_SCALE, NGP_OFFSET = 0.33, (0.5, 0.5, 0.5)


def find_transforms(source: Path) -> Path:
    """``source`` itself when it is a file, else ``source/transforms.json``."""
    path = contained_path(source, "transforms.json", str(source)) if source.is_dir() else source
    if not path.is_file():
        raise DataError(f"{path}: not found (a transforms.json file, or a folder that holds one)")
    return path


def read_transforms(source: Path | str) -> ImportedCapture:
    """Frames, cameras, poses (OpenCV axes) and points of a ``transforms.json`` (see the module docstring)."""
    path = find_transforms(Path(source))
    data = read_json(path)  # the one JSON reader: size, depth and number limits
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object at the top level, got {type(data).__name__}")
    listed = data.get("frames")
    if not isinstance(listed, list) or not listed:
        raise DataError(f"{path}: field 'frames': a non-empty list of frames is required")
    frames, missing = [], []
    downscaled: dict[int, int] = {}  # factor -> frames whose images are resampled copies
    shared = {k: data[k] for k in _CAMERA_KEYS if k in data}
    for i, item in enumerate(listed):
        where = f"{path}: field 'frames[{i}]'"
        if not isinstance(item, dict):
            raise DataError(f"{where}: an object is required, got {type(item).__name__}")
        name = item.get("file_path")
        if not isinstance(name, str) or not name:
            raise DataError(f"{where}.file_path: a file path (string) is required")
        image = _image_file(path.parent, name, f"{where}.file_path")
        if image is None:
            missing.append(name)
            continue
        camera = _camera({**shared, **{k: item[k] for k in _CAMERA_KEYS if k in item}}, image, f"{where} ({name})")
        camera, factor = _fit_to_image(camera, image)
        if factor > 1:
            downscaled[factor] = downscaled.get(factor, 0) + 1
        pose, correction = _pose(item.get("transform_matrix"), f"{where} ({name})")
        frames.append(SourceFrame(name, image, camera, pose, correction))
    points, colors, points_from = _points(path, data)
    details: dict[str, Any] = {k: data[k] for k in ("aabb_scale", "scale", "offset", "applied_transform") if k in data}
    if downscaled:
        details["images_downscaled"] = "; ".join(
            f"{n} frames' images are 1/{k} of the size the file describes: their intrinsics were scaled by 1/{k}"
            for k, n in sorted(downscaled.items()))
    with_depth = sum(1 for f in listed if isinstance(f, dict) and ("depth_file_path" in f or "depth_path" in f))
    if with_depth:
        details["depth_not_imported"] = f"{with_depth} frames list a depth map; depth is not imported (RGB only)"
    return ImportedCapture("transforms.json", path, frames, missing, points, colors, points_from,
                           _ngp_unit_cube(data, path), details)


def _image_file(root: Path, name: str, where: str) -> Path | None:
    """The image ``name`` inside ``root`` (:func:`brave6d.core.names.contained_path`: no ``..``, no
    absolute path, no link); a name without an extension tries the usual ones."""
    path = contained_path(root, name, where)
    if path.is_file():
        return path
    if not path.suffix:
        for suffix in _IMAGE_SUFFIXES:
            candidate = contained_path(root, name + suffix, where)
            if candidate.is_file():
                return candidate
    return None


def _number(values: dict[str, Any], key: str, where: str, default: float | None = None) -> float:
    value = values.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DataError(f"{where}: field '{key}': a finite number is required, got {value!r}")
    return float(value)


def _camera(values: dict[str, Any], image: Path, where: str) -> SourceCamera:
    """The frame's camera from its merged keys (see the module docstring)."""
    if "w" in values and "h" in values:
        w, h = _number(values, "w", where), _number(values, "h", where)
        if not (w.is_integer() and h.is_integer() and w >= 1 and h >= 1):
            raise DataError(f"{where}: fields 'w', 'h': whole numbers of pixels are required, got {w}, {h}")
        width, height = int(w), int(h)
    else:
        width, height = _image_size(image)
    if "fl_x" in values:
        fx = _number(values, "fl_x", where)
    elif "camera_angle_x" in values:
        fx = 0.5 * width / math.tan(0.5 * _angle(values, "camera_angle_x", where))
    else:
        raise DataError(f"{where}: no focal length: give 'fl_x' or 'camera_angle_x'")
    if "fl_y" in values:
        fy = _number(values, "fl_y", where)
    elif "camera_angle_y" in values:
        fy = 0.5 * height / math.tan(0.5 * _angle(values, "camera_angle_y", where))
    else:
        fy = fx
    cx = _number(values, "cx", where, width / 2.0)
    cy = _number(values, "cy", where, height / 2.0)
    k = {key: _number(values, key, where, 0.0) for key in ("k1", "k2", "k3", "k4", "p1", "p2")}
    model = values.get("camera_model")
    if model is None:
        model = "OPENCV_FISHEYE" if values.get("is_fisheye") is True else "OPENCV"
    if model in _FISHEYE:
        if k["p1"] or k["p2"]:
            raise DataError(f"{where}: OPENCV_FISHEYE has no tangential terms, but p1/p2 are {k['p1']}/{k['p2']}")
        return _source_camera("OPENCV_FISHEYE", width, height, (fx, fy, cx, cy, k["k1"], k["k2"], k["k3"], k["k4"]), where)
    if model not in _PERSPECTIVE:
        raise DataError(f"{where}: field 'camera_model': {model!r} is not supported "
                        f"(supported: {', '.join(_PERSPECTIVE + _FISHEYE)})")
    if k["k4"]:
        raise DataError(f"{where}: field 'k4' = {k['k4']} on a perspective camera (nerfstudio's r^8 radial term) "
                        "has no OpenCV equivalent; undistort the images first")
    if k["k3"]:
        return _source_camera("FULL_OPENCV", width, height,
                              (fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"], k["k3"], 0.0, 0.0, 0.0), where)
    return _source_camera("OPENCV", width, height, (fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"]), where)


def _fit_to_image(camera: SourceCamera, image: Path) -> tuple[SourceCamera, int]:
    """The camera for the image file as it is: when the file is a copy resampled by a whole factor
    (:func:`.source.downscale_factor`, e.g. nerfstudio's ``images_4`` or photos shrunk in place),
    the file's ``w``/``h`` and intrinsics describe the originals and are scaled to the copy. Any other
    size is left for the image reader to refuse, naming the frame and both sizes."""
    size = _image_size(image)
    factor = downscale_factor(camera, size)
    if factor is None or factor == 1:
        return camera, 1
    return camera.scaled_to(*size), factor


def _source_camera(model: str, width: int, height: int, params: tuple[float, ...], where: str) -> SourceCamera:
    try:
        return SourceCamera(model, width, height, params)
    except DataError as exc:
        raise DataError(f"{where}: {exc}") from None


def _angle(values: dict[str, Any], key: str, where: str) -> float:
    angle = _number(values, key, where)
    if not 0.0 < angle < math.pi:
        raise DataError(f"{where}: field '{key}': a field of view in (0, pi) radians is required, got {angle}")
    return angle


def _image_size(image: Path) -> tuple[int, int]:
    """(width, height) as stored in the file (EXIF orientation not applied: what w/h would describe),
    from its header; one held to the pixel limit (:func:`brave6d.core.png_check.check_image_header`)."""
    return check_image_header(image)


def _pose(value: Any, where: str) -> tuple[NDArray[np.float64], float]:
    """``world_T_cam`` with OpenCV axes from an OpenGL camera-to-world ``transform_matrix`` (4x4 or 3x4),
    its rotation projected onto the nearest rotation (:func:`brave6d.core.transforms.nearest_rigid`:
    the files carry rounding), and the correction that made."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}.transform_matrix: a 4x4 matrix of numbers is required") from None
    if m.shape not in ((3, 4), (4, 4)):
        raise DataError(f"{where}.transform_matrix: a 4x4 (or 3x4) matrix is required, got shape {m.shape}")
    try:
        T, correction = nearest_rigid(m, f"{where}.transform_matrix")
    except NonRigidTransformError as exc:
        raise DataError(str(exc)) from None
    return T @ GL_TO_CV, correction


def _points(path: Path, data: dict[str, Any]) -> tuple[NDArray[np.float64], NDArray[np.uint8], str | None]:
    """nerfstudio's ``ply_file_path`` points (x, y, z and red, green, blue when present)."""
    name = data.get("ply_file_path")
    if name is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), None
    if not isinstance(name, str):
        raise DataError(f"{path}: field 'ply_file_path': a file path (string) is required")
    ply = contained_path(path.parent, name, f"{path}: field 'ply_file_path'")
    if not ply.is_file():
        raise DataError(f"{path}: field 'ply_file_path': {ply} not found")
    vertex = read_ply_vertices(ply)  # the header against the file, then the vertex rows alone, in one pass
    if not all(c in vertex for c in ("x", "y", "z")):
        raise DataError(f"{ply}: not a point cloud PLY with x, y, z (its vertices hold {', '.join(vertex) or 'nothing'})")
    xyz = np.stack([np.asarray(vertex[c], np.float64) for c in ("x", "y", "z")], axis=1)
    if all(c in vertex for c in ("red", "green", "blue")):
        rgb = np.stack([np.asarray(vertex[c]) for c in ("red", "green", "blue")], axis=1).clip(0, 255).astype(np.uint8)
    else:
        rgb = np.full((len(xyz), 3), 128, np.uint8)
    return xyz, rgb, name


def _ngp_unit_cube(data: dict[str, Any], path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """instant-ngp's unit cube in the file's coordinates, when the file carries its keys."""
    if not any(k in data for k in ("aabb_scale", "scale", "offset")):
        return None
    scale = _number(data, "scale", str(path), NGP_SCALE)
    if scale <= 0:
        raise DataError(f"{path}: field 'scale': instant-ngp's scale must be positive, got {scale}")
    offset = data.get("offset", list(NGP_OFFSET))
    if not (isinstance(offset, list) and len(offset) == 3):
        raise DataError(f"{path}: field 'offset': three numbers are required, got {offset!r}")
    off = np.array([_number({"offset": v}, "offset", str(path)) for v in offset])
    # p_ngp = (y, z, x) * scale + offset: file x <- ngp z, file y <- ngp x, file z <- ngp y
    per_axis = np.array([off[2], off[0], off[1]])
    return (0.0 - per_axis) / scale, (1.0 - per_axis) / scale

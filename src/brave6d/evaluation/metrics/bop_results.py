"""BOP files on the evaluation side: the results CSV (read/write, owned here) and the ground truth
of BOP scene and model folders as scoring inputs (the dataset files themselves are parsed by
:mod:`annotation`, the owner of the BOP dataset format).

BOP units: millimetres (``cam_t_m2c``, model vertices, ``t`` of the results), depth images in
units of ``depth_scale`` mm. Formats (bop_toolkit ``docs/bop_datasets_format.md`` and
``docs/bop_challenge_2019.md``):

- Results CSV: header ``scene_id,im_id,obj_id,score,R,t,time``; ``R`` is 9 values row-major,
  ``t`` 3 values in mm, both space-separated; ``time`` in seconds (-1 = unknown), the same for
  every estimate of one image.
- Scene folder ``{split}/{scene_id:06d}/``: ``scene_camera.json`` (``cam_K``, ``depth_scale``),
  ``scene_gt.json`` (``cam_R_m2c``, ``cam_t_m2c``, ``obj_id``), ``scene_gt_info.json``
  (``visib_fract``, ...), ``depth/{im_id:06d}.png`` (uint16).
- Models folder: ``models_info.json`` (``diameter``, symmetries) and ``obj_{obj_id:06d}.ply``.

Every error a user can cause is a :class:`brave6d.core.errors.DataError` naming the file (and the
line of a CSV, or the image/instance of a JSON file).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.annotation import dataset_image_size, model_file, read_models_info, read_scene_camera, read_scene_gt, read_scene_gt_info
from brave6d.core.atomic import atomic_write_text, read_png
from brave6d.core.errors import DataError
from brave6d.core.png_check import check_image_header
from brave6d.evaluation.metrics.recall import Estimate, GTInstance, ObjectModel

RESULTS_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
#: Largest ``|R^T R - I|`` accepted for a rotation read from a results CSV (values are often
#: written with few digits, so this only catches matrices that are clearly not rotations).
ROTATION_TOLERANCE = 1e-2


# ----------------------------------------------------------------------------- results CSV
def format_results_csv(estimates: Iterable[Estimate]) -> str:
    """The BOP results CSV text (header + one line per estimate; floats round-trip exactly)."""
    lines = [RESULTS_HEADER]
    for e in estimates:
        R = " ".join(repr(float(x)) for x in np.asarray(e.R, dtype=np.float64).reshape(-1))
        t = " ".join(repr(float(x)) for x in np.asarray(e.t, dtype=np.float64).reshape(-1))
        lines.append(f"{int(e.scene_id)},{int(e.im_id)},{int(e.obj_id)},{float(e.score)!r},{R},{t},{float(e.time)!r}")
    return "\n".join(lines) + "\n"


def write_bop_results(path: Path | str, estimates: Iterable[Estimate]) -> Path:
    """Write a BOP results CSV atomically. Name it ``METHOD_DATASET-SPLIT.csv`` for the BOP server."""
    ests = list(estimates)
    for e in ests:
        values = np.concatenate([np.ravel(e.R), np.ravel(e.t), [e.score, e.time]])
        if not np.all(np.isfinite(values)):
            raise DataError(f"{path}: estimate (scene {e.scene_id}, image {e.im_id}, object {e.obj_id}) has NaN or inf")
    return atomic_write_text(path, format_results_csv(ests))


def _parse_floats(text: str, count: int, field: str, where: str) -> NDArray[np.float64]:
    parts = text.split()
    if len(parts) != count:
        raise DataError(f"{where}: {field} must have {count} space-separated numbers, got {len(parts)}: {text.strip()!r}")
    try:
        arr = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise DataError(f"{where}: {field} has a non-numeric value: {text.strip()!r}") from None
    if not np.all(np.isfinite(arr)):
        raise DataError(f"{where}: {field} contains NaN or inf: {text.strip()!r}")
    return arr


def _parse_int(text: str, field: str, where: str) -> int:
    try:
        return int(text.strip())
    except ValueError:
        raise DataError(f"{where}: {field} must be an integer, got {text.strip()!r}") from None


def _parse_float(text: str, field: str, where: str) -> float:
    try:
        value = float(text.strip())
    except ValueError:
        raise DataError(f"{where}: {field} must be a number, got {text.strip()!r}") from None
    if not math.isfinite(value):
        raise DataError(f"{where}: {field} must be finite, got {text.strip()!r}")
    return value


def parse_results_line(line: str, where: str, check_rotation: bool = True) -> Estimate:
    """One CSV data line -> :class:`Estimate`; ``where`` (e.g. ``file:line``) prefixes errors."""
    elems = line.rstrip("\r\n").split(",")
    if len(elems) != 7:
        raise DataError(
            f"{where}: expected 7 comma-separated fields ({RESULTS_HEADER}), got {len(elems)}: {line.strip()!r}"
        )
    scene_id = _parse_int(elems[0], "scene_id", where)
    im_id = _parse_int(elems[1], "im_id", where)
    obj_id = _parse_int(elems[2], "obj_id", where)
    score = _parse_float(elems[3], "score", where)
    R = _parse_floats(elems[4], 9, "R", where).reshape(3, 3)
    t = _parse_floats(elems[5], 3, "t", where)
    time = _parse_float(elems[6], "time", where)
    if check_rotation:
        orth = float(np.max(np.abs(R.T @ R - np.eye(3))))
        det = float(np.linalg.det(R))
        if orth > ROTATION_TOLERANCE or det <= 0:
            raise DataError(f"{where}: R is not a rotation matrix (max |R^T R - I| = {orth:.3g}, det = {det:.3g})")
    return Estimate(scene_id, im_id, obj_id, score, R, t, time)


def read_bop_results(path: Path | str, check_rotation: bool = True) -> list[Estimate]:
    """Read a BOP results CSV. The header line is optional (as in bop_toolkit); blank lines are
    skipped. Errors name the file and the line number."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError(f"{p}: results file not found") from None
    except UnicodeDecodeError as exc:
        raise DataError(f"{p}: not a UTF-8 text file ({exc})") from None
    out: list[Estimate] = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        if line_no == 1 and RESULTS_HEADER in line.replace(" ", ""):
            continue
        if not line.strip():
            continue
        out.append(parse_results_line(line, f"{p}:{line_no}", check_rotation))
    return out


def check_times(estimates: Iterable[Estimate], tolerance_s: float = 0.001) -> None:
    """Raise when the estimates of one image report different run times (BOP requires one
    time per image)."""
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        key = (int(e.scene_id), int(e.im_id))
        if key in times and abs(times[key] - e.time) > tolerance_s:
            raise DataError(
                f"scene {key[0]} image {key[1]}: estimates report different run times ({times[key]} s and {e.time} s); "
                "BOP needs one time per image"
            )
        times.setdefault(key, e.time)


# ----------------------------------------------------------------------------- scenes
def _depth_loader(path: Path, depth_scale: float, size: tuple[int, int]) -> Callable[[], NDArray[np.float64]]:
    def load() -> NDArray[np.float64]:
        return read_png(path, "depth", size, "the scene's image size").astype(np.float64) * depth_scale

    return load


def _image_size_of(scene_dir: Path, im_ids: Sequence[int]) -> tuple[int, int] | None:
    size = dataset_image_size(scene_dir.parent.parent)
    if size is not None:
        return size
    for im_id in im_ids[:1]:
        for sub, ext in (("depth", "png"), ("rgb", "png"), ("rgb", "jpg"), ("gray", "png")):
            f = scene_dir / sub / f"{im_id:06d}.{ext}"
            if f.is_file():
                return check_image_header(f)  # the size from the header: nothing decoded
    return None


def load_scene_gt_instances(
    scene_dir: Path | str,
    scene_id: int | None = None,
    image_size: tuple[int, int] | None = None,
    with_depth: bool = True,
) -> list[GTInstance]:
    """All GT instances of one BOP scene folder, in image order then ``scene_gt`` order.

    ``scene_id`` defaults to the folder name (``000001`` -> 1). The image size comes from
    ``image_size``, else the dataset's ``camera.json`` two levels up, else the first depth/RGB
    image. With ``with_depth`` each instance gets a lazy loader of ``depth/{im_id:06d}.png``
    (scaled by ``depth_scale`` to mm), read only when VSD needs it.
    """
    d = Path(scene_dir)
    if not d.is_dir():
        raise DataError(f"{d}: scene folder not found")
    if scene_id is None:
        if not re.fullmatch(r"\d+", d.name):
            raise DataError(f"{d}: folder name is not a scene id; pass scene_id")
        scene_id = int(d.name)
    # VSD reads the depth: its unit is never guessed
    cams = read_scene_camera(d / "scene_camera.json", require_depth_scale=with_depth and (d / "depth").is_dir())
    gt = read_scene_gt(d / "scene_gt.json")
    info = read_scene_gt_info(d / "scene_gt_info.json")
    im_ids = sorted(gt)
    size = image_size or _image_size_of(d, im_ids)
    if size is None:
        raise DataError(f"{d}: cannot tell the image size (no camera.json with width/height, no images); pass image_size")
    out: list[GTInstance] = []
    for im_id in im_ids:
        if im_id not in cams:
            raise DataError(f"{d / 'scene_camera.json'}: no entry for image {im_id} of scene_gt.json")
        if im_id not in info:
            raise DataError(f"{d / 'scene_gt_info.json'}: no entry for image {im_id} of scene_gt.json")
        if len(info[im_id]) != len(gt[im_id]):
            raise DataError(
                f"{d / 'scene_gt_info.json'}: image {im_id} has {len(info[im_id])} entries, scene_gt.json has {len(gt[im_id])}"
            )
        cam = cams[im_id]
        depth = _depth_loader(d / "depth" / f"{im_id:06d}.png", cam.depth_scale, size) if with_depth else None
        for g, gi in zip(gt[im_id], info[im_id]):
            out.append(GTInstance(scene_id, im_id, g.obj_id, g.cam_R_m2c, g.cam_t_m2c, gi.visib_fract, cam.cam_K, size,
                                  depth))
    return out


def load_split_gt_instances(split_dir: Path | str, image_size: tuple[int, int] | None = None, with_depth: bool = True) -> list[GTInstance]:
    """GT instances of every scene folder (six-digit names) of a BOP split folder (e.g. ``test``)."""
    from brave6d.annotation import split_scene_folders

    scenes = split_scene_folders(split_dir)
    out: list[GTInstance] = []
    for s in scenes:
        out.extend(load_scene_gt_instances(s, int(s.name), image_size, with_depth))
    return out


# ----------------------------------------------------------------------------- models
def load_ply_mesh(path: Path | str) -> tuple[NDArray[np.float64], NDArray[np.int64] | None]:
    """Vertices (N, 3) and triangle faces (M, 3) (None for a point cloud) of a model PLY, unchanged."""
    from brave6d.annotation import read_ply_mesh

    mesh = read_ply_mesh(path)
    return mesh.vertices, (mesh.faces if len(mesh.faces) else None)


def load_models(
    models_dir: Path | str,
    obj_ids: Iterable[int] | None = None,
    models_info: Mapping[int, Mapping[str, Any]] | None = None,
) -> dict[int, ObjectModel]:
    """Object models of a BOP ``models`` folder: ``obj_{id:06d}.ply`` (mm) + ``models_info.json``."""
    d = Path(models_dir)
    info = dict(models_info) if models_info is not None else read_models_info(d / "models_info.json")
    ids = sorted(info) if obj_ids is None else [int(i) for i in obj_ids]
    out: dict[int, ObjectModel] = {}
    for obj_id in ids:
        if obj_id not in info:
            raise DataError(f"{d / 'models_info.json'}: no entry for object {obj_id}")
        vertices, faces = load_ply_mesh(model_file(d, obj_id))
        try:
            out[obj_id] = ObjectModel.from_models_info(obj_id, vertices, info[obj_id], faces)
        except DataError as exc:
            raise DataError(f"{d / 'models_info.json'}: {exc}") from None
    return out

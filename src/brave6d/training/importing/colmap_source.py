"""Read a COLMAP model (``cameras``, ``images``, ``points3D``; binary or text) and its images folder.

pycolmap reads the model (the format's own reader, binary or text alike). COLMAP's poses are
``cam_from_world`` with OpenCV camera axes, its cameras already in :class:`SourceCamera`'s terms, so
nothing is converted but the pose's direction. Only registered images (with a pose) become frames;
an image the model names but the images folder lacks is reported in ``missing``. An image name is
a path inside the images folder (:func:`brave6d.core.names.contained_path`: no absolute name, no
``..``, no symbolic link).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from brave6d.core.errors import DataError, NonRigidTransformError
from brave6d.core.names import contained_path
from brave6d.core.transforms import invert, nearest_rigid
from brave6d.training.importing.source import CAMERA_MODELS, ImportedCapture, SourceCamera, SourceFrame

_MODEL_FILES = ("cameras", "images", "points3D")


def is_colmap_model(folder: Path) -> bool:
    """Whether ``folder`` holds a COLMAP model (``cameras.bin`` + ``images.bin`` or the ``.txt`` pair)."""
    return any(all((folder / f"{name}{ext}").is_file() for name in ("cameras", "images")) for ext in (".bin", ".txt"))


def find_model(source: Path) -> Path:
    """The model folder of ``source``: itself, or ``sparse/0``, ``sparse`` or ``colmap/sparse/0`` inside it
    (none of them, nor a model file in it, a symbolic link: :func:`brave6d.core.names.contained_path`)."""
    for rel in ("", "sparse/0", "sparse", "colmap/sparse/0"):
        folder = contained_path(source, rel, f"{source}: the COLMAP model folder") if rel else source
        if is_colmap_model(folder):
            for name in _MODEL_FILES:
                for ext in (".bin", ".txt"):
                    contained_path(folder, name + ext, f"{folder}: the COLMAP model file")
            return folder
    raise DataError(f"{source}: no COLMAP model (cameras.bin and images.bin, or cameras.txt and images.txt) "
                    "in it or in its sparse/0, sparse or colmap/sparse/0")


def find_images(source: Path, model: Path) -> Path:
    """The images folder: ``<source>/images``, else ``images`` next to the model's ``sparse`` folder."""
    candidates = list(dict.fromkeys([source / "images", model.parent.parent / "images", model.parent / "images"]))
    for folder in candidates:
        if folder.is_symlink():
            raise DataError(f"{folder}: the images folder is a symbolic link; an import reads only its source's "
                            "own files: put the folder itself there, or name it with --images")
        if folder.is_dir():
            return folder
    raise DataError(f"{source}: no images folder found (looked in {', '.join(str(c) for c in candidates)}); "
                    "name it with --images")


def read_colmap(source: Path | str, images: Path | str | None = None) -> ImportedCapture:
    """The registered images of the COLMAP model at ``source`` with their cameras, poses and points."""
    import pycolmap

    source = Path(source)
    model = find_model(source)
    image_dir = Path(images) if images is not None else find_images(source, model)
    if not image_dir.is_dir():
        raise DataError(f"{image_dir}: images folder not found")
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises RuntimeError/ValueError with its own text
        raise DataError(f"{model}: pycolmap cannot read this COLMAP model ({exc})") from None
    cameras: dict[int, SourceCamera] = {}
    for camera_id, cam in rec.cameras.items():
        name = cam.model.name
        if name not in CAMERA_MODELS:
            raise DataError(f"{model}: camera {camera_id} has model {name}, which the importer does not support "
                            f"(supported: {', '.join(CAMERA_MODELS)})")
        try:
            cameras[camera_id] = SourceCamera(name, int(cam.width), int(cam.height), tuple(float(v) for v in cam.params))
        except DataError as exc:
            raise DataError(f"{model}: camera {camera_id}: {exc}") from None
    frames, missing = [], []
    for image_id in sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name):
        image = rec.images[image_id]
        path = contained_path(image_dir, image.name, f"{model}: image {image_id}: name")
        if not path.is_file():
            missing.append(image.name)
            continue
        cam_T_world = np.eye(4)
        cam_T_world[:3, :4] = image.cam_from_world().matrix()
        if not np.isfinite(cam_T_world).all():
            raise DataError(f"{model}: image {image.name}: pose is not finite")
        try:  # a normalised quaternion is a rotation to the last digit; the rule is the same for every source
            cam_T_world, correction = nearest_rigid(cam_T_world, f"{model}: image {image.name}: pose")
        except NonRigidTransformError as exc:
            raise DataError(str(exc)) from None
        frames.append(SourceFrame(image.name, path, cameras[image.camera_id], invert(cam_T_world), correction))
    ids = sorted(rec.point3D_ids())
    points = np.array([rec.points3D[i].xyz for i in ids], np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[i].color for i in ids], np.uint8).reshape(-1, 3)
    unregistered = sorted(rec.images[i].name for i in rec.images if i not in set(rec.reg_image_ids()))
    details = {"model": str(model), "images": str(image_dir), "cameras": len(cameras),
               "registered_images": len(rec.reg_image_ids()), "unregistered_images": unregistered}
    return ImportedCapture("colmap", source, frames, missing, points, colors,
                           f"points3D of {model}" if ids else None, None, details)

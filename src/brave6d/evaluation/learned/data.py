"""A BOP ``train_pbr`` split as the learned estimator's training data, read once into memory.

Each image is resized to the preset's working width (K scaled, pixel centres kept). Each object
instance keeps its visible box and, inside a margin around its full box, its **model coordinates**
per pixel: the model is ray-cast at the ground-truth pose (Open3D), so the coordinates are exact,
not back-projected from the quantised, noisy depth. For a symmetric object the pose is first
mapped to its canonical member (the symmetric pose nearest the identity rotation, as GDR-Net
does), so two images that look alike never ask for different coordinates.

Every ``heldout_every``-th image (in split order) is held out: never trained on, scored by
:mod:`brave6d.evaluation.learned.heldout`.
"""

from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError

log = logging.getLogger(__name__)
Array = NDArray[np.float64]

#: Instances less visible than this are not trained on nor scored (BOP19's threshold).
MIN_VISIB_FRACT = 0.1
#: Symmetric poses tried per continuous symmetry axis (5 degree steps).
CONTINUOUS_STEP_RAD = math.radians(5.0)
_REGION_MARGIN = 0.25


@dataclass(frozen=True)
class ObjectInfo:
    """A library object as the estimator knows it (mm): its class index, the centre and radius that
    normalise its coordinates to [-1, 1], its diameter and symmetries (``R`` (S, 3, 3), ``t`` (S, 3))."""

    obj_id: int
    class_index: int
    centre_mm: Array
    radius_mm: float
    diameter_mm: float
    sym_R: Array
    sym_t: Array
    vertices_mm: Array
    faces: NDArray[np.int64]

    def canonical(self, R: Array, t_mm: Array) -> tuple[Array, Array, int]:
        """The symmetric pose of ``(R, t)`` nearest the identity rotation, and the symmetry's index."""
        s = int(np.argmax(np.einsum("ij,sji->s", R, self.sym_R)))  # max trace(R R_s)
        return R @ self.sym_R[s], R @ self.sym_t[s] + t_mm, s


@dataclass
class Instance:
    """One annotated object in one image. ``R``, ``t_mm``: its pose as ``scene_gt.json`` gives it (what
    BOP scores against; the coordinates are of its canonical symmetric pose). ``box``: visible box
    (x0, y0, x1, y1; pixel edges) in the detector's working resolution, ``box_crop`` in the crops'
    source resolution, where ``region`` ((x0, y0) of ``coords`` / ``mask``), ``coords`` (normalised
    canonical model coordinates, (h, w, 3) float16) and ``mask`` (visible pixels of the object) lie too."""

    image: int
    obj_id: int
    class_index: int
    R: Array
    t_mm: Array
    visib_fract: float
    box: tuple[float, float, float, float]
    region: tuple[int, int]
    coords: NDArray[np.float16]
    mask: NDArray[np.bool_]
    box_crop: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


@dataclass
class ImageRecord:
    """One image: where it came from, the detector's working-resolution RGB and K, the crops' source
    RGB and K (``rgb_crop``, ``K_crop``), the original K and size (scores use them), whether it is
    held out, and its instances' indices."""

    scene_id: int
    im_id: int
    rgb: NDArray[np.uint8]
    K: Array
    K_full: Array
    size_full: tuple[int, int]
    heldout: bool
    depth_path: Path
    rgb_crop: NDArray[np.uint8]
    K_crop: Array
    instances: list[int] = field(default_factory=list)
    depth_scale: float = 1.0  # mm per unit of the depth PNG (the image's scene_camera.json entry)

    def read_depth_mm(self) -> Array:
        """The image's depth in mm (its PNG times its ``depth_scale``)."""
        from brave6d.annotation import read_depth_mm

        return read_depth_mm(self.depth_path, self.depth_scale)


@dataclass
class TrainingData:
    """Images, instances and objects of one train_pbr split (see the module docstring)."""

    root: Path
    images: list[ImageRecord]
    instances: list[Instance]
    objects: dict[int, ObjectInfo]
    digest: str

    @property
    def classes(self) -> list[int]:
        """obj_ids in class-index order."""
        return sorted(self.objects, key=lambda o: self.objects[o].class_index)

    def split(self, heldout: bool) -> list[int]:
        """Indices of the training (``heldout=False``) or held-out images."""
        return [i for i, im in enumerate(self.images) if im.heldout == heldout]

    def instances_of(self, heldout: bool) -> list[int]:
        return [k for k, inst in enumerate(self.instances) if self.images[inst.image].heldout == heldout]


def load_objects(models_dir: Path | str, obj_ids: list[int] | None = None) -> dict[int, ObjectInfo]:
    """The objects of a BOP ``models`` folder (``models_info.json`` + ``obj_XXXXXX.ply``, mm)."""
    from brave6d.evaluation.metrics import load_models

    models = load_models(models_dir, obj_ids)
    out: dict[int, ObjectInfo] = {}
    for k, obj_id in enumerate(sorted(models)):
        m = models[obj_id]
        if m.faces is None:
            raise DataError(f"{models_dir}: model of object {obj_id} has no faces (a mesh is needed to ray-cast it)")
        lo, hi = m.points.min(axis=0), m.points.max(axis=0)
        centre = (lo + hi) / 2.0
        radius = float(np.linalg.norm(m.points - centre, axis=1).max())
        if not radius > 0:
            raise DataError(f"{models_dir}: model of object {obj_id} is a single point")
        syms = m.symmetries(CONTINUOUS_STEP_RAD)
        out[obj_id] = ObjectInfo(obj_id, k, centre, radius, m.diameter, syms.R, syms.t, m.points, m.faces)
    return out


def split_digest(root: Path | str) -> tuple[str, int]:
    """SHA-256 over every file of a train_pbr folder (relative path and content digest), and the image count."""
    from brave6d.core.atomic import file_sha256

    root = Path(root)
    h = hashlib.sha256()
    count = 0
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(f"{p.relative_to(root).as_posix()}\0{file_sha256(p)}\n".encode())
            count += p.parent.name == "rgb"
    return h.hexdigest(), count


def scene_folders(root: Path | str) -> list[Path]:
    """The six-digit scene folders of a train_pbr split (``root`` is the split, or holds ``train_pbr/``)."""
    root = Path(root)
    if (root / "train_pbr").is_dir():
        root = root / "train_pbr"
    if not root.is_dir():
        raise DataError(f"{root}: train_pbr folder not found")
    from brave6d.annotation import split_scene_folders

    return split_scene_folders(root, "; render one with 'brave6d synth'")


def load_training_data(train_pbr: Path | str, models_dir: Path | str, work_width: int, heldout_every: int,
                       max_images: int | None = None, show_progress: bool = True,
                       crop_width: int | None = None) -> TrainingData:
    """Read ``train_pbr`` (through annotation's BOP split reader: JPEG or PNG ``rgb/``, depth by
    each image's ``depth_scale``) and the models (see the module docstring); ``max_images`` reads
    the first n only; ``crop_width``: the crops' source width (default ``work_width``)."""
    from brave6d.annotation import read_split_scene
    from brave6d.core.progress import progress

    scenes = scene_folders(train_pbr)
    root = scenes[0].parent
    objects = load_objects(models_dir)
    entries = [image for folder in scenes for image in read_split_scene(folder)]
    if max_images is not None:
        entries = entries[:max_images]
    unknown = sorted({g.obj_id for image in entries for g in image.gts} - set(objects))
    if unknown:
        raise DataError(f"{train_pbr}: objects {unknown} appear in scene_gt but have no model in {models_dir}")
    digest, _ = split_digest(root)
    casters = _Casters(objects)
    data = TrainingData(root, [], [], objects, digest)
    for n, image in enumerate(progress(entries, total=len(entries), desc="learn: read", unit="img",
                                       disable=not show_progress)):
        _add_image(data, casters, image, work_width, crop_width or work_width,
                   heldout=(n % heldout_every == heldout_every - 1))
    if not data.instances_of(False):
        raise DataError(f"{train_pbr}: no object instance at least {MIN_VISIB_FRACT:.0%} visible to train on")
    return data


def scale_K(K: Array, s: float) -> Array:
    """K of the image resized by ``s`` (OpenCV's pixel-centre convention kept)."""
    out = np.array(K, dtype=np.float64)
    out[0, 0] *= s
    out[1, 1] *= s
    out[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    out[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return out


def resize_to_width(rgb: NDArray[np.uint8], K: Array, width: int) -> tuple[NDArray[np.uint8], Array, float]:
    """``rgb`` resized to ``width`` (area filter when shrinking), its K, and the scale."""
    import cv2

    h, w = rgb.shape[:2]
    if w == width:
        return rgb, np.asarray(K, dtype=np.float64), 1.0
    s = width / w
    size = (width, max(1, round(h * s)))
    out = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    return out, scale_K(np.asarray(K, dtype=np.float64), s), s


def _add_image(data: TrainingData, casters: _Casters, image: Any, work_width: int, crop_width: int,
               heldout: bool) -> None:
    """Add one :class:`brave6d.annotation.SplitImage` and its instances to ``data``."""
    import cv2

    from brave6d.core.atomic import read_png

    cam = image.camera
    rgb_full = image.read_rgb()
    rgb_work, K_work, s_work = resize_to_width(rgb_full, cam.cam_K, work_width)
    rgb, K, s = resize_to_width(rgb_full, cam.cam_K, crop_width)
    record = ImageRecord(image.scene_id, image.im_id, rgb_work, K_work, np.asarray(cam.cam_K),
                         (rgb_full.shape[1], rgb_full.shape[0]), heldout, image.depth_path, rgb, K,
                         depth_scale=cam.depth_scale)
    data.images.append(record)
    h, w = rgb.shape[:2]
    for gt_id, (gt, info) in enumerate(zip(image.gts, image.infos)):
        if info.visib_fract < MIN_VISIB_FRACT or info.bbox_visib is None or info.bbox_obj is None:
            continue
        mask_full = read_png(image.mask_visib_path(gt_id))
        visible = cv2.resize((mask_full > 0).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5
        bx, by, bw, bh = info.bbox_visib
        box = (bx * s, by * s, (bx + bw + 1) * s, (by + bh + 1) * s)  # crop-source pixels
        box_work = tuple(b * s_work / s for b in box)
        ox, oy, ow, oh = info.bbox_obj
        mx, my = _REGION_MARGIN * ow * s, _REGION_MARGIN * oh * s
        x0, y0 = max(0, int(math.floor(ox * s - mx))), max(0, int(math.floor(oy * s - my)))
        x1, y1 = min(w, int(math.ceil((ox + ow + 1) * s + mx))), min(h, int(math.ceil((oy + oh + 1) * s + my)))
        if x1 - x0 < 2 or y1 - y0 < 2:
            continue
        obj = data.objects[gt.obj_id]
        _, _, sym = obj.canonical(gt.cam_R_m2c, gt.cam_t_m2c)
        coords, hit = casters.coordinates(gt.obj_id, gt.cam_R_m2c, gt.cam_t_m2c, K, x0, y0, x1, y1)
        # canonical coordinates: q = R_s^T (p - t_s), normalised by the model's centre and radius
        q = (coords - obj.sym_t[sym]) @ obj.sym_R[sym]
        q = (q - obj.centre_mm) / obj.radius_mm
        mask = hit & visible[y0:y1, x0:x1]
        if mask.sum() < 4:
            continue
        data.instances.append(Instance(len(data.images) - 1, gt.obj_id, obj.class_index, gt.cam_R_m2c, gt.cam_t_m2c,
                                       float(info.visib_fract), box_work, (x0, y0),  # type: ignore[arg-type]
                                       np.where(mask[..., None], q, 0.0).astype(np.float16), mask, box))
        record.instances.append(len(data.instances) - 1)


class _Casters:
    """One Open3D ray-casting scene per object, in its model frame (mm)."""

    def __init__(self, objects: dict[int, ObjectInfo]) -> None:
        import open3d as o3d

        self._scenes = {}
        for obj_id, obj in objects.items():
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(obj.vertices_mm.astype(np.float32)),
                                o3d.core.Tensor(obj.faces.astype(np.uint32)))
            self._scenes[obj_id] = scene

    def coordinates(self, obj_id: int, R: Array, t_mm: Array, K: Array, x0: int, y0: int, x1: int,
                    y1: int) -> tuple[Array, NDArray[np.bool_]]:
        """Model coordinates (mm) of the first hit of each pixel's ray in ``[y0:y1, x0:x1]``, and the hit mask."""
        import open3d as o3d

        u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
        rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
        dirs = rays_cam @ R  # R^T d per ray, in the model frame
        origin = -R.T @ t_mm
        rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], axis=-1).reshape(-1, 6)
        hits = self._scenes[obj_id].cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
        t_hit = hits["t_hit"].numpy().reshape(u.shape).astype(np.float64)
        hit = np.isfinite(t_hit)
        points = origin + np.where(hit, t_hit, 0.0)[..., None] * dirs
        return points, hit

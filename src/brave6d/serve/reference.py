"""The scene's reference geometry: the fixed surface that scores are measured against.

Agents see the splat; scores must not move when the same scene is trained again. So the depth
that VSD is scored on (the "test depth") and the occluders of the served visible fractions come
from one mesh built once from the CAPTURED depth and the CALIBRATED camera poses (robot pose x
hand-eye, never a simulator's truth), not from the splat being served.

Build: Open3D's TSDF integration (tensor ``VoxelBlockGrid``, CPU) of the undistorted depth frames
(:func:`brave6d.core.undistort.ensure_undistorted`, poses from
:func:`brave6d.core.calibration_io.camera_poses`), then marching cubes. Depths outside
``[depth_min_m, depth_max_m]``, zero, NaN or inf are no data; a frame without any valid depth
is skipped and counted; no valid frame at all, or a mesh without triangles, is a clear error.

File: ``reference.ply`` in the bundle (:data:`brave6d.serve.bundle.REFERENCE`), a binary
triangle mesh in METRES in the world (robot base) frame, written atomically; its build settings
(:class:`ReferenceSettings` and :class:`ReferenceStats`) go to ``scene.json`` under
``reference``. This module is the one owner of that file and that record.

Depth from the reference (:meth:`ReferenceGeometry.depth`): z-depth in metres at the pixel
centres of a pinhole camera (integer pixel coordinates, as the object silhouettes), 0 where a ray
hits nothing (never NaN/inf, also from a camera inside the scene's bounds).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, DataError
from brave6d.core.layout import SceneDir
from brave6d.core.progress import progress
from brave6d.core.transforms import check_rigid, invert

log = logging.getLogger(__name__)

#: the record's format name in ``scene.json``
FORMAT = "brave6d-reference/1"
#: what the geometry that scores are measured against is called in logs and scores
REFERENCE_GEOMETRY = "reference"
#: ... and the fallback for bundles exported without a reference
SPLAT_GEOMETRY = "splat"


class ReferenceGeometryError(BraveError):
    """The reference geometry cannot be built or read (the message names the scene or file)."""


@dataclass(frozen=True)
class ReferenceSettings:
    """How the reference is integrated (metres). Defaults chosen by measurement on the demo scene
    (``benchmarks/reference_geometry.py``; docs/BENCHMARKS.md)."""

    voxel_m: float = 0.002
    trunc_m: float = 0.008
    depth_min_m: float = 0.05
    depth_max_m: float = 1.0
    min_weight: float = 3.0  # observations a voxel needs to take part in the surface (fewer: noise)

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not (np.isfinite(value) and value > 0):
                raise ReferenceGeometryError(f"reference settings: {name} must be a finite number > 0, got {value}")
        if self.depth_min_m >= self.depth_max_m:
            raise ReferenceGeometryError(f"reference settings: depth_min_m ({self.depth_min_m}) must be below depth_max_m "
                                 f"({self.depth_max_m})")
        if self.trunc_m < self.voxel_m:
            raise ReferenceGeometryError(f"reference settings: trunc_m ({self.trunc_m}) must be at least voxel_m "
                                 f"({self.voxel_m})")


@dataclass(frozen=True)
class ReferenceStats:
    """What a build used and made."""

    frames_used: int
    frames_skipped: int  # frames without any valid depth (or without a depth file)
    vertices: int
    triangles: int
    build_s: float


@dataclass(frozen=True)
class ReferenceMesh:
    vertices: NDArray[np.float64]  # (N, 3) metres, world frame
    faces: NDArray[np.int64]  # (M, 3)
    settings: ReferenceSettings
    stats: ReferenceStats

    def record(self, file: str) -> dict[str, Any]:
        """The ``scene.json`` ``reference`` record of this mesh stored as ``file``."""
        return {"format": FORMAT, "file": file, "units": "m", "frame": "world",
                "settings": asdict(self.settings), **asdict(self.stats)}


# ----------------------------------------------------------------------------- build
def clean_depth(depth_m: NDArray[np.floating], settings: ReferenceSettings) -> NDArray[np.float32]:
    """Depth with everything that is not data (NaN, inf, <= 0, outside the range) set to 0."""
    d = np.asarray(depth_m, dtype=np.float32)
    ok = np.isfinite(d) & (d >= settings.depth_min_m) & (d <= settings.depth_max_m)
    return np.where(ok, d, np.float32(0.0)).astype(np.float32)


def integrate_depth(frames: Iterable[tuple[NDArray[np.floating] | None, NDArray[np.float64]]],
                    camera: PinholeCamera, settings: ReferenceSettings, where: str,
                    total: int | None = None) -> ReferenceMesh:
    """TSDF-integrate ``(depth in metres (H, W) or None, world_T_cam)`` frames seen through the
    undistorted pinhole ``camera``; ``where`` names the scene in errors."""
    import open3d as o3d
    import open3d.core as o3c

    t0 = time.perf_counter()
    cpu = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32), attr_channels=((1), (1)),
        voxel_size=float(settings.voxel_m), block_resolution=8, block_count=50_000, device=cpu)
    K = o3c.Tensor(camera.K, o3c.float64)
    trunc = float(settings.trunc_m / settings.voxel_m)
    used = skipped = 0
    for n, (depth, world_T_cam) in enumerate(progress(frames, total=total, desc="reference geometry", unit="frame")):
        if depth is None:
            skipped += 1
            continue
        if depth.shape != (camera.height, camera.width):
            raise ReferenceGeometryError(f"{where}: depth frame {n} is {depth.shape[1]}x{depth.shape[0]}, the camera is "
                                 f"{camera.width}x{camera.height}")
        d = clean_depth(depth, settings)
        if not np.any(d > 0):
            skipped += 1
            continue
        T = check_rigid(world_T_cam, f"{where}: frame {n} world_T_cam")
        image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(d)))
        extrinsic = o3c.Tensor(invert(T), o3c.float64)
        blocks = grid.compute_unique_block_coordinates(image, K, extrinsic, 1.0, float(settings.depth_max_m), trunc)
        grid.integrate(blocks, image, K, extrinsic, 1.0, float(settings.depth_max_m), trunc)
        used += 1
    if used == 0:
        raise ReferenceGeometryError(f"{where}: no depth frame has valid depth in [{settings.depth_min_m:g}, "
                             f"{settings.depth_max_m:g}] m ({skipped} frame(s) skipped); the reference geometry "
                             "needs the captured depth")
    try:
        mesh = grid.extract_triangle_mesh(weight_threshold=float(min(settings.min_weight, used)))
        vertices = mesh.vertex.positions.numpy().astype(np.float64)
        faces = mesh.triangle.indices.numpy().astype(np.int64)
    except RuntimeError:  # Open3D raises on an empty extraction (no zero crossing)
        vertices, faces = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    check_mesh(vertices, faces, where)
    vertices, faces = canonical_order(vertices, faces)
    stats = ReferenceStats(used, skipped, len(vertices), len(faces), time.perf_counter() - t0)
    return ReferenceMesh(vertices, faces, settings, stats)


def canonical_order(vertices: NDArray[np.float64], faces: NDArray[np.int64]
                    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The same mesh in one order: vertices sorted by (x, y, z), each face turned to start at its
    smallest index (winding kept), faces sorted. Open3D's extraction runs on several threads and
    emits the same surface in a different order each time; sorting makes ``reference.ply`` and its
    checksum the same for every export of one scene."""
    if len(vertices) == 0:
        return vertices, faces
    order = np.lexsort((vertices[:, 2], vertices[:, 1], vertices[:, 0]))
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    f = rank[faces]
    if len(f):
        start = np.argmin(f, axis=1)
        f = np.take_along_axis(f, (start[:, None] + np.arange(3)[None, :]) % 3, axis=1)
        f = f[np.lexsort((f[:, 2], f[:, 1], f[:, 0]))]
    return vertices[order], f


def check_mesh(vertices: NDArray[np.float64], faces: NDArray[np.int64], where: str) -> None:
    """A clear error for a mesh that cannot serve as the reference (no triangles, non-finite
    vertices, indices out of range, or all triangles of zero area)."""
    if len(faces) == 0 or len(vertices) < 3:
        raise ReferenceGeometryError(f"{where}: the reference geometry has no triangles (the depth frames hold no surface "
                             "that the TSDF could close; check the depth range and the calibration)")
    if not np.all(np.isfinite(vertices)):
        raise ReferenceGeometryError(f"{where}: the reference geometry has non-finite vertices")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ReferenceGeometryError(f"{where}: the reference geometry's faces index vertices that do not exist")
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    if not np.any(np.linalg.norm(np.cross(b - a, c - a), axis=1) > 0):
        raise ReferenceGeometryError(f"{where}: the reference geometry is degenerate (every triangle has zero area)")


def scene_depth_frames(scene: SceneDir) -> tuple[PinholeCamera, list[tuple[Any, NDArray[np.float64]]]]:
    """The undistorted camera and ``(depth loader, world_T_cam)`` of every captured frame (calibrated
    poses); a frame without a depth file loads None."""
    from brave6d.core.atomic import depth_mm_u16_to_m, read_png
    from brave6d.core.calibration_io import camera_poses
    from brave6d.core.undistort import ensure_undistorted

    frames = ensure_undistorted(scene)
    poses = camera_poses(scene, frames.records)
    size = (frames.camera.width, frames.camera.height)

    def loader(record: Any) -> Any:
        def load() -> NDArray[np.float32] | None:
            path = frames.depth_path(record)
            if path is None or not path.is_file():
                return None
            return depth_mm_u16_to_m(read_png(path, expect="depth", size=size, size_of="the undistorted camera"))
        return load

    return frames.camera, [(loader(r), T) for r, T in poses]


def build_scene_reference(scene_dir: Path | str, settings: ReferenceSettings | None = None) -> ReferenceMesh:
    """The reference mesh of a captured and calibrated scene (see the module docstring)."""
    scene = SceneDir(scene_dir)
    where = f"scene {scene.root}"
    for needed, what in ((scene.frames_path, "no capture"), (scene.handeye_path, "no hand-eye calibration"),
                         (scene.intrinsics_path, "no calibrated intrinsics")):
        if not needed.is_file():
            raise ReferenceGeometryError(f"{where}: {what} ({needed}); the reference geometry is built from the captured "
                                 "depth at the calibrated poses")
    try:
        camera, frames = scene_depth_frames(scene)
    except DataError as exc:
        raise ReferenceGeometryError(f"{where}: {exc}") from None

    def loaded() -> Iterator[tuple[NDArray[np.float32] | None, NDArray[np.float64]]]:
        for load, T in frames:
            yield load(), T

    return integrate_depth(loaded(), camera, settings or ReferenceSettings(), where, total=len(frames))


# ----------------------------------------------------------------------------- file
def write_reference(path: Path | str, mesh: ReferenceMesh) -> Path:
    """Write the mesh as a binary PLY (metres, world frame), atomically."""
    from brave6d.annotation import write_ply_mesh

    return write_ply_mesh(path, mesh.vertices, mesh.faces, comment="BRAVE-6D reference geometry (metres, world frame)")


def read_reference(path: Path | str) -> ReferenceGeometry:
    """The reference geometry of a bundle file (errors name the file)."""
    from brave6d.annotation import read_ply_mesh

    p = Path(path)
    try:
        mesh = read_ply_mesh(p)
    except (DataError, OSError, ValueError) as exc:
        raise ReferenceGeometryError(f"{p}: cannot read the reference geometry ({exc})") from None
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    check_mesh(vertices, faces, str(p))
    return ReferenceGeometry(vertices, faces)


class ReferenceGeometry:
    """Ray-castable reference mesh (Open3D ``RaycastingScene``); thread-safe."""

    def __init__(self, vertices: NDArray[np.float64], faces: NDArray[np.int64]) -> None:
        import open3d as o3d

        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                                  o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
        self.triangles = len(faces)
        # the first cast builds the scene's BVH: done here, at load, not in the first observation
        self._scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 0, 0, 0, 1]], dtype=np.float32)))
        self._rays: dict[tuple[Any, ...], NDArray[np.float32]] = {}
        self._lock = threading.Lock()

    def _camera_rays(self, camera: PinholeCamera) -> NDArray[np.float32]:
        key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
        rays = self._rays.get(key)
        if rays is None:
            xy = camera.without_distortion().normalized_rays(camera.pixel_grid())
            rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1).astype(np.float32)
            if len(self._rays) > 8:
                self._rays.clear()
            self._rays[key] = rays
        return rays

    def depth(self, world_T_cam: NDArray[np.float64], camera: PinholeCamera) -> NDArray[np.float32]:
        """(H, W) z-depth in metres of the first surface at each pixel centre; 0 = no surface."""
        return self._cast(self._world_rays(world_T_cam, self._camera_rays(camera))).reshape(camera.height, camera.width)

    def depth_along(self, world_T_cam: NDArray[np.float64], rays_cam: NDArray[np.float32]) -> NDArray[np.float32]:
        """(N,) z-depth in metres of the first surface along camera-frame rays ``(x, y, 1)`` (N, 3)
        from the camera at ``world_T_cam``; 0 = no surface. Never NaN/inf. :meth:`depth_along_many` of
        this one set (the visible fractions' occluders, one view or many alike)."""
        return self.depth_along_many([world_T_cam], [rays_cam])

    def depth_along_many(self, world_T_cams: Sequence[NDArray[np.float64]], rays_cam: Sequence[NDArray[np.float32]],
                         needed: NDArray[np.bool_] | None = None) -> NDArray[np.float32]:
        """:meth:`depth_along` of many cameras' rays in one cast (many agents), concatenated: ray set ``k``
        from the camera at ``world_T_cams[k]``. Each ray's world direction is the float32 sum
        ``x R[:, 0] + y R[:, 1] + z R[:, 2]`` (products and sums rounded one by one, the rotation and
        origin rounded to float32), computed for all rays at once from per-ray copies of their camera's
        entries: a ray's depth does not depend on the other rays cast with it (:meth:`depth`, the test
        depth, keeps its matrix product). ``needed`` (one flag per ray, concatenated): only those rays
        are cast, the others get 0 (no surface)."""
        sets = [np.asarray(d, dtype=np.float32).reshape(-1, 3) for d in rays_cam]
        if not sets:
            return np.zeros(0, dtype=np.float32)
        d = np.concatenate(sets)
        owner = np.repeat(np.arange(len(sets)), [len(s) for s in sets])
        if needed is not None:
            d, owner = d[needed], owner[needed]
        poses = np.asarray([np.asarray(T, dtype=np.float64) for T in world_T_cams]).reshape(-1, 4, 4)
        origins = poses[:, :3, 3].astype(np.float32).T.copy()  # (3, cameras)
        rotations = poses[:, :3, :3].astype(np.float32).reshape(-1, 9).T.copy()  # (9, cameras), row by row
        rays = np.empty((len(d), 6), dtype=np.float32)
        for k in range(3):
            rays[:, k] = origins[k].take(owner)
            rays[:, 3 + k] = (d[:, 0] * rotations[3 * k].take(owner) + d[:, 1] * rotations[3 * k + 1].take(owner)
                              + d[:, 2] * rotations[3 * k + 2].take(owner))
        if needed is None:
            return self._cast(rays)
        out = np.zeros(len(needed), dtype=np.float32)
        if len(rays):
            out[needed] = self._cast(rays)
        return out

    @staticmethod
    def _world_rays(world_T_cam: NDArray[np.float64], rays_cam: NDArray[np.float32]) -> NDArray[np.float32]:
        """(N, 6) the world-frame rays from the camera at ``world_T_cam`` along camera-frame ``rays_cam`` (N, 3)."""
        d = np.asarray(rays_cam, dtype=np.float32).reshape(-1, 3)
        T = np.asarray(world_T_cam, dtype=np.float64)
        rays = np.empty((len(d), 6), dtype=np.float32)
        rays[:, :3] = T[:3, 3]
        rays[:, 3:] = d @ T[:3, :3].T.astype(np.float32)  # z = 1 in the camera: t is the z-depth
        return rays

    def _cast(self, rays: NDArray[np.float32]) -> NDArray[np.float32]:
        with self._lock:
            t = self._scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
        return np.where(np.isfinite(t) & (t > 0), t, np.float32(0.0)).astype(np.float32)


def bundle_reference(bundle: Any) -> ReferenceGeometry | None:
    """The reference geometry of a loaded bundle (read once, by the scene's server), or None with
    ONE warning for a bundle exported without it: its scores fall back to the splat's depth, and
    every score says which geometry it was measured on."""
    path = bundle.reference_path
    if path is None:
        log.warning("bundle %s has no reference geometry (%s): %s", bundle.name, bundle.root,
                    missing_reference_advice(bool(bundle.objects)))
        return None
    return read_reference(path)


def missing_reference_advice(has_objects: bool) -> str:
    """What a bundle without reference geometry means and what can fix it. Exporting again helps
    only when the capture recorded depth (a bundle exported before the reference existed); a
    capture without depth (an imported photo set) never gets one, and a bundle without objects
    has nothing to score: it is looked at with free views (``POST /render``)."""
    if not has_objects:
        return ("it has no objects either, so nothing is scored on it; look at it with free views "
                "(POST /render, or the viewer's free view); annotate objects (brave6d annotate) for episodes")
    return ("visible fractions and the depth VSD is scored on come from the splat being served, so its scores "
            "move with each training; if its capture recorded depth, export the bundle again to add the reference "
            "(a capture without depth, such as an imported photo set, cannot have one)")

"""Initial points for training, and the COLMAP model of the scene in ``sparse/0``.

With the camera poses known (robot + calibrated hand-eye), COLMAP only has to find and
triangulate points: SIFT features (CPU), matching of each training image with its nearest
cameras (by camera centre: cheap and sufficient for a ring capture), then
``pycolmap.triangulate_points`` with the poses held fixed (no pose estimation). The model is
written to ``sparse/0`` (``cameras.bin``, ``images.bin``, ``points3D.bin``; PINHOLE camera of the
undistorted images in COLMAP's pixel convention, see :func:`colmap_pinhole_params`, named as in
``undistorted/rgb``) so that Inria's trainer
(``-s SCENE -i undistorted/rgb``), gsplat and nerfstudio can train on the same scene; the
holdout images are included with their poses and listed in ``sparse/holdout.txt`` (for COLMAP's
users; the split every stage reads is ``splat/holdout.json``).

Fallbacks when COLMAP yields too few points: back-projected depth frames (voxel-downsampled),
then uniformly random points inside the workspace (with a warning). Holdout views are never
used to make points.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from brave6d.core.atomic import atomic_write_json, atomic_write_text, file_sha256, read_json
from brave6d.core.camera import CORNER_ORIGIN_OFFSET, PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import invert
from brave6d.training.scene_frame import SceneFrame
from brave6d.training.views import TrainingData, View, load_depth_m

log = logging.getLogger(__name__)


@dataclass
class InitPoints:
    """Points (N, 3) in the world frame, colours (N, 3) in [0, 1], and where they came from."""

    points: NDArray[np.float64]
    colors: NDArray[np.float32]
    source: str  # "colmap" | "depth" | "random"
    details: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)

    def subsample(self, max_points: int, seed: int = 0) -> InitPoints:
        """At most ``max_points`` points, a deterministic random subset."""
        if len(self) <= max_points:
            return self
        keep = np.sort(np.random.default_rng(seed).choice(len(self), max_points, replace=False))
        return InitPoints(self.points[keep], self.colors[keep], self.source,
                          {**self.details, "subsampled_from": len(self)})


@dataclass(frozen=True)
class ColmapOptions:
    """How COLMAP finds points (SIFT on the CPU)."""

    max_features: int = 4096
    neighbours: int = 8  # each image is matched with this many nearest cameras
    num_threads: int = -1  # feature extraction threads (-1: every core; the features do not depend on it)
    min_points: int = 1000  # fewer triangulated points -> depth fallback
    max_reprojection_error: float = 2.0  # px; points above are dropped from the initialisation
    seed: int = 0  # RANSAC and triangulation seeds (repeatable points)
    match_threads: int = 1  # matching + verification threads; 1: repeatable (see match_pairs)
    triangulation_threads: int | None = None  # bundle adjustment threads (None: 1, repeatable; see triangulate_database)


# ----------------------------------------------------------------------------- COLMAP model
def _pycolmap():  # type: ignore[no-untyped-def]
    try:
        import pycolmap
    except ImportError as exc:  # pragma: no cover - pycolmap is a dependency
        raise BraveError(f"pycolmap is needed for COLMAP initialisation ({exc})") from None
    return pycolmap


def _rigid(cam_T_world: NDArray[np.float64]):  # type: ignore[no-untyped-def]
    return _pycolmap().Rigid3d(np.ascontiguousarray(cam_T_world[:3, :4], dtype=np.float64))


#: COLMAP's coordinate of a pixel centre minus OpenCV's (px, both axes): the corner-origin offset.
COLMAP_PIXEL_OFFSET = CORNER_ORIGIN_OFFSET


def colmap_pinhole_params(camera: PinholeCamera) -> list[float]:
    """PINHOLE ``[fx, fy, cx, cy]`` of the undistorted ``camera`` in COLMAP's pixel convention.

    COLMAP's camera models put the upper-left image corner at (0, 0), so pixel (0, 0) is
    centred at (0.5, 0.5) (``src/colmap/sensor/models.h``, header comment; its SIFT keypoints
    and ``Camera.create``'s default principal point ``(width / 2, height / 2)`` agree). The
    project's ``K`` is OpenCV's (pixel (0, 0) centred at (0, 0)): the principal point moves by
    +0.5 px, focal lengths stay (colmap/colmap#2587 and its FAQ, PR #4566). Every camera handed
    to COLMAP comes from here: the feature database and the ``sparse/0`` model alike.
    """
    if camera.has_distortion:
        raise BraveError("COLMAP model: the camera must be undistorted (PINHOLE)")
    return [float(camera.fx), float(camera.fy), float(camera.cx) + COLMAP_PIXEL_OFFSET,
            float(camera.cy) + COLMAP_PIXEL_OFFSET]


def _colmap_camera(camera: PinholeCamera, camera_id: int = 1):  # type: ignore[no-untyped-def]
    return _pycolmap().Camera(model="PINHOLE", width=camera.width, height=camera.height,
                              params=colmap_pinhole_params(camera), camera_id=camera_id)


def empty_reconstruction(camera: PinholeCamera, images: list[tuple[str, NDArray[np.float64]]]):  # type: ignore[no-untyped-def]
    """A reconstruction with one PINHOLE camera and posed images ``(name, base_T_cam)``, no points."""
    pc = _pycolmap()
    rec = pc.Reconstruction()
    rec.add_camera_with_trivial_rig(_colmap_camera(camera))
    for image_id, (name, base_T_cam) in enumerate(images, start=1):
        rec.add_image_with_trivial_frame(pc.Image(name=name, camera_id=1, image_id=image_id),
                                         _rigid(invert(base_T_cam)))
    return rec


def add_posed_images(rec: Any, images: list[tuple[str, NDArray[np.float64]]], camera_id: int = 1) -> None:
    """Add images (without observations) to ``rec`` with fixed poses."""
    pc = _pycolmap()
    next_id = max(rec.images.keys(), default=0) + 1
    for offset, (name, base_T_cam) in enumerate(images):
        rec.add_image_with_trivial_frame(pc.Image(name=name, camera_id=camera_id, image_id=next_id + offset),
                                         _rigid(invert(base_T_cam)))


def add_points(rec: Any, points: NDArray[np.float64], colors: NDArray[np.float32]) -> None:
    """Add track-less 3D points (e.g. from depth) to ``rec``."""
    pc = _pycolmap()
    rgb = np.clip(np.rint(np.asarray(colors) * 255.0), 0, 255).astype(np.uint8)
    for xyz, c in zip(np.asarray(points, np.float64), rgb):
        rec.add_point3D(xyz, pc.Track(), c)


def write_model(rec: Any, scene: SceneDir, holdout_names: list[str] | None = None) -> Path:
    """Write ``rec`` to ``sparse/0`` (binary) replacing any previous model (never half-written), and
    the names of its held-out images to ``sparse/holdout.txt`` (COLMAP's bookkeeping: the split is
    ``splat/holdout.json``, :mod:`brave6d.training.holdout`)."""
    sparse_dir = scene.sparse_dir
    sparse_dir.mkdir(parents=True, exist_ok=True)
    final = scene.sparse_model_dir
    tmp = Path(tempfile.mkdtemp(prefix=".0.", dir=sparse_dir))
    try:
        rec.write_binary(str(tmp))
        old = sparse_dir / f".0.old-{time.time_ns()}"
        if final.exists():
            final.rename(old)
        tmp.rename(final)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if holdout_names is not None:
        atomic_write_text(scene.sparse_holdout_path, "".join(f"{n}\n" for n in holdout_names))
    return final


def read_model_points(model_dir: Path) -> InitPoints:
    """Points and colours of an existing COLMAP model."""
    rec = _pycolmap().Reconstruction(str(model_dir))
    pts = [p.xyz for p in rec.points3D.values()]
    cols = [p.color for p in rec.points3D.values()]
    points = np.asarray(pts, np.float64).reshape(-1, 3)
    colors = (np.asarray(cols, np.float32).reshape(-1, 3) / 255.0).astype(np.float32)
    return InitPoints(points, colors, "colmap", {"model": str(model_dir)})


# ----------------------------------------------------------------------------- triangulation
def nearest_camera_pairs(centres: NDArray[np.float64], k: int) -> list[tuple[int, int]]:
    """Unordered index pairs linking each camera with its ``k`` nearest camera centres."""
    n = len(centres)
    if n < 2:
        return []
    k = min(k, n - 1)
    _, nn = cKDTree(centres).query(centres, k=k + 1)
    pairs = {(min(i, int(j)), max(i, int(j))) for i in range(n) for j in np.atleast_1d(nn[i])[1:] if int(j) != i}
    return sorted(pairs)


def triangulate(
    image_dir: Path,
    camera: PinholeCamera,
    images: list[tuple[str, NDArray[np.float64]]],
    work_dir: Path,
    options: ColmapOptions = ColmapOptions(),
):  # type: ignore[no-untyped-def]
    """Extract, match and triangulate with fixed poses; returns the pycolmap Reconstruction and timings.

    ``images``: ``(file name in image_dir, base_T_cam)``. ``work_dir`` holds the database
    (``database.db``, which :func:`triangulate_database` can triangulate again).
    Repeatable: see :func:`extract_features`, :func:`match_pairs` and :func:`triangulate_database`.
    """
    db_path = work_dir / "database.db"  # extract_features makes work_dir
    t0 = time.perf_counter()
    extract_features(db_path, image_dir, camera, [n for n, _ in images], options)
    t1 = time.perf_counter()
    n_pairs = match_pairs(db_path, images, work_dir / "pairs.txt", options)
    t2 = time.perf_counter()
    rec = triangulate_database(db_path, image_dir, images, work_dir / "triangulated", options)
    t3 = time.perf_counter()
    log.info("COLMAP: %d images, %d pairs, %d points (extract %.1f s, match %.1f s, triangulate %.1f s)",
             len(images), n_pairs, rec.num_points3D(), t1 - t0, t2 - t1, t3 - t2)
    rec_timings = {"extract_s": t1 - t0, "match_s": t2 - t1, "triangulate_s": t3 - t2, "pairs": n_pairs}
    return rec, rec_timings


def extract_features(db_path: Path, image_dir: Path, camera: PinholeCamera, names: list[str],
                     options: ColmapOptions = ColmapOptions()) -> None:
    """A new COLMAP database at ``db_path`` (an old one is replaced) with the SIFT features of ``names``.

    The images are imported first, on one thread and in the given order, so that image ids do not
    depend on thread timing; the extraction itself runs on ``options.num_threads`` (each image's
    features are the same whichever thread extracts them).
    """
    pc = _pycolmap()
    db_path.parent.mkdir(parents=True, exist_ok=True)
    db_path.unlink(missing_ok=True)
    reader = pc.ImageReaderOptions(camera_model="PINHOLE",
                                   camera_params=",".join(repr(p) for p in colmap_pinhole_params(camera)))
    extraction = pc.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.sift.max_num_features = options.max_features
    pc.Database.open(db_path).close()
    pc.import_images(db_path, image_dir, camera_mode=pc.CameraMode.SINGLE, image_names=names, options=reader)
    pc.extract_features(db_path, image_dir, image_names=names, camera_mode=pc.CameraMode.SINGLE,
                        reader_options=reader, extraction_options=extraction, device=pc.Device.cpu)


def match_pairs(db_path: Path, images: list[tuple[str, NDArray[np.float64]]], pairs_path: Path,
                options: ColmapOptions = ColmapOptions()) -> int:
    """Match each image of ``images`` (name, base_T_cam) with its ``options.neighbours`` nearest cameras
    and verify each pair's geometry, into ``db_path``; returns the number of pairs (listed in ``pairs_path``).

    Repeatable at ``options.match_threads = 1`` (the default): every pair's RANSAC is seeded
    (``options.seed``) and runs on one thread. With several matching threads, COLMAP's CPU matchers
    search the shared per-image descriptor indexes (FAISS, over the OpenBLAS built into pycolmap)
    at the same time, and now and then a pair's matches differ between runs of the same database:
    3 of 150 repeated matchings of the test plane scene at 8 threads, none of 150 at 1
    (``benchmarks/colmap_threads.py --stage match``, which also prices the thread count).
    """
    pc = _pycolmap()
    names = [n for n, _ in images]
    centres = np.array([T[:3, 3] for _, T in images])
    pairs = nearest_camera_pairs(centres, options.neighbours)
    atomic_write_text(pairs_path, "".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
    matching = pc.FeatureMatchingOptions()
    matching.num_threads = options.match_threads
    verification = pc.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.seed
    verification.ransac.num_threads = 1  # COLMAP's parallel RANSAC keeps whichever thread's best model comes first
    pc.set_random_seed(options.seed)
    pc.match_image_pairs(db_path, matching_options=matching,
                         pairing_options=pc.ImportedPairingOptions(match_list_path=pairs_path),
                         verification_options=verification, device=pc.Device.cpu)
    return len(pairs)


def triangulate_database(db_path: Path, image_dir: Path, images: list[tuple[str, NDArray[np.float64]]],
                         out_dir: Path, options: ColmapOptions = ColmapOptions()):  # type: ignore[no-untyped-def]
    """Triangulate the matches of ``db_path`` with the poses of ``images`` held fixed (``out_dir``:
    COLMAP's scratch folder); returns the pycolmap Reconstruction.

    ``options.triangulation_threads`` (None: 1) are the threads of the point-only bundle adjustment
    (Ceres). With more than one, Ceres sums the cost and gradient per thread over whichever residual
    blocks each thread took, so the rounding can change between runs, and a point whose
    reprojection error is near a filter threshold (``merge_max_reproj_error``, ``max_reprojection_error``)
    can end in another track or be dropped. One thread makes it repeatable at no measurable cost
    (docs/BENCHMARKS.md, ``benchmarks/colmap_threads.py``).

    COLMAP triangulates in the cameras' training frame (:mod:`brave6d.training.scene_frame`: their
    mean at the origin, their extent as the unit) and the model comes back to the world once, at
    the end: COLMAP's own absolute tolerances (its bundle adjustment's, its depth checks') then see
    the same numbers whatever the world's units, so a capture imported at another ``--scale`` gets
    the same points (the shipped fox at scales 0.1 to 10 got 4912 to 4915 points in world units).
    """
    pc = _pycolmap()
    frame = SceneFrame.of_cameras([T[:3, 3] for _, T in images])
    pose_of = {name: frame.pose(T) for name, T in images}
    db = pc.Database.open(db_path)
    try:
        rec = pc.Reconstruction()
        for cam in db.read_all_cameras():
            rec.add_camera_with_trivial_rig(cam)
        for im in db.read_all_images():
            rec.add_image_with_trivial_frame(pc.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id),
                                             _rigid(invert(pose_of[im.name])))
    finally:
        db.close()
    pipeline = pc.IncrementalPipelineOptions()
    pipeline.num_threads = 1 if options.triangulation_threads is None else options.triangulation_threads
    pipeline.random_seed = options.seed
    pipeline.triangulation.random_seed = options.seed
    out_dir.mkdir(parents=True, exist_ok=True)
    rec = pc.triangulate_points(rec, db_path, image_dir, out_dir, options=pipeline)
    rec.transform(pc.Sim3d(frame.unit, pc.Rotation3d(), frame.centre_array))  # world = unit * p + centre
    return rec


def points_of(rec: Any, max_error: float) -> InitPoints:
    """Triangulated points with reprojection error <= ``max_error`` px."""
    pts, cols = [], []
    points3D = rec.points3D
    for pid in sorted(rec.point3D_ids()):  # id order: the same model always gives the same sequence
        p = points3D[pid]
        if p.error <= max_error:
            pts.append(p.xyz)
            cols.append(p.color)
    points = np.asarray(pts, np.float64).reshape(-1, 3)
    colors = (np.asarray(cols, np.float32).reshape(-1, 3) / 255.0).astype(np.float32)
    return InitPoints(points, colors, "colmap", {"triangulated": rec.num_points3D(), "kept": len(points)})


# ----------------------------------------------------------------------------- fallbacks
def backproject_depth(views: list[View], camera: PinholeCamera, depth_camera: PinholeCamera | None = None,
                      max_points: int = 100_000, stride: int = 4) -> InitPoints:
    """Depth frames lifted to the world (every ``stride``-th pixel), voxel-downsampled to <= ``max_points``.

    ``camera``: the undistorted camera at depth resolution; colours come from the view images.
    """
    chunks, colours = [], []
    for view in views:
        depth = load_depth_m(view, depth_camera)
        if depth is None:
            continue
        if depth.shape != (camera.height, camera.width):
            log.warning("frame %d: depth is %dx%d, camera %dx%d; ignored", view.index, depth.shape[1],
                        depth.shape[0], camera.width, camera.height)
            continue
        v, u = np.mgrid[0:camera.height:stride, 0:camera.width:stride]
        d = depth[v, u]
        ok = np.isfinite(d) & (d > 0)
        if not ok.any():
            continue
        pix = np.stack([u[ok], v[ok]], axis=1).astype(np.float64)
        pts_cam = camera.unproject(pix, d[ok])
        R, t = view.base_T_cam[:3, :3], view.base_T_cam[:3, 3]
        chunks.append(pts_cam @ R.T + t)
        h, w = view.image.shape[:2]
        iu = np.clip(np.rint((pix[:, 0] + 0.5) * w / camera.width - 0.5), 0, w - 1).astype(int)
        iv = np.clip(np.rint((pix[:, 1] + 0.5) * h / camera.height - 0.5), 0, h - 1).astype(int)
        colours.append(view.image[iv, iu].astype(np.float32) / 255.0)
    if not chunks:
        return InitPoints(np.zeros((0, 3)), np.zeros((0, 3), np.float32), "depth", {"frames": 0})
    points = np.concatenate(chunks)
    colors = np.concatenate(colours)
    raw = len(points)
    points, colors, voxel = voxel_downsample(points, colors, max_points)
    return InitPoints(points, colors, "depth", {"frames": len(chunks), "raw_points": raw, "voxel_m": voxel})


def voxel_downsample(points: NDArray[np.float64], colors: NDArray[np.float32], max_points: int
                     ) -> tuple[NDArray[np.float64], NDArray[np.float32], float]:
    """Average points and colours per voxel, with the voxel grown until <= ``max_points`` remain."""
    lo = points.min(0)
    extent = float(np.max(points.max(0) - lo))
    voxel = max(extent / 4000.0, 1e-6)
    while True:
        cells = np.floor((points - lo) / voxel).astype(np.int64)
        dims = cells.max(0) + 1
        keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        uniq, inverse = np.unique(keys, return_inverse=True)
        if len(uniq) <= max_points:
            break
        voxel *= max(1.1, float((len(uniq) / max_points) ** 0.5))
    counts = np.bincount(inverse, minlength=len(uniq)).astype(np.float64)[:, None]
    mean_pts = np.stack([np.bincount(inverse, points[:, k], len(uniq)) for k in range(3)], 1) / counts
    mean_col = np.stack([np.bincount(inverse, colors[:, k], len(uniq)) for k in range(3)], 1) / counts
    return mean_pts, mean_col.astype(np.float32), voxel


def random_points(lo: NDArray[np.float64], hi: NDArray[np.float64], n: int, seed: int = 0) -> InitPoints:
    """``n`` uniformly random points with random colours inside the box ``[lo, hi]``."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    pts = lo + rng.random((n, 3)) * (hi - lo)
    return InitPoints(pts, rng.random((n, 3)).astype(np.float32), "random", {"box": [lo.tolist(), hi.tolist()]})


def workspace_box(scene: SceneDir | None, data: TrainingData) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The spec's workspace box when there is one, else the cameras' bounding box (padded)."""
    if scene is not None and scene.spec_path.exists():
        try:
            ws = scene.load_spec().workspace
            return np.asarray(ws.min, np.float64), np.asarray(ws.max, np.float64)
        except Exception as exc:  # noqa: BLE001 - a broken spec must not stop a fallback
            log.warning("workspace from %s unavailable (%s); using the camera bounding box", scene.spec_path, exc)
    centres = np.array([v.base_T_cam[:3, 3] for v in data.views])
    pad = data.scene_extent()
    return centres.min(0) - pad, centres.max(0) + pad


# ----------------------------------------------------------------------------- reuse
def model_stamp(camera: PinholeCamera, images: list[tuple[str, NDArray[np.float64]]], options: ColmapOptions,
                contents: dict[str, str] | None = None) -> str:
    """Hash of what a triangulation depends on: camera (and the pixel offset COLMAP was given it
    with, so models made before that conversion are not reused), image names, poses and
    contents, options."""
    payload = json.dumps({"camera": camera.to_json(), "colmap_pixel_offset": COLMAP_PIXEL_OFFSET,
                          "options": repr(options),
                          "images": [(n, np.round(T, 12).tolist()) for n, T in images],
                          "contents": contents or {}}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()


def image_contents(data: TrainingData) -> dict[str, str]:
    """SHA-256 of each view's image file, by file name (part of the reuse stamp).

    A recapture under the same names and poses (a simulated capture of an edited scene) must not
    reuse the old triangulation.
    """
    return {Path(v.rgb_path).name: file_sha256(Path(v.rgb_path)) for v in data.views
            if v.rgb_path is not None and Path(v.rgb_path).is_file()}


def _reusable_colmap(scene: SceneDir, stamp: str, options: ColmapOptions) -> InitPoints | None:
    """The points of ``sparse/0`` when it was triangulated from the same inputs (else None)."""
    stamp_path = scene.sparse_stamp_path
    model = scene.sparse_model_dir
    if not (stamp_path.is_file() and model.is_dir()):
        return None
    try:
        saved = read_json(stamp_path)
        if saved.get("stamp") != stamp or saved.get("source") != "colmap":
            return None
        rec = _pycolmap().Reconstruction(str(model))
    except Exception:  # noqa: BLE001 - unreadable stamp or model: triangulate again
        return None
    init = points_of(rec, options.max_reprojection_error)
    init.details["reused"] = str(model)
    return init


# ----------------------------------------------------------------------------- the chain
def initial_points(
    scene: SceneDir | None,
    data: TrainingData,
    options: ColmapOptions = ColmapOptions(),
    max_points: int = 300_000,
    seed: int = 0,
    method: str = "auto",
    write_sparse: bool = True,
) -> InitPoints:
    """COLMAP points (writing ``sparse/0``), else an imported capture's points, else depth
    back-projection, else random points.

    ``method``: ``auto`` (that chain), ``colmap``, ``depth`` or ``random`` (start the chain there), or
    ``imported``: first the sparse points an imported capture brought (``capture/imported_points.ply``),
    then the chain. The source made those from all its images, the holdout views included (as the
    usual COLMAP-initialised benchmarks do), so ``auto`` takes them only when COLMAP, which
    triangulates the training views alone, finds too few points.
    Whatever the source, ``sparse/0`` receives all cameras and the points used (when ``scene``
    is given and ``write_sparse``), so other 3DGS tools start from the same model; a benchmark that
    starts from depth or random points and needs no model passes ``write_sparse=False`` (then no
    pycolmap either).
    """
    full = data.full_camera or data.camera
    names = {v.index: Path(v.rgb_path).name if v.rgb_path else f"{v.index:06d}.png" for v in data.views}
    train_images = [(names[v.index], v.base_T_cam) for v in data.train]
    test_images = [(names[v.index], v.base_T_cam) for v in data.test]
    chains = {"auto": ["colmap", "imported", "depth", "random"], "colmap": ["colmap", "imported", "depth", "random"],
              "imported": ["imported", "colmap", "depth", "random"], "depth": ["depth", "random"], "random": ["random"]}
    if method not in chains:
        raise BraveError(f"unknown initialisation {method!r}; choose auto, imported, colmap, depth or random")
    chain = chains[method]
    rec = None
    result: InitPoints | None = None
    notes: dict[str, Any] = {}
    t0 = time.perf_counter()
    if chain[0] == "imported":
        result = _imported_points(scene, data, notes)
        chain = ["imported"] if result is not None else chain[1:]  # found: no triangulation (sparse/0 gets them)
    stamp = model_stamp(full, train_images + test_images, options, image_contents(data))
    reused = _reusable_colmap(scene, stamp, options) if chain[0] == "colmap" and scene is not None else None
    if reused is not None and scene is not None and len(reused) >= options.min_points:
        log.info("reusing the COLMAP points of %s (same images, poses and camera)", scene.sparse_model_dir)
        return _drop_far_points(reused, data).subsample(max_points, seed)
    if "colmap" in chain and result is None:
        if data.undistorted_root is None:
            notes["colmap"] = "skipped: no undistorted image files (in-memory undistortion)"
        else:
            with tempfile.TemporaryDirectory(prefix="brave6d-colmap-") as work:
                try:
                    rec, timings = triangulate(data.undistorted_root / "rgb", full, train_images, Path(work), options)
                    result = points_of(rec, options.max_reprojection_error)
                    result.details.update(timings)
                except Exception as exc:  # noqa: BLE001 - COLMAP failures must fall back, not stop training
                    log.warning("COLMAP triangulation failed: %s", exc)
                    notes["colmap"] = f"failed: {exc}"
                    rec = None
            if result is not None and len(result) < options.min_points:
                imported = "imported" in chain and scene is not None and scene.imported_points_path.is_file()
                log.warning("COLMAP triangulated only %d points (< %d); falling back to %s", len(result),
                            options.min_points, "the imported capture's points" if imported else "depth frames")
                notes["colmap"] = f"{len(result)} points (< {options.min_points})"
                result = None
    if result is None and "imported" in chain and chain[0] != "imported":
        result = _imported_points(scene, data, notes)
    if result is None and "depth" in chain:
        result = backproject_depth(data.train, full, data.depth_camera, max_points=max_points)
        if len(result) < 100:
            notes["depth"] = f"{len(result)} points"
            result = None
    if result is None:
        lo, hi = workspace_box(scene, data)
        n = min(max_points, 100_000)
        log.warning("initialising with %d RANDOM points inside the workspace %s..%s: no usable COLMAP or "
                    "depth points; expect slower, worse training", n, lo.round(3).tolist(), hi.round(3).tolist())
        result = random_points(lo, hi, n, seed)
    result.details.update(notes)
    result = _drop_far_points(result, data)
    if scene is not None and write_sparse:
        if rec is None:
            rec = empty_reconstruction(full, train_images)
        if result.source != "colmap":
            add_points(rec, result.points, result.colors)
        add_posed_images(rec, test_images)
        model = write_model(rec, scene, [n for n, _ in test_images])
        atomic_write_json(scene.sparse_stamp_path, {"stamp": stamp, "source": result.source})
        result.details["sparse_model"] = str(model)
    result.details["seconds"] = time.perf_counter() - t0
    return result.subsample(max_points, seed)


def _imported_points(scene: SceneDir | None, data: TrainingData, notes: dict[str, Any],
                     min_views: int = 2) -> InitPoints | None:
    """The imported capture's sparse points inside the view of at least ``min_views`` training
    views, or None (noted) when the scene has none.

    The source made its points from all its images: a point only the holdout views see would never
    be trained and would float, as initialised, in front of those views; so it is left out.
    """
    from brave6d.training.importing.scene_files import read_imported_points
    from brave6d.training.pose_check import visible_mask

    found = read_imported_points(scene) if scene is not None else None
    if found is None or len(found[0]) == 0:
        notes["imported"] = "no imported points (capture/imported_points.ply)"
        return None
    xyz, rgb = found
    seen = np.zeros(len(xyz), dtype=np.int64)
    for view in data.train:
        seen += visible_mask(data.camera, view.base_T_cam, xyz, margin=0.0)
    keep = seen >= min(min_views, len(data.train))
    if not keep.any():
        notes["imported"] = f"none of the {len(xyz)} imported points is in view of {min_views} training views"
        return None
    return InitPoints(xyz[keep], (rgb[keep].astype(np.float32) / 255.0).astype(np.float32), "imported",
                      {"file": str(scene.imported_points_path) if scene is not None else None, "imported": len(xyz),
                       "kept_in_view_of_training": int(keep.sum()),
                       "note": "the source's points (made from all its images) that training views see"})


def _drop_far_points(init: InitPoints, data: TrainingData, factor: float = 10.0) -> InitPoints:
    """Drop stray points far outside the captured region (bad matches at infinity)."""
    centres = np.array([v.base_T_cam[:3, 3] for v in data.views])
    keep = np.linalg.norm(init.points - centres.mean(0), axis=1) <= factor * data.scene_extent()
    if keep.all():
        return init
    return InitPoints(init.points[keep], init.colors[keep], init.source,
                      {**init.details, "dropped_far": int((~keep).sum())})

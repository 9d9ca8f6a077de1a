"""The scene bundle: everything the render server loads, in one self-contained, checksummed folder.

``brave6d export SCENE_DIR`` writes ``<scene>/bundle/``::

    manifest.json     format, scene name, creation time, the versions that made it (brave6d,
                      torch, numpy, scipy, plyfile, python, git commit when known), where it came
                      from without a path of the machine that made it (``source``: the scene's
                      name, the splat's path inside the scene directory and its sha256, the
                      sha256 of the training's metrics and holdout split) and, per file, its
                      sha256 and size. Written last.
    splat.ply         the trained Gaussians (Inria 3DGS PLY layout, copied unchanged)
    splat_viewer.ply  the same Gaussians for other 3DGS viewers (SuperSplat, gsplat's, SIBR): the
                      3D filter baked into scales and opacities, no ``filter_3d`` property
                      (``brave6d.training.write_viewer_ply``); absent in older bundles
    scene.json        pinhole intrinsics of the undistorted images, render defaults (size,
                      near/far, background, depth validity, ``antialiasing``: ``mip`` when the
                      splat was trained with Mip-Splatting's filters, i.e. its PLY has
                      ``filter_3d``; absent in older bundles: ``classic``), collision boxes (oriented, world
                      frame), workspace bounds, camera collision radius, start-pose hints
    objects.json      one entry per annotated instance (``gt_id`` = the BOP ground-truth index):
                      ``obj_id`` (BOP), name, ``world_T_obj`` (metres), ``model`` (BOP PLY in mm),
                      ``diameter_mm``, symmetries (BOP style, mm)
    models/obj_XXXXXX.ply   the object models in millimetres (BOP's files when the BOP export
                      exists, else converted from the annotation's meshes)
    holdout.json      the views held out of training: frame index, view id, ``world_T_cam``,
                      image file (``holdout/<name>.png``, undistorted) when present
    holdout/          the held-out undistorted RGB images
    reference.ply     the reference geometry scores are measured against (VSD's test depth, the
                      occluders of the visible fractions): a TSDF mesh of the captured depth at the
                      calibrated poses, metres, world frame (:mod:`brave6d.serve.reference`); its
                      build settings are ``scene.json``'s ``reference``. Absent when the capture
                      has no depth (or ``--no-reference``): the server then falls back to the
                      splat's depth and says so in every score

The folder is built in a hidden sibling and renamed into place (all or nothing). Export
replaces only what it made: an absent or empty folder, or a bundle (every file listed by its
manifest). Anything else at ``--out`` is refused unless ``force``, and then moved aside to
``<name>.old-<time>`` (never deleted); the scene directory, its stage folders and their
ancestors are always refused.
A splat with NaN/inf, no Gaussians or none visible is refused (:mod:`brave6d.serve.splat_check`), and
so are a corrupt ``frames.jsonl`` and holdout images that cannot be made (unless left out on
purpose with ``include_holdout_images=False``).
:func:`load_bundle` recomputes every checksum and refuses a bundle whose files do not match
its manifest (or that lists a file outside itself); files the manifest does not list are
ignored (never read). The manifest is read by :func:`read_bundle_manifest` only (verify, load,
the server's catalog, export's replace check), which checks its structure: a malformed one
(a list, ``files`` not an object, an entry without a 64-hex ``sha256`` or an integer ``bytes``,
a listed path that is absolute or has ``..``) is a :class:`BundleError` naming the file and the
field; so are a ``scene.json``/``objects.json`` that are not objects (:func:`read_bundle_json`).

What another stage writes is read in ONE small function each (easy to adapt when a format
changes): :func:`find_splat_ply`, :func:`read_annotation_instances`, :func:`holdout_frames` (the
split through :func:`brave6d.training.read_holdout`), :func:`scene_camera`.

This module owns the bundle's file names (:data:`MANIFEST`, :data:`SPLAT`, ...): whoever asks
whether a folder is a bundle asks :func:`is_bundle`, and whoever names a bundle's file imports
its name from here (through ``brave6d.serve``).
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import atomic_write_json, file_sha256, move_aside, read_json, staged_folder
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError, DataError
from brave6d.core.layout import FrameRecord, SceneDir
from brave6d.core.names import relative_path_problem
from brave6d.core.png_check import png_problem
from brave6d.core.provenance import software_versions
from brave6d.core.transforms import check_rigid
from brave6d.serve.geometry import DEFAULT_CAMERA_RADIUS, CollisionWorld, OrientedBox, Workspace
from brave6d.serve.limits import MAX_HEIGHT, MAX_WIDTH, fit_image_size, image_size_error
from brave6d.serve.reference import (
    ReferenceGeometryError,
    ReferenceMesh,
    ReferenceSettings,
    build_scene_reference,
    write_reference,
)
from brave6d.serve.renderer import DEPTH_MODES
from brave6d.serve.splat_check import check_splat, ply_vertex_count
from brave6d.training import ANTIALIASING_MODES

log = logging.getLogger(__name__)

FORMAT = "brave6d-bundle/1"
MANIFEST = "manifest.json"
SPLAT = "splat.ply"
SPLAT_VIEWER = "splat_viewer.ply"  # the splat for other viewers (the 3D filter baked in); absent in older bundles
SCENE = "scene.json"
OBJECTS = "objects.json"
HOLDOUT = "holdout.json"
HOLDOUT_IMAGES = "holdout"
MODELS = "models"
REFERENCE = "reference.ply"  # the reference geometry (brave6d.serve.reference); absent in older bundles
REQUIRED = (SPLAT, SCENE, OBJECTS, HOLDOUT)

Matrix4 = NDArray[np.float64]


class BundleError(DataError):
    """A bundle is missing, malformed, or does not match its manifest."""


def is_bundle(path: Path | str) -> bool:
    """Whether ``path`` is a bundle folder: it holds a :data:`MANIFEST` and a :data:`SPLAT`.

    Cheap (no file is read): the one test for "is this a bundle?" (serving a path, finding the
    bundle of episodes, a release's unpacked scene). :func:`load_bundle` then verifies it.
    """
    folder = Path(path)
    return (folder / MANIFEST).is_file() and (folder / SPLAT).is_file()


# ----------------------------------------------------------------------------- typed bundle
@dataclass(frozen=True)
class RenderDefaults:
    """How views are rendered unless a request says otherwise.

    The default size obeys the server's image-size cap (:mod:`brave6d.serve.limits`) like an explicit
    request: a larger one (a bundle exported from a large camera, or by an older exporter) is
    scaled down to fit, same aspect ratio, with a warning.
    """

    width: int
    height: int
    near: float = 0.01
    far: float = 100.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    depth_alpha_min: float = 0.5  # depth is 0 (no data) where the splat's alpha is below this
    # which depth a pixel reports: "median" (the surface that takes the transmittance across 0.5, as a
    # sensor sees one surface at an edge) or "expected" (alpha-weighted mean; a bundle without the key)
    depth_mode: str = "median"
    # how the splat was trained and must be drawn: "mip" (Mip-Splatting's 2D mip filter, the rasterizer's
    # antialiased mode; the PLY's filter_3d is applied whenever present) or "classic" (older bundles)
    antialiasing: str = "classic"

    def __post_init__(self) -> None:
        for name, choices in (("depth_mode", DEPTH_MODES), ("antialiasing", ANTIALIASING_MODES)):
            if (value := getattr(self, name)) not in choices:
                raise DataError(f"render.{name} must be one of {', '.join(choices)}, got {value!r}")
        width, height = fit_image_size(self.width, self.height)
        if (width, height) != (self.width, self.height):
            log.warning("render defaults %dx%d exceed the server's image-size cap %dx%d: using %dx%d",
                        self.width, self.height, MAX_WIDTH, MAX_HEIGHT, width, height)
            object.__setattr__(self, "width", width)
            object.__setattr__(self, "height", height)

    def to_json(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "near": self.near, "far": self.far,
                "background": list(self.background), "depth_alpha_min": self.depth_alpha_min,
                "depth_mode": self.depth_mode, "antialiasing": self.antialiasing}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> RenderDefaults:
        return cls(int(d["width"]), int(d["height"]), float(d.get("near", 0.01)), float(d.get("far", 100.0)),
                   tuple(float(x) for x in d.get("background", (0, 0, 0))),  # type: ignore[arg-type]
                   float(d.get("depth_alpha_min", 0.5)), str(d.get("depth_mode", "expected")),
                   str(d.get("antialiasing", "classic")))


@dataclass(frozen=True)
class BundleObject:
    """One annotated instance (``gt_id`` = its index in BOP's ``scene_gt`` lists)."""

    gt_id: int
    obj_id: int
    name: str
    world_T_obj: Matrix4
    model: str  # relative path of the model PLY (mm) inside the bundle
    diameter_mm: float
    class_name: str | None = None
    symmetries_discrete_mm: tuple[tuple[float, ...], ...] = ()
    symmetries_continuous: tuple[dict[str, Any], ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {"gt_id": self.gt_id, "obj_id": self.obj_id, "name": self.name, "class": self.class_name,
                "world_T_obj": np.asarray(self.world_T_obj).tolist(), "model": self.model,
                "diameter_mm": self.diameter_mm,
                "symmetries_discrete_mm": [list(m) for m in self.symmetries_discrete_mm],
                "symmetries_continuous": list(self.symmetries_continuous)}


@dataclass(frozen=True)
class HoldoutView:
    index: int
    view_id: str
    world_T_cam: Matrix4
    image: str | None = None  # relative path inside the bundle

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "view_id": self.view_id, "world_T_cam": self.world_T_cam.tolist(),
                "image": self.image}


@dataclass(frozen=True)
class Bundle:
    """A loaded (and verified) bundle."""

    root: Path
    manifest: dict[str, Any]
    name: str
    camera: PinholeCamera  # undistorted pinhole at the default render size
    render: RenderDefaults
    world: CollisionWorld
    objects: tuple[BundleObject, ...]
    holdout: tuple[HoldoutView, ...]
    start: dict[str, Any] = field(default_factory=dict)

    @property
    def splat_path(self) -> Path:
        return self.root / SPLAT

    @property
    def viewer_splat_path(self) -> Path | None:
        """The splat for other 3DGS viewers when the manifest lists one (:data:`SPLAT_VIEWER`); None
        for a bundle exported before it existed."""
        return self.root / SPLAT_VIEWER if SPLAT_VIEWER in self.manifest.get("files", {}) else None

    @property
    def reference_path(self) -> Path | None:
        """The reference geometry's file when the manifest lists one; None for a bundle exported
        without it (before it existed, or from a capture without depth)."""
        return self.root / REFERENCE if REFERENCE in self.manifest.get("files", {}) else None

    @property
    def source(self) -> BundleSource:
        """Where the bundle came from, as its manifest records it (:func:`bundle_source`)."""
        return bundle_source(self.manifest)

    def model_path(self, obj: BundleObject) -> Path:
        return self.root / obj.model

    def object_by(self, key: int | str) -> BundleObject:
        """Instance by ``gt_id`` (int) or by name (str); a name shared by several instances is refused."""
        if isinstance(key, int):
            for o in self.objects:
                if o.gt_id == key:
                    return o
            raise KeyError(f"no object instance with gt_id {key} (known: {[o.gt_id for o in self.objects]})")
        matches = [o for o in self.objects if o.name == key]
        if len(matches) == 1:
            return matches[0]
        if not matches:
            raise KeyError(f"no object named {key!r} (known: {[o.name for o in self.objects]})")
        raise KeyError(f"{len(matches)} instances are named {key!r}: give a gt_id instead")

    def summary(self) -> dict[str, Any]:
        """JSON description for clients (what ``GET /bundle`` returns)."""
        return {
            "format": self.manifest.get("format"), "name": self.name,
            "created": self.manifest.get("created"), "versions": self.manifest.get("versions", {}),
            "gaussians": self.manifest.get("gaussians"),
            "camera": self.camera.to_json(), "render": self.render.to_json(),
            "collision": {"boxes": [b.to_json() for b in self.world.boxes],
                          "workspace": self.world.workspace.to_json(),
                          "camera_radius": self.world.camera_radius},
            "objects": [o.to_json() for o in self.objects],
            "holdout": [h.to_json() for h in self.holdout],
            "start": self.start,
        }


@dataclass(frozen=True)
class BundleSource:
    """What identifies the scene and the training a bundle was made from, without a path of the
    machine that made it (``manifest.json``'s ``source``). A field the manifest does not record
    is None: bundles made before this record held only the builder's absolute paths, which are
    ignored."""

    scene: str | None = None
    splat: str | None = None  # the splat's path inside the scene directory (posix)
    splat_sha256: str | None = None
    metrics_sha256: str | None = None  # the training's splat/metrics.json
    holdout_sha256: str | None = None  # the training's splat/holdout.json (None: recomputed by the rule)

    def to_json(self) -> dict[str, Any]:
        return {"scene": self.scene, "splat": self.splat, "splat_sha256": self.splat_sha256,
                "metrics_sha256": self.metrics_sha256, "holdout_sha256": self.holdout_sha256}


def bundle_source(manifest: dict[str, Any]) -> BundleSource:
    """The :class:`BundleSource` a manifest records; what is absent, not a string, or an absolute
    path (a bundle made before this record: ``{"scene": "/home/...", "splat": "/home/..."}``) is None."""
    raw = manifest.get("source")
    if not isinstance(raw, dict):
        return BundleSource()

    def text(key: str) -> str | None:
        value = raw.get(key)
        if not isinstance(value, str) or value.startswith("/") or re.match(r"[A-Za-z]:[\\/]", value):
            return None
        return value

    def digest(key: str) -> str | None:
        value = raw.get(key)
        return value if isinstance(value, str) and _SHA256.fullmatch(value) else None

    splat = text("splat")
    return BundleSource(text("scene"), splat if splat is None or relative_path_problem(splat) is None else None,
                        digest("splat_sha256"), digest("metrics_sha256"), digest("holdout_sha256"))


# ----------------------------------------------------------------------------- adapters (one per source)
def find_splat_ply(scene: SceneDir) -> Path:
    """The trained splat of a scene: ``splat/point_cloud.ply``, else the newest
    ``splat/**/point_cloud*.ply`` (Inria's ``point_cloud/iteration_N/point_cloud.ply``), never the
    viewer PLY (``point_cloud_viewer.ply``: its filter is baked in, the server would apply it twice)."""
    direct = scene.splat_ply_path
    if direct.is_file():
        return direct
    viewer = scene.splat_viewer_ply_path.name
    candidates = sorted((p for p in scene.splat_dir.glob("**/point_cloud*.ply") if p.name != viewer),
                        key=lambda p: p.stat().st_mtime)
    if candidates:
        return candidates[-1]
    raise BraveError(f"{scene.splat_dir}: no trained splat (point_cloud.ply); train the scene first")


def read_annotation_instances(scene: SceneDir) -> list[dict[str, Any]]:
    """The annotated instances from ``annotation/objects.json`` (format ``brave6d-annotation/1``).

    Returns, in the annotation's instance order (= BOP ``gt_id`` order), dicts with ``obj_id``,
    ``name``, ``class``, ``world_T_obj`` (metres), ``mesh`` (absolute path), ``scale`` (mesh
    units to metres), ``symmetries_discrete`` (flattened 4x4, metres) and
    ``symmetries_continuous`` ({axis, offset (metres)}).
    """
    from brave6d.annotation import load_annotation  # the owner of objects.json

    annotation = load_annotation(scene)
    out = []
    for inst in annotation.instances:
        obj = annotation.object(inst.obj_id)
        out.append({
            "obj_id": inst.obj_id, "name": obj.name, "class": obj.class_name, "world_T_obj": inst.world_T_model,
            "mesh": obj.mesh, "scale": obj.scale,
            "symmetries_discrete": [np.asarray(m, dtype=np.float64).reshape(-1).tolist() for m in obj.symmetries_discrete],
            "symmetries_continuous": [{"axis": list(c.axis), "offset": list(c.offset)} for c in obj.symmetries_continuous],
        })
    return out


def holdout_frames(scene: SceneDir) -> list[tuple[FrameRecord, Matrix4]]:
    """``(frame record, world_T_cam)`` of the views held out of training, in frame order.

    The split is training's, read by :func:`brave6d.training.read_holdout` (``splat/holdout.json``;
    a scene trained before that file: the trainer's rule on the capture). No capture
    (``frames.jsonl``) or no hand-eye calibration: no views (with a warning). A corrupt
    ``frames.jsonl``, ``handeye.json`` or ``holdout.json``, or a split that names a frame the
    capture does not hold (or holds under another view id), is an error: a bundle silently
    without its holdout views would be scored on nothing.
    """
    from brave6d.core.calibration_io import camera_poses
    from brave6d.training import read_holdout

    for needed, what in ((scene.frames_path, "no capture"), (scene.handeye_path, "no hand-eye calibration")):
        if not needed.is_file():
            log.warning("%s: %s, so the bundle has no holdout views", needed, what)
            return []
    try:
        views = camera_poses(scene)
        split = read_holdout(scene)
    except DataError as exc:
        raise DataError(f"{exc}; the bundle's holdout views are read from it: repair it and export again") from None
    by_index = {r.index: (r, T) for r, T in views}
    out = []
    for held in split.views:
        found = by_index.get(held.index)
        if found is None or found[0].view_id != held.view_id:
            now = "is not in the capture" if found is None else f"is view {found[0].view_id!r} in the capture"
            raise DataError(f"{scene.holdout_split_path}: held-out frame {held.index} ({held.view_id}) {now} "
                            f"({scene.frames_path}): the capture changed since training; train the scene again")
        out.append(found)
    return out


def scene_camera(scene: SceneDir, spec: Any) -> PinholeCamera:
    """The pinhole camera of the undistorted images: the calibrated intrinsics without distortion
    (as the BOP export and the trainer use), else the spec's nominal camera (with a warning)."""
    from brave6d.core.calibration_io import read_intrinsics

    if scene.intrinsics_path.is_file():
        return read_intrinsics(scene).without_distortion()
    log.warning("%s: no calibrated intrinsics; using the spec's nominal camera", scene.intrinsics_path)
    return spec.camera.pinhole().without_distortion()


# ----------------------------------------------------------------------------- models
def load_model_m(path: Path) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """A bundle model (BOP PLY in mm) in metres: vertices and triangles."""
    from brave6d.annotation import read_ply_mesh

    mesh = read_ply_mesh(path)
    return mesh.vertices / 1000.0, mesh.faces


def _convert_mesh_to_mm(mesh: Path, scale: float, out: Path) -> NDArray[np.float64]:
    """Write ``mesh`` (any mesh format) scaled to millimetres as the bundle's model PLY; returns vertices (mm)."""
    from brave6d.annotation import load_mesh, write_ply_mesh

    source = load_mesh(mesh, colors=False)
    v = source.vertices * scale * 1000.0
    write_ply_mesh(out, v, source.faces, comment="BRAVE-6D bundle model (millimetres)")
    return v


def model_diameter(points: NDArray[np.float64]) -> float:
    """Largest distance between two points (the annotation stage's one implementation)."""
    from brave6d.annotation import model_diameter as diameter

    return diameter(points)


def _bop_models(scene: SceneDir) -> tuple[Path | None, dict[int, dict[str, Any]]]:
    """``(models folder, models_info)`` of the scene's BOP export, or ``(None, {})``."""
    from brave6d.annotation import BopLayout, read_models_info

    bop = BopLayout(scene.bop_dir)
    if not bop.models_info_path.is_file():
        return None, {}
    return bop.models_dir, read_models_info(bop.models_info_path)


# ----------------------------------------------------------------------------- export
@dataclass(frozen=True)
class ExportResult:
    root: Path
    gaussians: int
    objects: int
    holdout_views: int
    bytes: int
    models_from: str  # "bop" or "annotation"
    moved_aside: Path | None = None  # where ``force`` moved what was at ``root`` (it was not a bundle)
    reference_triangles: int | None = None  # the reference geometry's size; None: the bundle has none


def versions() -> dict[str, str]:
    """Versions of what makes and reads a bundle (``brave6d.core.provenance``)."""
    return software_versions(("brave6d", "torch", "numpy", "scipy", "plyfile", "open3d", "fastapi"))


def not_a_bundle(folder: Path) -> str | None:
    """Why export may not simply replace ``folder``, or None when it may: absent, empty, or a
    bundle holding nothing but the files its manifest lists (all of which export rewrites)."""
    if folder.is_symlink():
        return "is a symbolic link"
    if not folder.exists():
        return None
    if not folder.is_dir():
        return "is a file, not a bundle folder"
    if next(folder.iterdir(), None) is None:
        return None
    if not (folder / MANIFEST).is_file():
        return f"is a folder that is not a bundle (no {MANIFEST})"
    try:
        listed = set(read_bundle_manifest(folder)["files"])
    except BundleError as exc:
        return f"is a folder that is not a bundle ({exc})"
    extra = sorted(rel for p in folder.rglob("*") if (p.is_file() or p.is_symlink())
                   and (rel := p.relative_to(folder).as_posix()) not in listed and rel != MANIFEST)
    if extra:
        more = f" and {len(extra) - 1} more" if len(extra) > 1 else ""
        return f"is a bundle folder that also holds files its manifest does not list ({extra[0]}{more})"
    return None


def _protected_folders(scene: SceneDir) -> list[tuple[Path, str]]:
    """The folders an export must never replace or move aside, even with ``force``: the scene
    directory and the folders of the stages that made it (the export's own inputs)."""
    return [(scene.root, "the scene directory"), (scene.capture_dir, "the scene's capture"),
            (scene.calibration_dir, "the scene's calibration"), (scene.sparse_dir, "the scene's sparse model"),
            (scene.splat_dir, "the scene's splat"), (scene.annotation_dir, "the scene's annotation")]


def check_out(target: Path, scene: SceneDir, force: bool) -> bool:
    """Refuse an export to ``target`` that would lose data; True when ``target`` must be moved aside.

    The scene directory, its stage folders and anything containing them are refused even with
    ``force`` (the scene would be renamed away from under its own bundle); anything
    :func:`not_a_bundle` names is refused unless ``force``.
    """
    out = target.resolve()
    for folder, label in _protected_folders(scene):
        inside = folder.resolve()
        if out == inside or out in inside.parents:
            what = f"is {label}" if out == inside else f"contains {label} ({folder})"
            raise BraveError(f"{target}: --out {what}; the bundle needs a folder of its own "
                             f"(default {scene.bundle_dir})")
    blocker = next((p for p in (target.parent, *target.parent.parents) if p.exists() or p.is_symlink()), None)
    if blocker is not None and not blocker.is_dir():
        raise BraveError(f"{blocker}: is a file, so the bundle folder {target} cannot be made there")
    why = not_a_bundle(target)
    if why is not None and not force:
        raise BraveError(f"{target}: {why}; export replaces only a bundle folder: choose another --out, or pass "
                         f"--force to move it aside (to {target.name}.old-<time>, nothing is deleted)")
    return why is not None


def export_bundle(scene_dir: Path | str, out: Path | str | None = None, *, include_holdout_images: bool = True,
                  camera_radius: float = DEFAULT_CAMERA_RADIUS, width: int | None = None, height: int | None = None,
                  near: float | None = None, far: float | None = None,
                  background: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  depth_alpha_min: float = 0.5, force: bool = False, reference: bool = True,
                  reference_settings: ReferenceSettings | None = None) -> ExportResult:
    """Write the bundle of ``scene_dir`` (default ``<scene>/bundle``) atomically; see the module docstring.

    ``out`` is replaced only if it is absent, empty or a bundle; with ``force`` anything else there
    is moved aside (:func:`brave6d.core.atomic.move_aside`) once the new bundle is complete.
    ``reference``: build the reference geometry (:func:`reference_mesh`) with ``reference_settings``.
    ``near`` / ``far`` (None): the planes the splat was trained with, in the scene's units
    (:func:`brave6d.training.serve_planes`: 0.02 and 200 scene extents, about 0.01 and 100 m on the demo).
    """
    from brave6d.training import read_ply, write_viewer_ply

    scene = SceneDir(scene_dir)
    if not scene.spec_path.is_file():
        raise BraveError(f"{scene.spec_path}: not a scene directory (no scene.yaml)")
    spec = scene.load_spec()
    # absolute (not resolved: a symbolic link at --out must stay visible), so that "." has a name and a parent
    target = Path(os.path.abspath(out)) if out is not None else scene.bundle_dir
    size_error = image_size_error(width, height)
    if size_error is not None:
        raise BraveError(f"render {size_error} (the server's image-size cap)")
    if camera_radius < 0 or not np.isfinite(camera_radius):
        raise BraveError(f"camera radius must be a finite number >= 0, got {camera_radius}")
    if near is None or far is None:
        from brave6d.training import serve_planes

        trained_near, trained_far = serve_planes(scene.root)
        near = trained_near if near is None else near
        far = trained_far if far is None else far
    splat_src = find_splat_ply(scene)
    splat = read_ply(splat_src)
    check_splat(splat, splat_src)
    check_out(target, scene, force)  # fail fast; checked again just before the swap
    instances = read_annotation_instances(scene)
    camera = scene_camera(scene, spec)
    if width is not None or height is not None:
        camera = camera.scaled(width or camera.width, height or camera.height)
    bop_models, bop_info = _bop_models(scene)
    frames = holdout_frames(scene)
    ref_mesh = reference_mesh(scene, reference_settings) if reference else None

    moved: Path | None = None
    with staged_folder(target) as staging:
        shutil.copyfile(splat_src, staging / SPLAT)
        write_viewer_ply(staging / SPLAT_VIEWER, splat)
        objects, models_from = _export_objects(staging, instances, bop_models, bop_info)
        atomic_write_json(staging / OBJECTS, {
            "format": "brave6d-bundle-objects/1",
            "frame": "world = robot base frame; world_T_obj in metres maps model points (model file in mm "
                     "times 0.001) to the world; gt_id = index in BOP scene_gt lists",
            "objects": [o.to_json() for o in objects]})
        render = RenderDefaults(camera.width, camera.height, near, far, tuple(background), depth_alpha_min,  # type: ignore[arg-type]
                                antialiasing="mip" if splat.filter_3d is not None else "classic")
        boxes = [OrientedBox(b.name, b.matrix(), b.size) for b in spec.collision_boxes]
        atomic_write_json(staging / SCENE, {
            "format": FORMAT, "name": spec.name, "camera": camera.to_json(), "render": render.to_json(),
            "collision": {"boxes": [b.to_json() for b in boxes],
                          "workspace": {"min": list(spec.workspace.min), "max": list(spec.workspace.max)},
                          "camera_radius": camera_radius},
            "start": {"target": list(spec.capture.target), "distances_m": list(spec.capture.distances_m),
                      "min_elevation_deg": spec.capture.min_elevation_deg,
                      "max_elevation_deg": spec.capture.max_elevation_deg,
                      "azimuth_range_deg": list(spec.capture.azimuth_range_deg)},
            **({"reference": ref_mesh.record(REFERENCE)} if ref_mesh is not None else {}),
        })
        if ref_mesh is not None:
            write_reference(staging / REFERENCE, ref_mesh)
        holdout = []
        undistorted = _undistorted_rgb(scene) if include_holdout_images and frames else None
        for record, world_T_cam in frames:
            image = None
            if undistorted is not None:
                src = _holdout_image(undistorted, record)
                image = f"{HOLDOUT_IMAGES}/{src.name}"
                (staging / HOLDOUT_IMAGES).mkdir(exist_ok=True)
                shutil.copyfile(src, staging / image)
            holdout.append(HoldoutView(record.index, record.view_id, world_T_cam, image))
        atomic_write_json(staging / HOLDOUT, {"views": [h.to_json() for h in holdout]})
        files = _file_table(staging)
        atomic_write_json(staging / MANIFEST, {
            "format": FORMAT, "name": spec.name,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "source": _source_record(scene, spec.name, splat_src, files[SPLAT]["sha256"]).to_json(),
            "gaussians": splat.num_gaussians, "sh_degree": splat.sh_degree,
            "versions": versions(), "files": files})
        if check_out(target, scene, force):
            moved = move_aside(target)
            log.warning("%s was not a bundle: moved aside to %s", target, moved)
    size = sum(v["bytes"] for v in files.values())
    log.info("bundle written to %s (%d Gaussians, %d objects, %d holdout views, %.1f MB)", target,
             splat.num_gaussians, len(objects), len(holdout), size / 1e6)
    return ExportResult(target, splat.num_gaussians, len(objects), len(holdout), size, models_from, moved,
                        ref_mesh.stats.triangles if ref_mesh is not None else None)


def reference_mesh(scene: SceneDir, settings: ReferenceSettings | None = None) -> ReferenceMesh | None:
    """The scene's reference geometry (:func:`brave6d.serve.reference.build_scene_reference`), or
    None with a warning when the capture recorded no depth at all (an RGB-only capture: its bundle
    is scored on the splat's depth). A capture with depth that cannot be integrated is an error."""
    records = scene.frames() if scene.frames_path.is_file() else []
    if not any(r.depth for r in records):
        log.warning("%s: the capture recorded no depth, so the bundle has no reference geometry; scores of "
                    "its episodes use the splat's depth", scene.frames_path)
        return None
    try:
        return build_scene_reference(scene.root, settings)
    except ReferenceGeometryError as exc:
        raise ReferenceGeometryError(f"{exc}; export with --no-reference to serve the scene without it "
                                     "(scores then use the splat's depth)") from None


def _source_record(scene: SceneDir, name: str, splat: Path, splat_sha256: str) -> BundleSource:
    """What the manifest records of the bundle's source: names and digests, never a path of this
    machine (the manifest ships inside every release)."""
    def digest(path: Path) -> str | None:
        return file_sha256(path) if path.is_file() else None

    return BundleSource(scene=name, splat=splat.relative_to(scene.root).as_posix(), splat_sha256=splat_sha256,
                        metrics_sha256=digest(scene.metrics_path), holdout_sha256=digest(scene.holdout_split_path))


_NO_IMAGES = "repair the capture, or export with --no-holdout-images to leave the images out"


def _undistorted_rgb(scene: SceneDir) -> Callable[[FrameRecord], Path]:
    """``record -> path`` of the undistorted RGB frames (made once by the kernel's cache).

    A capture that cannot be undistorted is an error: holdout views silently without their
    images would look like a complete bundle. Leaving them out is ``include_holdout_images=False``.
    """
    from brave6d.core.undistort import ensure_undistorted

    try:
        return ensure_undistorted(scene).rgb_path
    except (DataError, OSError) as exc:
        raise DataError(f"cannot make the holdout images: {exc}; {_NO_IMAGES}") from None


def _holdout_image(undistorted: Callable[[FrameRecord], Path], record: FrameRecord) -> Path:
    """The undistorted image of holdout frame ``record``; a missing one is an error, not a gap."""
    src = undistorted(record)
    if not src.is_file():
        raise DataError(f"{src}: the undistorted image of holdout frame {record.index} ({record.view_id}) is "
                        f"missing; {_NO_IMAGES}")
    return src


def _export_objects(staging: Path, instances: list[dict[str, Any]], bop_models: Path | None,
                    bop_info: dict[int, dict[str, Any]]) -> tuple[list[BundleObject], str]:
    from brave6d.annotation import model_file

    models_dir = staging / MODELS
    models_dir.mkdir()
    done: dict[int, tuple[str, float, list, list]] = {}
    source = "bop" if bop_models is not None else "annotation"
    objects = []
    for gt_id, inst in enumerate(instances):
        obj_id = inst["obj_id"]
        if obj_id not in done:
            rel = f"{MODELS}/obj_{obj_id:06d}.ply"
            bop_file = model_file(bop_models, obj_id) if bop_models is not None else None
            if bop_file is not None and bop_file.is_file() and obj_id in bop_info:
                shutil.copyfile(bop_file, staging / rel)
                info = bop_info[obj_id]
                diameter = float(info["diameter"])
                discrete = [list(map(float, m)) for m in info.get("symmetries_discrete", [])]
                continuous = list(info.get("symmetries_continuous", []))
            else:
                verts_mm = _convert_mesh_to_mm(inst["mesh"], inst["scale"], staging / rel)
                diameter = model_diameter(verts_mm)
                discrete = []
                for m in inst["symmetries_discrete"]:
                    mm = np.asarray(m, dtype=np.float64).reshape(4, 4)
                    mm[:3, 3] *= 1000.0
                    discrete.append(mm.reshape(-1).tolist())
                continuous = [{"axis": list(s["axis"]), "offset": [1000.0 * float(o) for o in s.get("offset", (0, 0, 0))]}
                              for s in inst["symmetries_continuous"]]
            done[obj_id] = (rel, diameter, discrete, continuous)
        rel, diameter, discrete, continuous = done[obj_id]
        objects.append(BundleObject(gt_id, obj_id, inst["name"], inst["world_T_obj"], rel, diameter,
                                    inst.get("class"), tuple(tuple(m) for m in discrete), tuple(continuous)))
    return objects, source


def _file_table(root: Path) -> dict[str, dict[str, Any]]:
    table = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = path.relative_to(root).as_posix()
        if rel == MANIFEST:
            continue
        table[rel] = {"sha256": file_sha256(path), "bytes": path.stat().st_size}
    return table


# ----------------------------------------------------------------------------- read + verify
_SHA256 = re.compile(r"[0-9a-f]{64}")


def _kind(value: object) -> str:
    """How a JSON value is named in messages."""
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null",
            int: "an integer", float: "a number"}.get(type(value), type(value).__name__)


def _shown(value: object) -> str:
    """``value`` as a message shows it: its repr when short, else its kind."""
    text = repr(value)
    return text if len(text) <= 70 and not isinstance(value, (dict, list)) else _kind(value)


def read_bundle_json(root: Path | str, name: str) -> dict[str, Any]:
    """The JSON object in the bundle file ``root/name``; :class:`BundleError` naming the file when
    it is missing, not JSON, or not an object."""
    path = Path(root) / name
    try:
        data = read_json(path)
    except DataError as exc:
        raise BundleError(str(exc)) from None
    if not isinstance(data, dict):
        raise BundleError(f"{path}: must be a JSON object, got {_kind(data)}")
    return data


def bundle_scene_name(root: Path | str, scene: dict[str, Any]) -> str:
    """The scene's name from the bundle's ``scene.json`` object ``scene`` (default: the folder's name)."""
    name = scene.get("name", Path(root).name)
    if not isinstance(name, str):
        raise BundleError(f"{Path(root) / SCENE}: field 'name': a string is required, got {_kind(name)}")
    return name


def read_listed_objects(root: Path | str) -> list[dict[str, Any]]:
    """The ``objects`` of the bundle's ``objects.json`` with their ids and names checked (an integer
    ``obj_id`` >= 0, a string ``name``, ``class`` a string or absent), for listing a scene without
    loading it; :class:`BundleError` naming the file and the field otherwise."""
    path = Path(root) / OBJECTS
    objects = read_bundle_json(root, OBJECTS).get("objects", [])
    if not isinstance(objects, list):
        raise BundleError(f"{path}: field 'objects': a list is required, got {_kind(objects)}")
    for i, o in enumerate(objects):
        if not isinstance(o, dict):
            raise BundleError(f"{path}: field 'objects[{i}]': an object is required, got {_kind(o)}")
        obj_id, name, cls = o.get("obj_id"), o.get("name"), o.get("class")
        if isinstance(obj_id, bool) or not isinstance(obj_id, int) or obj_id < 0:
            raise BundleError(f"{path}: field 'objects[{i}].obj_id': an integer >= 0 is required, got {_shown(obj_id)}")
        if not isinstance(name, str) or (cls is not None and not isinstance(cls, str)):
            which, value = ("name", name) if not isinstance(name, str) else ("class", cls)
            raise BundleError(f"{path}: field 'objects[{i}].{which}': a string is required, got {_kind(value)}")
    return objects


def read_bundle_manifest(root: Path | str) -> dict[str, Any]:
    """The bundle's ``manifest.json``, its structure checked: an object of format :data:`FORMAT`
    whose ``files`` maps plain relative paths to ``{sha256: 64 lowercase hex digits, bytes: int >= 0}``.

    The one reader of the manifest (verify, load, the catalog's estimates, export's replace check):
    a malformed one raises :class:`BundleError` naming the file and the field. Files are not opened.
    """
    path = Path(root) / MANIFEST
    if not path.is_file():
        raise BundleError(f"{path}: no manifest; not a bundle (export one with 'brave6d export SCENE_DIR')")
    manifest = read_bundle_json(root, MANIFEST)
    if manifest.get("format") != FORMAT:
        raise BundleError(f"{path}: field 'format': unsupported bundle format {manifest.get('format')!r} (this "
                          f"server reads {FORMAT!r})")
    files = manifest.get("files")
    if not isinstance(files, dict):
        raise BundleError(f"{path}: field 'files': an object (file path -> {{sha256, bytes}}) is required, got "
                          f"{_kind(files) if 'files' in manifest else 'nothing'}")
    for rel, entry in files.items():
        field = f"{path}: field 'files[{rel!r}]"
        problem = relative_path_problem(rel)
        if problem is not None:
            raise BundleError(f"{field}': not a plain path inside the bundle ({problem})")
        if not isinstance(entry, dict):
            raise BundleError(f"{field}': an object {{sha256, bytes}} is required, got {_kind(entry)}")
        sha = entry.get("sha256")
        if not isinstance(sha, str) or _SHA256.fullmatch(sha) is None:
            raise BundleError(f"{field}.sha256': 64 lowercase hex digits are required, got {_shown(sha)}")
        size = entry.get("bytes")
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            raise BundleError(f"{field}.bytes': a size in bytes (an integer >= 0) is required, got {_shown(size)}")
    return manifest


def verify_manifest(root: Path | str) -> dict[str, Any]:
    """Read ``manifest.json`` (:func:`read_bundle_manifest`) and check every listed file's size and
    sha256; returns the manifest."""
    base = Path(root)
    if not base.is_dir():
        raise BundleError(f"{base}: bundle folder not found")
    path = base / MANIFEST
    manifest = read_bundle_manifest(base)
    files = manifest["files"]
    resolved_root = base.resolve()
    for rel, entry in files.items():
        p = (base / rel)
        if not p.resolve().is_relative_to(resolved_root):  # a link out of the folder
            raise BundleError(f"{path}: file {rel!r} lies outside the bundle")
        if not p.is_file():
            raise BundleError(f"{p}: listed in the manifest but missing")
        size = p.stat().st_size
        if size != entry["bytes"]:
            raise BundleError(f"{p}: size {size} bytes does not match the manifest ({entry['bytes']}); "
                              "the bundle was modified or is incomplete")
        digest = file_sha256(p)
        if digest != entry["sha256"]:
            raise BundleError(f"{p}: sha256 {digest[:12]}... does not match the manifest "
                              f"({str(entry['sha256'])[:12]}...); the bundle was modified or is corrupt")
    missing = [r for r in REQUIRED if r not in files]
    if missing:
        raise BundleError(f"{path}: the manifest does not list {missing}")
    return manifest


def _check_holdout_images(base: Path, holdout: tuple[HoldoutView, ...], listed: set[str]) -> None:
    """Every holdout image is a file the manifest lists and a whole 8-bit RGB PNG (header, pixel
    limit and every chunk's CRC: :mod:`brave6d.core.png_check`), else :class:`BundleError` naming it."""
    for h in holdout:
        if h.image is None:
            continue
        if not isinstance(h.image, str) or h.image not in listed:
            raise BundleError(f"{base / HOLDOUT}: holdout view {h.index}: image {h.image!r} is not in the manifest")
        problem = png_problem(base / h.image, "rgb", check="crc")
        if problem is not None:
            raise BundleError(f"{base / h.image}: holdout image of view {h.index}: {problem}")


def load_bundle(root: Path | str, verify: bool = True) -> Bundle:
    """Load a bundle; with ``verify`` (default) every checksum is checked first."""
    base = Path(root)
    manifest = verify_manifest(base) if verify else read_bundle_manifest(base)
    scene = read_bundle_json(base, SCENE)
    try:
        camera = PinholeCamera.from_json(scene["camera"])
        render = RenderDefaults.from_json(scene["render"])
        coll = scene["collision"]
        world = CollisionWorld(tuple(OrientedBox.from_json(b) for b in coll["boxes"]),
                               Workspace.from_json(coll["workspace"]),
                               float(coll.get("camera_radius", DEFAULT_CAMERA_RADIUS)))
        objs = read_bundle_json(base, OBJECTS)["objects"]
        objects = tuple(BundleObject(
            int(o["gt_id"]), int(o["obj_id"]), str(o["name"]),
            check_rigid(o["world_T_obj"], f"{OBJECTS}: objects[{i}].world_T_obj"), str(o["model"]),
            float(o["diameter_mm"]), o.get("class"),
            tuple(tuple(float(x) for x in m) for m in o.get("symmetries_discrete_mm", [])),
            tuple(o.get("symmetries_continuous", []))) for i, o in enumerate(objs))
        holdout = tuple(HoldoutView(int(h["index"]), str(h["view_id"]), check_rigid(h["world_T_cam"], "holdout view"),
                                    h.get("image")) for h in read_bundle_json(base, HOLDOUT)["views"])
        name, start = bundle_scene_name(base, scene), dict(scene.get("start", {}))
    except BundleError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, BraveError) as exc:
        raise BundleError(f"{base}: malformed bundle ({type(exc).__name__}: {exc})") from None
    splat = base / SPLAT
    if not splat.is_file():
        raise BundleError(f"{splat}: the bundle has no splat")
    try:
        count = ply_vertex_count(splat)
    except DataError as exc:
        raise BundleError(str(exc)) from None
    if count == 0:
        raise BundleError(f"{splat}: the splat holds no Gaussians; export the bundle again from a trained scene")
    listed = set(manifest["files"])
    for o in objects:
        if verify and o.model not in listed:
            raise BundleError(f"{base}: model {o.model} of object {o.name} is not in the manifest")
    if verify:
        _check_holdout_images(base, holdout, listed)
    return Bundle(base, manifest, name, camera, render, world, objects, holdout, start)

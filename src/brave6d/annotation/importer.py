"""Import a 3D-DAT annotation into ``<scene>/annotation/`` (world = robot base frame, metres).

Steps, all checks before any write: read and validate the 3D-DAT folder; load the mesh of every
annotated library object; pair its camera poses with the captured views as 3D-DAT pairs them
with its images, the ids as a cross-check (:mod:`brave6d.annotation.pairing`), and align its world frame
to the robot base (:mod:`brave6d.annotation.alignment`); assign stable BOP ``obj_id`` values to every
library id (sorted 3D-DAT ids, the saved map reused so ids never change; or, for a scene of a
dataset, the explicit ``obj_ids`` map of the dataset's object library); then write the meshes
of the annotated objects (content-addressed, never overwritten), then the commit point
``objects.json`` (with the alignment report; ``alignment.json`` is a readable copy). Library
objects that are not annotated keep their ``obj_id`` in the id map but are no object of the
annotation (no mesh copied, no BOP model). A failure at any check writes nothing.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from brave6d.annotation.alignment import AlignmentOptions, AlignmentReport, apply_alignment
from brave6d.annotation.models import load_mesh
from brave6d.annotation.pairing import pair_and_align
from brave6d.annotation.store import (
    AnnotatedInstance,
    AnnotatedObject,
    Annotation,
    alignment_path,
    meshes_dir,
    read_id_map,
    write_annotation,
)
from brave6d.annotation.threedat import LibraryEntry, ThreeDatScene, ThreeDatId, id_key, id_sort_key, read_threedat
from brave6d.core.atomic import atomic_write_json, staged_folder
from brave6d.core.calibration_io import camera_poses, read_intrinsics
from brave6d.core.errors import BraveError, DataError
from brave6d.core.layout import SceneDir

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImportResult:
    """What an import did."""

    annotation: Annotation
    alignment: AlignmentReport
    matched_by: str
    warnings: tuple[str, ...]

    @property
    def n_objects(self) -> int:
        return len(self.annotation.objects)

    @property
    def n_instances(self) -> int:
        return len(self.annotation.instances)


def assign_obj_ids(ids: Sequence[ThreeDatId], previous: dict[str, int]) -> dict[str, int]:
    """BOP obj_ids for 3D-DAT ids: ids already in ``previous`` keep theirs; new ones, in sorted
    id order, get the next free integers (starting at 1). Returns the full map (with old ids)."""
    mapping = dict(previous)
    used = set(mapping.values())
    if len(used) != len(mapping):
        raise DataError("saved id map gives two 3D-DAT ids the same obj_id")
    next_id = max(used, default=0) + 1
    for oid in sorted(ids, key=id_sort_key):
        if id_key(oid) not in mapping:
            mapping[id_key(oid)] = next_id
            next_id += 1
    return mapping


def explicit_obj_ids(ids: Sequence[ThreeDatId], obj_ids: Mapping[str, int], where: str) -> dict[str, int]:
    """The id map given by ``obj_ids`` (3D-DAT id -> obj_id, e.g. a dataset's object library) for
    the library ``ids``: every id must be in it, with distinct positive obj_ids."""
    missing = [id_key(i) for i in ids if id_key(i) not in obj_ids]
    if missing:
        raise DataError(f"{where}: library ids {missing} have no obj_id in the given map "
                        f"(it has {sorted(obj_ids)})")
    mapping = {id_key(i): obj_ids[id_key(i)] for i in ids}
    if not all(isinstance(v, int) and v > 0 for v in mapping.values()):
        raise DataError(f"{where}: the given obj_ids must be positive integers, got {mapping}")
    if len(set(mapping.values())) != len(mapping):
        raise DataError(f"{where}: the given map gives two library ids the same obj_id ({mapping})")
    return mapping


def import_threedat(dat_dir: Path | str, scene_dir: Path | str, scene_id: str | None = None,
                    options: AlignmentOptions = AlignmentOptions(),
                    obj_ids: Mapping[str, int] | None = None) -> ImportResult:
    """Import one annotated 3D-DAT scene into ``scene_dir`` (see the module docstring).

    ``obj_ids`` (3D-DAT id -> BOP obj_id) fixes the ids, e.g. a dataset's library ids so that an
    object has one obj_id in every scene; without it ids are assigned and kept per scene.
    """
    dat = read_threedat(dat_dir, scene_id)
    scene = SceneDir(scene_dir)
    lib_name = dat.config.show(dat.config.object_library_file)
    annotated = annotated_entries(dat)
    for entry in annotated:  # every annotated object's mesh must load before anything is written
        load_mesh(_mesh_of(entry), f"{lib_name}: entry {entry.entry} (id {entry.id!r})", colors=False)

    captured = camera_poses(scene)
    if not captured:
        raise DataError(f"{scene.frames_path}: no captured frames; capture and calibrate the scene before importing")
    warnings = [*dat.warnings, *_camera_warnings(dat, scene)]
    paired = pair_and_align(dat, captured, options)
    report, how = paired.report, paired.pairing.how
    warnings += paired.warnings
    log.info("%s (matched by %s)", report.summary(), how)
    world_poses = apply_alignment(report.target_T_source, [o.world_T_model for o in dat.objects])

    if obj_ids is None:
        id_map = assign_obj_ids([e.id for e in dat.library], read_id_map(scene))
    else:
        id_map = explicit_obj_ids([e.id for e in dat.library], obj_ids, lib_name)
        previous = read_id_map(scene)
        changed = sorted(k for k, v in id_map.items() if previous.get(k, v) != v)
        if changed:
            log.warning("%s: obj_ids of %s change to the given map's", scene.root, changed)
    objects = [_annotated_object(e, id_map[e.key], scene) for e in annotated]
    instances = [AnnotatedInstance(obj_id=id_map[id_key(o.object_id)], threedat_id=o.object_id,
                                   world_T_model=T, entry=o.entry) for o, T in zip(dat.objects, world_poses)]
    pairing = {"matched_by": how, "cross_checked_by": list(paired.pairing.agrees),
               "paired_views": {p.frame_id: r.index for p, r, _ in paired.pairing.views}}
    source = {"config": str(dat.config.path), "scene_id": dat.scene_id,
              "files": {k: str(v) for k, v in dat.files.items()},
              "imported_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **pairing, "warnings": warnings}
    alignment = {**pairing, **report.to_json()}
    annotation = Annotation(tuple(sorted(objects, key=lambda o: o.obj_id)), tuple(instances), id_map, source,
                            alignment)

    _copy_meshes(annotated, objects)
    write_annotation(scene, annotation)  # the commit point
    atomic_write_json(alignment_path(scene), alignment)  # a readable copy of the report
    _remove_unused_meshes(scene, objects)
    for w in warnings:
        log.warning("%s", w)
    return ImportResult(annotation, report, how, tuple(warnings))


def annotated_entries(dat: ThreeDatScene) -> list[LibraryEntry]:
    """The library entries with at least one annotated instance, in library order."""
    used = {id_key(o.object_id) for o in dat.objects}
    return [e for e in dat.library if e.key in used]


def _mesh_of(entry: LibraryEntry) -> Path:
    if entry.mesh is None:  # read_object_poses refuses instances of mesh-less entries
        raise DataError(f"library entry {entry.entry} (id {entry.id!r}) has no mesh")
    return entry.mesh


def _mesh_digest(entry: LibraryEntry) -> str:
    h = hashlib.sha256()
    mesh = _mesh_of(entry)
    for sibling in sorted(mesh.parent.glob(mesh.stem + ".*")):
        if sibling.is_file():
            h.update(sibling.name.encode())
            h.update(sibling.read_bytes())
    return h.hexdigest()[:16]


def _annotated_object(entry: LibraryEntry, obj_id: int, scene: SceneDir) -> AnnotatedObject:
    target = meshes_dir(scene) / _mesh_digest(entry) / _mesh_of(entry).name
    return AnnotatedObject(
        obj_id=obj_id, threedat_id=entry.id, name=entry.display_name, mesh=target, scale=entry.scale,
        class_name=entry.class_name, description=entry.description,
        symmetries_discrete=entry.symmetries_discrete, symmetries_continuous=entry.symmetries_continuous)


def _copy_meshes(library: Sequence[LibraryEntry], objects: Sequence[AnnotatedObject]) -> None:
    """Copy each mesh (and same-stem sidecars) into its content-addressed folder, once."""
    for entry, obj in zip(library, objects):
        folder = obj.mesh.parent
        if obj.mesh.is_file():
            continue  # same content already there (the folder name is its digest)
        mesh = _mesh_of(entry)
        with staged_folder(folder) as staging:  # whole or absent, like every folder the project writes
            for sibling in mesh.parent.glob(mesh.stem + ".*"):
                if sibling.is_file():
                    shutil.copy2(sibling, staging / sibling.name)


def _remove_unused_meshes(scene: SceneDir, objects: Sequence[AnnotatedObject]) -> None:
    keep = {o.mesh.parent.name for o in objects}
    root = meshes_dir(scene)
    for folder in root.iterdir() if root.is_dir() else ():
        if folder.is_dir() and folder.name not in keep:
            shutil.rmtree(folder, ignore_errors=True)


def _camera_warnings(dat: ThreeDatScene, scene: SceneDir) -> list[str]:
    """Differences between 3D-DAT's camera.yaml and the calibrated pinhole camera (warnings only:
    object poses are in the world frame and do not depend on it)."""
    try:
        calibrated = read_intrinsics(scene).without_distortion()
    except BraveError:
        return []
    cam = dat.camera
    out: list[str] = []
    if (cam.width, cam.height) != (calibrated.width, calibrated.height):
        out.append(f"3D-DAT camera.yaml is {cam.width}x{cam.height}, the capture is "
                   f"{calibrated.width}x{calibrated.height}")
    elif (abs(cam.fx / calibrated.fx - 1) > 0.01 or abs(cam.fy / calibrated.fy - 1) > 0.01
          or abs(cam.cx - calibrated.cx) > 2 or abs(cam.cy - calibrated.cy) > 2):
        out.append(f"3D-DAT camera.yaml (fx={cam.fx:.1f}, fy={cam.fy:.1f}, cx={cam.cx:.1f}, cy={cam.cy:.1f}) differs "
                   f"from the calibrated camera (fx={calibrated.fx:.1f}, fy={calibrated.fy:.1f}, "
                   f"cx={calibrated.cx:.1f}, cy={calibrated.cy:.1f})")
    return out


def import_summary(result: ImportResult) -> dict[str, Any]:
    """Key figures of an import (for the CLI and the demo)."""
    return {"objects": result.n_objects, "instances": result.n_instances, "views": result.alignment.frames,
            "aligned": result.alignment.applied, "residual_rms_mm": result.alignment.rms_mm,
            "residual_rms_deg": result.alignment.rms_deg, "matched_by": result.matched_by}

"""The imported annotation of a scene: ``<scene>/annotation/objects.json`` (+ ``meshes/``).

``objects.json`` is the single commit point of an import. It holds the object table (BOP
``obj_id`` <-> 3D-DAT id, name, class, mesh copied under ``annotation/meshes/``, scale to
metres, symmetries in metres), the id map (every 3D-DAT id ever given an ``obj_id`` here, so
ids never change on re-import), the annotated instances with ``world_T_model`` in the robot
base frame (metres) and a summary of the frame alignment (full report: ``alignment.json``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.annotation.threedat import ContinuousSymmetry, ThreeDatId, id_key
from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.core.errors import DataError, NonRigidTransformError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import check_rigid

FORMAT = "brave6d-annotation/1"
Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class AnnotatedObject:
    """An object model: BOP ``obj_id``, its 3D-DAT id, mesh (absolute path) and scale to metres."""

    obj_id: int
    threedat_id: ThreeDatId
    name: str
    mesh: Path
    scale: float
    class_name: str | None = None
    description: str | None = None
    symmetries_discrete: tuple[Matrix4, ...] = ()
    symmetries_continuous: tuple[ContinuousSymmetry, ...] = ()


@dataclass(frozen=True)
class AnnotatedInstance:
    """One annotated instance: ``world_T_model`` (robot base frame, metres) of object ``obj_id``."""

    obj_id: int
    threedat_id: ThreeDatId
    world_T_model: Matrix4
    entry: int = 0


@dataclass(frozen=True)
class Annotation:
    """Everything ``objects.json`` holds."""

    objects: tuple[AnnotatedObject, ...]
    instances: tuple[AnnotatedInstance, ...]
    id_map: dict[str, int]
    source: dict[str, Any] = field(default_factory=dict)
    alignment: dict[str, Any] = field(default_factory=dict)

    def object(self, obj_id: int) -> AnnotatedObject:
        for obj in self.objects:
            if obj.obj_id == obj_id:
                return obj
        raise KeyError(obj_id)


def objects_path(scene: SceneDir) -> Path:
    return scene.objects_path


def alignment_path(scene: SceneDir) -> Path:
    return scene.alignment_path


def meshes_dir(scene: SceneDir) -> Path:
    return scene.annotation_meshes_dir


def read_id_map(scene: SceneDir) -> dict[str, int]:
    """The saved 3D-DAT id -> obj_id map (empty before the first import)."""
    path = objects_path(scene)
    if not path.exists():
        return {}
    data = read_json(path)
    id_map = data.get("id_map") if isinstance(data, dict) else None
    if not isinstance(id_map, dict) or not all(isinstance(v, int) and v > 0 for v in id_map.values()):
        raise DataError(f"{path}: field 'id_map' is missing or malformed (3D-DAT id -> positive obj_id)")
    return {str(k): int(v) for k, v in id_map.items()}


def write_annotation(scene: SceneDir, annotation: Annotation) -> Path:
    """Write ``objects.json`` atomically (mesh paths stored relative to ``annotation/``)."""
    root = scene.annotation_dir.resolve()
    data = {
        "format": FORMAT,
        "frame": "world = robot base frame; metres; world_T_model maps model points (mesh units x scale) to world",
        "source": annotation.source,
        "id_map": dict(sorted(annotation.id_map.items(), key=lambda kv: kv[1])),
        "objects": [_object_json(o, root) for o in annotation.objects],
        "instances": [{"obj_id": i.obj_id, "threedat_id": i.threedat_id, "entry": i.entry,
                       "world_T_model": np.asarray(i.world_T_model).tolist()} for i in annotation.instances],
        "alignment": annotation.alignment,
    }
    return atomic_write_json(objects_path(scene), data)


def _object_json(obj: AnnotatedObject, root: Path) -> dict[str, Any]:
    mesh = obj.mesh.resolve()
    try:
        mesh_text = str(mesh.relative_to(root))
    except ValueError:
        mesh_text = str(mesh)
    return {
        "obj_id": obj.obj_id, "threedat_id": obj.threedat_id, "name": obj.name, "class": obj.class_name,
        "description": obj.description, "mesh": mesh_text, "scale": obj.scale,
        "symmetries_discrete": [np.asarray(m).reshape(-1).tolist() for m in obj.symmetries_discrete],
        "symmetries_continuous": [{"axis": list(s.axis), "offset": list(s.offset)} for s in obj.symmetries_continuous],
    }


def load_annotation(scene: SceneDir) -> Annotation:
    """Read ``objects.json``; errors name the file and the field."""
    path = objects_path(scene)
    if not path.exists():
        raise DataError(f"{path}: no imported annotation; run "
                        f"'brave6d annotate import-3ddat DAT_DIR {scene.root}' first")
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise DataError(f"{path}: not a BRAVE-6D annotation file (expected format {FORMAT!r})")
    try:
        objects = tuple(_object_from_json(o, scene.annotation_dir) for o in data["objects"])
        known = {o.obj_id for o in objects}
        instances = []
        for n, item in enumerate(data["instances"]):
            if item["obj_id"] not in known:
                raise ValueError(f"instances[{n}]: obj_id {item['obj_id']} is not in 'objects'")
            instances.append(AnnotatedInstance(
                obj_id=int(item["obj_id"]), threedat_id=item["threedat_id"], entry=int(item.get("entry", 0)),
                world_T_model=check_rigid(item["world_T_model"], f"instances[{n}].world_T_model")))
        id_map = {str(k): int(v) for k, v in data["id_map"].items()}
    except (KeyError, TypeError, ValueError, NonRigidTransformError) as exc:
        raise DataError(f"{path}: malformed annotation ({type(exc).__name__}: {exc})") from None
    return Annotation(objects, tuple(instances), id_map, data.get("source", {}), data.get("alignment", {}))


def _object_from_json(item: dict[str, Any], root: Path) -> AnnotatedObject:
    mesh = Path(item["mesh"])
    return AnnotatedObject(
        obj_id=int(item["obj_id"]), threedat_id=item["threedat_id"], name=str(item["name"]),
        mesh=mesh if mesh.is_absolute() else (root / mesh).resolve(), scale=float(item["scale"]),
        class_name=item.get("class"), description=item.get("description"),
        symmetries_discrete=tuple(check_rigid(np.reshape(m, (4, 4)), "symmetry")
                                  for m in item.get("symmetries_discrete", [])),
        symmetries_continuous=tuple(ContinuousSymmetry(tuple(s["axis"]), tuple(s.get("offset", (0, 0, 0))))
                                    for s in item.get("symmetries_continuous", [])),
    )


def find_object(annotation: Annotation, threedat_id: ThreeDatId) -> AnnotatedObject:
    """The object with this 3D-DAT id."""
    key = id_key(threedat_id)
    for obj in annotation.objects:
        if id_key(obj.threedat_id) == key:
            return obj
    raise KeyError(key)

"""A dataset's captured scenes: what they bring from the robot, decided from their files.

A ``dir`` scene of ``dataset.yaml`` was captured, calibrated and annotated at a robot, by people
(``brave6d capture run --robot ur:HOST --camera oak``, ``brave6d calibrate all``, ``brave6d annotate
import-3ddat``). ``dataset run`` never runs those stages for it: its jobs run unattended, on
cluster nodes far from any robot, and no simulator knows the scene's true poses. The driver looks
at the scene directory's files instead (:func:`check_rig_stage`) and records each of
:data:`RIG_STAGES` ``done`` when its outputs are there, or ``failed`` with one line naming the scene,
what is missing and the command that makes it; only a scene with all three gets a job, which
runs its training and export. Every run looks again, so a scene annotated since the last run goes on.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from brave6d.core.dataset_spec import Dataset, DatasetScene, scene_fingerprint
from brave6d.core.errors import BraveError, DataError
from brave6d.core.layout import SceneDir

#: The stages of a captured scene that happen at the robot, in pipeline order: never run by ``dataset run``.
RIG_STAGES = ("calibrate", "capture", "annotate")
#: What a captured scene's job runs: everything after the rig stages.
CAPTURED_JOB_STAGES = ("train", "export")

_BEFORE = "before the cluster can train it"


def captured_fingerprint(scene: DatasetScene) -> str:
    """The fingerprint of a captured scene: its merged spec and obj_ids (as a simulated scene's) and
    where it lies, so that another folder under the same name is not taken for this one."""
    text = f"{scene_fingerprint(scene.spec, scene.obj_ids)} {scene.dir}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def check_rig_stage(scene: DatasetScene, stage: str, dataset: Dataset) -> dict[str, Any]:
    """The figures of ``stage`` (one of :data:`RIG_STAGES`) of captured ``scene``, read from its files;
    :class:`BraveError` naming the scene, what is missing and how to make it when they are not there."""
    assert scene.dir is not None, f"{scene.name} is not a captured scene"
    root = SceneDir(scene.dir)
    if stage == "calibrate":
        return _calibration(scene.name, root)
    if stage == "capture":
        return _capture(scene.name, root)
    if stage == "annotate":
        return _annotation(scene.name, root, dataset)
    raise ValueError(f"{stage!r} is not a rig stage ({', '.join(RIG_STAGES)})")


def _rel(root: SceneDir, path: Path) -> str:
    return path.relative_to(root.root).as_posix()


def _calibration(name: str, root: SceneDir) -> dict[str, Any]:
    for path in (root.intrinsics_path, root.handeye_path):
        if not path.is_file():
            raise BraveError(f"scene {name}: no calibration ({_rel(root, path)}); calibrate it at the robot with "
                             f"'brave6d calibrate all {root.root} --robot ur:HOST --camera oak' {_BEFORE}")
    return {"calibration": "in the scene directory"}


def _capture(name: str, root: SceneDir) -> dict[str, Any]:
    fix = f"capture it at the robot with 'brave6d capture run {root.root} --robot ur:HOST --camera oak' {_BEFORE}"
    try:
        frames = len(root.frames()) if root.frames_path.is_file() else 0
    except DataError as exc:
        raise BraveError(f"scene {name}: {exc}") from None
    if frames == 0 or not root.camera_path.is_file():
        missing = root.frames_path if frames == 0 else root.camera_path
        raise BraveError(f"scene {name}: no capture ({_rel(root, missing)}); {fix}")
    return {"frames": frames}


def _annotation(name: str, root: SceneDir, dataset: Dataset) -> dict[str, Any]:
    """The imported annotation, whose obj_ids must be the library's (one obj_id per object in every scene)."""
    from brave6d.annotation import load_annotation

    again = (f"'brave6d annotate import-3ddat DAT_DIR {root.root} --dataset {dataset.spec.source}' "
             "(3D-DAT object ids = the library's names)")
    if not root.annotation_dir.is_dir():
        raise BraveError(f"scene {name}: no annotation ({_rel(root, root.annotation_dir)}/); annotate it in 3D-DAT "
                         f"and import it with {again} {_BEFORE}")
    try:
        annotation = load_annotation(root)
    except DataError as exc:  # its message names the file and what to run
        raise BraveError(f"scene {name}: {exc}") from None
    library = dataset.spec.obj_ids()
    for obj in annotation.objects:
        key = str(obj.threedat_id) if str(obj.threedat_id) in library else obj.name
        if key not in library:
            raise BraveError(f"scene {name}: the annotation in {root.annotation_dir} has object {obj.name!r} "
                             f"(3D-DAT id {obj.threedat_id}), which the library of {dataset.spec.source} does not "
                             f"have; add it to the library or annotate the scene again")
        if library[key] != obj.obj_id:
            raise BraveError(f"scene {name}: the annotation in {root.annotation_dir} gives {key!r} obj_id "
                             f"{obj.obj_id}, the library of {dataset.spec.source} gives {library[key]}; "
                             f"import it again with {again}")
    return {"objects": len(annotation.objects), "instances": len(annotation.instances)}

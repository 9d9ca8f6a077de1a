"""A dataset's work directory: ``dataset.yaml``, ``objects/``, ``scenes/<name>/``, ``status/``.

:func:`prepare_workdir` (the ``init`` stage of every scene, in the driver) creates each simulated
scene's directory from its merged scene spec (``--quick``: the demo's miniature capture), and
writes ``WORKDIR/dataset.yaml``: the dataset spec with its library meshes copied to
``objects/<name>/`` and its simulated scenes pointing at ``scenes/<name>/scene.yaml``. A captured
scene (a ``dir`` entry) is used where it lies, not copied (its frames are gigabytes): the work
directory's ``dataset.yaml`` names its folder by absolute path, and :func:`scene_root` is where
every reader of a work directory (the jobs, ``dataset status`` / ``report``, ``release build``)
finds a scene. Its ``init`` checks what it brings from the robot (:mod:`brave6d.dataset.captured`).

A scene directory is tied to the fingerprint of what it was made from: if the scene spec, its
meshes or the library's obj_ids change (or a captured scene's folder), its ``init`` fails,
naming the scene, rather than mixing old outputs with a new spec.
"""

from __future__ import annotations

import filecmp
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

from brave6d.core.atomic import atomic_write_text, move_aside
from brave6d.core.dataset_spec import Dataset, DatasetScene, load_dataset_spec, parse_dataset_spec, scene_fingerprint
from brave6d.core.errors import BraveError, SpecError
from brave6d.core.layout import SceneDir, init_scene_dir, mesh_files
from brave6d.core.run_context import QUICK_CAPTURE  # the miniature capture of `--quick` runs
from brave6d.core.spec import SceneSpec, spec_to_yaml
from brave6d.core.yaml_io import read_yaml
from brave6d.dataset.captured import RIG_STAGES, captured_fingerprint, check_rig_stage
from brave6d.dataset.status import live_scene_holder, mark, read_scene_status

#: The work directory's copy of the dataset spec.
WORKDIR_DATASET = "dataset.yaml"


def scene_dir(workdir: Path, name: str) -> SceneDir:
    """Where the work directory makes simulated scene ``name``: ``WORKDIR/scenes/<name>``."""
    return SceneDir(Path(workdir) / "scenes" / name)


def scene_root(workdir: Path, scene: DatasetScene) -> SceneDir:
    """Where a scene of the work directory lives: its captured folder, else :func:`scene_dir`."""
    return SceneDir(scene.dir) if scene.dir is not None else scene_dir(workdir, scene.name)


def load_workdir_dataset(workdir: Path | str) -> Dataset:
    """``WORKDIR/dataset.yaml``, loaded with the captured scene directories it names allowed where they lie.

    Only ``dataset run`` writes that file, after checking each folder against the user's
    dataset folder and ``--scene-dir`` flags (:func:`prepare_workdir`); so a work directory is
    read without those flags again. A user's own ``dataset.yaml`` never gets this (it is loaded with
    :func:`brave6d.core.dataset_spec.load_dataset_spec` and the user's flags).
    """
    path = Path(workdir) / WORKDIR_DATASET
    spec = parse_dataset_spec(read_yaml(path, error=SpecError), path)
    folders = [spec.resolve(s.dir) for s in spec.scenes if s.dir is not None]
    return load_dataset_spec(path, scene_dirs=[f for f in folders if f.is_dir()])  # a missing one: named there


def scene_spec_for_run(scene: DatasetScene, quick: bool) -> SceneSpec:
    """The spec a scene directory is made from: every mesh an absolute path, so it can be written
    anywhere (``quick``: the miniature capture)."""
    spec = scene.spec
    update: dict[str, object] = {
        key: [m.model_copy(update={"mesh": spec.resolve(m.mesh).resolve()}) for m in getattr(spec, key)]
        for key in ("static_meshes", "objects")}
    if quick:
        update["capture"] = spec.capture.model_copy(update=QUICK_CAPTURE)
    return spec.model_copy(update=update)


def init_scene(workdir: Path, scene: DatasetScene, quick: bool) -> str:
    """The ``init`` stage of one scene: ``"done"``, ``"reused"``, ``"failed"`` (recorded with its error) or
    ``"busy"`` (a job runs the scene now: its record is that job's to write, so nothing is written)."""
    if live_scene_holder(workdir, scene.name) is not None:
        return "busy"
    spec = scene_spec_for_run(scene, quick)
    fingerprint = scene_fingerprint(spec, scene.obj_ids)
    status = read_scene_status(workdir, scene.name, scene.scene_id)
    target = scene_dir(workdir, scene.name)
    if status.fingerprint and status.fingerprint != fingerprint:
        mark(workdir, status, "init", "failed", error=(
            f"{scene.spec_file}: the scene spec, its meshes, the library's obj_ids or --quick changed since "
            f"{target.root} was made; move that folder and {workdir}/status/{scene.name}.json aside "
            "(or use another WORKDIR) to run it again"))
        return "failed"
    if status.done("init") and target.spec_path.is_file():
        return "reused"
    try:
        target.root.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=target.root, prefix=".init-") as tmp:
            merged = Path(tmp) / "scene.yaml"  # library meshes are absolute paths in the merged spec
            merged.write_text(spec_to_yaml(spec), encoding="utf-8")
            init_scene_dir(target.root, merged)
    except BraveError as exc:
        mark(workdir, status, "init", "failed", error=str(exc))
        return "failed"
    status.fingerprint = fingerprint
    mark(workdir, status, "init", "done", seconds=0.0, figures={"objects": len(spec.objects), "scene_id": scene.scene_id})
    return "done"


def init_captured(workdir: Path, scene: DatasetScene, dataset: Dataset) -> str:
    """The ``init`` stage of a captured scene, then its rig stages from its files
    (:mod:`brave6d.dataset.captured`): ``"done"``, ``"reused"``, ``"missing"`` (a rig stage's outputs are
    not there: recorded ``failed`` with what is missing), ``"failed"`` or ``"busy"`` (as :func:`init_scene`)."""
    if live_scene_holder(workdir, scene.name) is not None:
        return "busy"
    fingerprint = captured_fingerprint(scene)
    status = read_scene_status(workdir, scene.name, scene.scene_id)
    if status.fingerprint and status.fingerprint != fingerprint:
        mark(workdir, status, "init", "failed", error=(
            f"{scene.spec_file}: the scene's spec, the library's obj_ids or its folder changed since its stages "
            f"ran; move {workdir}/status/{scene.name}.json aside (or use another WORKDIR) to run it again"))
        return "failed"
    result = "reused"
    if not status.done("init"):
        status.fingerprint = fingerprint
        mark(workdir, status, "init", "done", seconds=0.0,
             figures={"objects": len(scene.spec.objects), "scene_id": scene.scene_id, "captured in": str(scene.dir)})
        result = "done"
    for stage in RIG_STAGES:
        try:
            figures = check_rig_stage(scene, stage, dataset)
        except BraveError as exc:
            if status.stages.get(stage, {}).get("error") != str(exc):
                mark(workdir, status, stage, "failed", error=str(exc))
            result = "missing"
            continue
        if not status.done(stage):
            mark(workdir, status, stage, "done", seconds=0.0, figures=figures)
    return result


def write_workdir_dataset(dataset: Dataset, workdir: Path) -> Path:
    """Write ``WORKDIR/dataset.yaml`` (module docstring); a different previous one is moved aside."""
    workdir = Path(workdir)
    data = dataset.spec.model_dump(mode="json", exclude={"source"})
    for item, obj in zip(data["objects"], dataset.spec.objects):
        src = dataset.spec.resolve(obj.mesh).resolve()
        folder = workdir / "objects" / obj.name
        folder.mkdir(parents=True, exist_ok=True)
        for sibling in mesh_files(src):
            if not ((folder / sibling.name).is_file() and filecmp.cmp(sibling, folder / sibling.name, shallow=False)):
                shutil.copy2(sibling, folder / sibling.name)
        item["mesh"] = f"objects/{obj.name}/{src.name}"
    data["scenes"] = [{"dir": str(s.dir)} if s.dir is not None else {"spec": f"scenes/{s.name}/scene.yaml"}
                      for s in dataset.scenes]
    import yaml

    text = yaml.safe_dump(data, sort_keys=False)
    path = workdir / WORKDIR_DATASET
    if path.is_file() and path.read_text(encoding="utf-8") != text:
        move_aside(path)
    atomic_write_text(path, text)
    load_workdir_dataset(workdir)  # the copy must validate like the source
    return path


def prepare_workdir(dataset_file: Path, workdir: Path, quick: bool = False, mesh_dirs: Sequence[Path | str] = (),
                    scene_dirs: Sequence[Path | str] = ()) -> tuple[Dataset, dict[str, str]]:
    """Load the dataset spec, init every scene, write ``WORKDIR/dataset.yaml``; returns the
    dataset and each scene's init result (``done``, ``reused``, ``missing``, ``failed`` or ``busy``).

    ``mesh_dirs``: folders besides the dataset's own that its meshes may lie in (``--mesh-dir``);
    the work directory gets copies, so its ``dataset.yaml`` needs none. ``scene_dirs``: folders
    its captured scene directories may lie in (``--scene-dir``); they stay where they are.
    """
    dataset = load_dataset_spec(dataset_file, mesh_dirs, scene_dirs)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    results = {s.name: init_captured(workdir, s, dataset) if s.captured else init_scene(workdir, s, quick)
               for s in dataset.scenes}
    if all(r != "failed" for r in results.values()):
        write_workdir_dataset(dataset, workdir)
    return dataset, results


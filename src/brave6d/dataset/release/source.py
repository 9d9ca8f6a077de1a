"""What a release is built from: the dataset's identity, its object library and its scenes.

:func:`load_release_source` reads ``WORKDIR/dataset.yaml`` through ``brave6d.core.dataset_spec`` (the
file's one owner) and keeps what a release needs. Ids follow the dataset contract: a scene's BOP
``scene_id`` is its 1-based position in ``scenes``, an object's ``obj_id`` its 1-based position in
``objects``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from brave6d.core.errors import BraveError, DataError

DATASET_YAML = "dataset.yaml"


class ReleaseError(DataError):
    """A release cannot be built or does not verify; the message names the file and the problem."""


@dataclass(frozen=True)
class LibraryObject:
    """One entry of the dataset's object library; ``obj_id`` is its 1-based position."""

    obj_id: int
    name: str
    category: str
    description: str = ""


@dataclass(frozen=True)
class SceneSource:
    """One scene of the dataset: its BOP ``scene_id`` (1-based position), name and directory."""

    scene_id: int
    name: str
    root: Path


@dataclass(frozen=True)
class ReleaseSource:
    """The dataset a release packages (see the module docstring)."""

    workdir: Path
    name: str
    version: str
    license: str
    citation: str
    description: str
    objects: tuple[LibraryObject, ...]
    scenes: tuple[SceneSource, ...]

    def obj_id_of(self, name: str) -> int | None:
        """The library ``obj_id`` of object ``name``, or None when the library has no such object."""
        return next((o.obj_id for o in self.objects if o.name == name), None)


def load_release_source(workdir: Path | str) -> ReleaseSource:
    """Read ``WORKDIR/dataset.yaml`` through the work directory's loader and locate each scene
    directory (``WORKDIR/scenes/<scene name>/``, or a captured scene's folder where it lies, as the
    work directory's ``dataset.yaml`` records it: :func:`brave6d.dataset.workdir.scene_root`)."""
    from brave6d.dataset.workdir import load_workdir_dataset, scene_root

    root = Path(workdir)
    path = root / DATASET_YAML
    if not root.is_dir():
        raise ReleaseError(f"{root}: dataset work directory not found")
    if not path.is_file():
        raise ReleaseError(f"{path}: file not found; run 'brave6d dataset run DATASET.yaml {root}' first")
    try:
        dataset = load_workdir_dataset(root)
    except BraveError as exc:
        raise ReleaseError(str(exc)) from None
    spec = dataset.spec
    ids = spec.obj_ids()
    objects = tuple(LibraryObject(ids[o.name], o.name, str(o.category.value if hasattr(o.category, "value") else o.category),
                                  o.description) for o in spec.objects)
    scenes = []
    for i, scene in enumerate(dataset.scenes):
        folder = scene_root(root, scene).root
        if not folder.is_dir():
            raise ReleaseError(f"{path}: field 'scenes[{i}]': no scene directory {folder}; "
                               f"run 'brave6d dataset run' for the dataset first")
        scenes.append(SceneSource(scene.scene_id, scene.name, folder))
    return ReleaseSource(root, spec.name, spec.version, spec.license, spec.citation, spec.description.strip(),
                         objects, tuple(scenes))

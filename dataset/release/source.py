"""What a release is built from: the dataset's identity, its object library and its scenes.

:func:`load_release_source` is the ONE place the release reads ``WORKDIR/dataset.yaml``. It parses
only the fields a release needs (name, version, license, citation, description, the object
library, the scene order) with the project's strict YAML reader, so that the release does not
depend on how the dataset spec is validated elsewhere (swap its body for the dataset spec's own
loader when one exists). Ids follow the dataset contract: a scene's BOP ``scene_id`` is its
1-based position in ``scenes``, an object's ``obj_id`` its 1-based position in ``objects``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from brave6d.errors import DataError
from brave6d.yaml_io import read_yaml

DATASET_YAML = "dataset.yaml"
SCENES_DIR = "scenes"
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


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
    """Read ``WORKDIR/dataset.yaml`` (only the release's fields) and locate each scene directory."""
    root = Path(workdir)
    path = root / DATASET_YAML
    if not root.is_dir():
        raise ReleaseError(f"{root}: dataset work directory not found")
    data = read_yaml(path, error=ReleaseError)
    if not isinstance(data, dict):
        raise ReleaseError(f"{path}: expected a mapping of dataset fields, got {type(data).__name__}")
    name = _text(data, "name", path)
    if not _NAME.match(name):
        raise ReleaseError(f"{path}: field 'name': {name!r} must match [A-Za-z0-9_.-]+ (it names the release files)")
    objects = _library(data.get("objects"), path)
    scenes = _scenes(data.get("scenes"), path, root)
    return ReleaseSource(root, name, _text(data, "version", path), _text(data, "license", path),
                         _text(data, "citation", path), str(data.get("description") or "").strip(),
                         objects, scenes)


def _text(data: dict[str, Any], key: str, path: Path) -> str:
    value = data.get(key)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and key == "version":
        value = str(value)
    if not isinstance(value, str) or not value.strip():
        raise ReleaseError(f"{path}: field '{key}': a non-empty string is required")
    return value.strip()


def _library(items: Any, path: Path) -> tuple[LibraryObject, ...]:
    if not isinstance(items, list) or not items:
        raise ReleaseError(f"{path}: field 'objects': a non-empty list of library objects is required")
    out: list[LibraryObject] = []
    for i, item in enumerate(items):
        where = f"{path}: field 'objects[{i}]"
        if not isinstance(item, dict) or not isinstance(item.get("name"), str) or not item["name"]:
            raise ReleaseError(f"{where}.name': a non-empty string is required")
        if any(o.name == item["name"] for o in out):
            raise ReleaseError(f"{where}.name': {item['name']!r} is already in the library (names are unique)")
        out.append(LibraryObject(i + 1, item["name"], str(item.get("category", "")), str(item.get("description") or "")))
    return tuple(out)


def _scenes(items: Any, path: Path, workdir: Path) -> tuple[SceneSource, ...]:
    if not isinstance(items, list) or not items:
        raise ReleaseError(f"{path}: field 'scenes': a non-empty list of {{spec: path}} entries is required")
    out: list[SceneSource] = []
    for i, item in enumerate(items):
        if not isinstance(item, dict) or not isinstance(item.get("spec"), str) or not item["spec"]:
            raise ReleaseError(f"{path}: field 'scenes[{i}].spec': a path to a scene spec is required")
        spec = path.parent / item["spec"]
        candidates = [n for n in (_spec_name(spec), spec.stem) if n]
        found = next((workdir / SCENES_DIR / n for n in candidates if (workdir / SCENES_DIR / n).is_dir()), None)
        if found is None:
            tried = " or ".join(str(workdir / SCENES_DIR / n) for n in dict.fromkeys(candidates))
            raise ReleaseError(f"{path}: field 'scenes[{i}]': no scene directory {tried}; "
                               f"run 'brave6d dataset run' for the dataset first")
        if any(s.root == found for s in out):
            raise ReleaseError(f"{path}: field 'scenes[{i}]': scene {found.name!r} is listed twice")
        out.append(SceneSource(i + 1, found.name, found))
    return tuple(out)


def _spec_name(spec: Path) -> str | None:
    """The scene spec's ``name`` (which names its scene directory), or None when unreadable."""
    try:
        data = read_yaml(spec)
    except DataError:
        return None
    name = data.get("name") if isinstance(data, dict) else None
    return name if isinstance(name, str) and _NAME.match(name) else None

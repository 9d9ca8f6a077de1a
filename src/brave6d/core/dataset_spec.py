"""The dataset spec (``dataset.yaml``): many scenes sharing one object library.

A dataset names itself (``name``, ``version``, ``license``, ``citation``), holds one object
library (``objects``: every field of a scene spec's object except ``pose``) and lists its scenes
(paths relative to ``dataset.yaml``), each either a scene spec to simulate (``{spec: path}``) or a
scene directory captured at a robot (``{dir: path}``: made by ``brave6d init``, captured,
calibrated and annotated there; its ``scene.yaml`` is the scene's spec). An object in a listed
scene spec may give only ``name`` and ``pose``: the rest comes from the library; a field it does
give must equal the library's (a mesh: the same file or the same content). So an object keeps
one BOP ``obj_id`` in every scene: its 1-based position in the library. A scene's BOP
``scene_id`` is its 1-based position in ``scenes``. An optional ``cluster`` block holds the
defaults of ``brave6d dataset run`` for a Slurm cluster (and the training ``preset`` of every scene, and
the learned model's ``learn``, ``learn_preset`` and ``learn_images``).

Every name here becomes a path part (``WORKDIR/objects/<object>/``, ``scenes/<scene>/``, the
release's ``<name>_...zip``, the serve cache's ``<name>-<version>-...``), so each follows the one
rule of :mod:`brave6d.core.names`. Every file ``dataset.yaml`` names (meshes, with the files that travel
with them, and scene specs, with every file they name: meshes, a board's ``dictionary_file``;
:func:`brave6d.core.spec.named_files`) must lie inside its folder, symlinks resolved, before any is read:
``dataset run`` copies them into the work directory and on into releases, so a shared
``dataset.yaml`` must not be able to name a file elsewhere (``/etc/passwd``). Only the user widens
that, with ``mesh_dirs`` (``--mesh-dir DIR``); no field of the file itself can. A captured scene
directory (``dir``) likewise lies inside the folder unless the user allows its folder with
``scene_dirs`` (``--scene-dir DIR``, a flag of its own: ``dataset run`` trains and exports into a
scene directory where it lies, it does not only read it); its own meshes lie inside it.

Every bad value raises :class:`~brave6d.core.errors.SpecError` with one line naming the file and the
field, like :mod:`brave6d.core.spec` (the owner of the scene spec, which this module reuses).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from brave6d.core.atomic import file_sha256
from brave6d.core.errors import SpecError, validation_error_field
from brave6d.core.layout import SceneDir, mesh_files
from brave6d.core.names import FolderName
from brave6d.core.spec import (Category, ObjectSpec, PositiveFloat, SceneSpec, SymmetrySpec, check_named_files,
                               named_files, parse_scene_spec)
from brave6d.core.yaml_io import read_yaml

#: The object fields the library gives (everything of a scene object but its pose).
LIBRARY_FIELDS = ("mesh", "category", "scale", "description", "symmetry")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LibraryObject(_Strict):
    """One object of the library: a scene spec's object without the pose."""

    name: FolderName  # WORKDIR/objects/<name>/
    category: Category
    mesh: Path
    scale: PositiveFloat = 1.0
    description: str = ""
    symmetry: SymmetrySpec | None = None


class SceneRef(_Strict):
    """A scene of the dataset, one of two kinds (paths relative to ``dataset.yaml``): ``spec``, a
    scene spec that ``dataset run`` makes a scene directory of and captures on the simulated rig;
    or ``dir``, a scene directory captured at a real robot (``brave6d init``, ``capture run``,
    ``calibrate all``, ``annotate import-3ddat``), used where it lies."""

    spec: Path | None = None
    dir: Path | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> SceneRef:
        if (self.spec is None) == (self.dir is None):
            raise ValueError("give exactly one of 'spec' (a scene spec to simulate) or 'dir' (a captured "
                             "scene directory)")
        return self


class ClusterSpec(_Strict):
    """Defaults of ``brave6d dataset run`` (each can be overridden by the command-line flag)."""

    executor: Literal["local", "slurm"] = "local"
    partition: str | None = None
    time_min: Annotated[int, Field(ge=1)] = 240
    gpus_per_task: Annotated[int, Field(ge=0)] = 1
    cpus_per_task: Annotated[int, Field(ge=1)] = 8
    mem_gb: PositiveFloat = 32.0
    array_parallelism: Annotated[int, Field(ge=1)] = 16
    account: str | None = None
    qos: str | None = None
    setup: list[str] = Field(default_factory=list, description="shell lines run before each job (module load, venv)")
    preset: str | None = Field(default=None, description="training preset of every scene (None: the training "
                                                          "stage's default, fast; a GPU cluster wants default)")
    learn: bool = Field(default=True, description="train the dataset's learned model, one for its object library")
    learn_preset: str | None = Field(default=None, description="its learn preset (None: fast; --quick: tiny)")
    learn_images: Annotated[int, Field(ge=1)] | None = Field(
        default=None, description="train_pbr images rendered for it (None: 300; --quick: 24)")


class DatasetSpec(_Strict):
    """The whole ``dataset.yaml``."""

    name: FolderName  # <name>_base.zip, ... and the serve cache's <name>-<version>-<digest>/
    version: FolderName
    license: str = Field(min_length=1)
    citation: str = Field(min_length=1)
    description: str = ""
    objects: list[LibraryObject] = Field(min_length=1)
    scenes: list[SceneRef] = Field(min_length=1)
    cluster: ClusterSpec = ClusterSpec()

    source: Path | None = Field(default=None, exclude=True, description="file this spec was read from")

    @field_validator("objects")
    @classmethod
    def _unique(cls, value: list[LibraryObject]) -> list[LibraryObject]:
        names = [o.name for o in value]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"duplicate names {dupes} (one library entry per object)")
        return value

    @property
    def base_dir(self) -> Path:
        return self.source.parent if self.source is not None else Path.cwd()

    def resolve(self, path: Path) -> Path:
        """Absolute path of a file named in the dataset spec."""
        return path if path.is_absolute() else (self.base_dir / path)

    def obj_ids(self) -> dict[str, int]:
        """Object name -> BOP ``obj_id`` (1-based position in the library)."""
        return {o.name: i for i, o in enumerate(self.objects, start=1)}


@dataclass(frozen=True)
class DatasetScene:
    """One scene of a loaded dataset: its merged, validated scene spec and its ids; ``dir``: the
    captured scene directory (absolute, symlinks resolved) of a ``dir`` entry, None for a ``spec``."""

    scene_id: int
    spec: SceneSpec
    spec_file: Path
    obj_ids: dict[str, int]  # the scene's object names -> dataset obj_ids
    dir: Path | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def captured(self) -> bool:
        """A scene captured at a robot (a ``dir`` entry): ``dataset run`` never runs its rig stages."""
        return self.dir is not None


@dataclass(frozen=True)
class Dataset:
    """A loaded ``dataset.yaml``: the spec and every scene, merged with the library."""

    spec: DatasetSpec
    scenes: tuple[DatasetScene, ...]

    def scene(self, name: str) -> DatasetScene:
        for s in self.scenes:
            if s.name == name:
                return s
        raise SpecError(f"{self.spec.source}: no scene named {name!r} (scenes: {[s.name for s in self.scenes]})")


# ----------------------------------------------------------------------------- loading
def parse_dataset_spec(data: Any, source: Path | str = "<memory>") -> DatasetSpec:
    """Validate a parsed YAML mapping into a :class:`DatasetSpec` (errors name ``source`` and the field)."""
    src = Path(source)
    if not isinstance(data, dict):
        raise SpecError(f"{src}: the dataset spec must be a YAML mapping at the top level, got {type(data).__name__}")
    try:
        return DatasetSpec.model_validate({**data, "source": None if str(source) == "<memory>" else src.resolve()})
    except ValidationError as exc:
        field_path, msg = validation_error_field(exc.errors(include_url=False))
        raise SpecError(f"{src}: field '{field_path or '<root>'}': {msg}") from None


def load_dataset_spec(path: Path | str, mesh_dirs: Sequence[Path | str] = (),
                      scene_dirs: Sequence[Path | str] = ()) -> Dataset:
    """Read ``dataset.yaml`` and every scene spec it lists, merged with the library (module docstring).

    Every file it names must lie inside its folder or one of ``mesh_dirs`` (the user's own
    ``--mesh-dir`` folders), and every scene directory (``dir``) inside its folder or one of
    ``scene_dirs`` (``--scene-dir``), else :class:`SpecError` naming the file, the field and the folder.
    A scene directory's meshes may also lie inside the scene directory itself.
    """
    p = Path(path)
    if not p.is_file():
        raise SpecError(f"{p}: dataset spec not found")
    spec = parse_dataset_spec(read_yaml(p, error=SpecError), p)
    allowed = _allowed_folders(spec, mesh_dirs)
    allowed_scenes = (allowed[0], *_flag_folders(scene_dirs, "--scene-dir"))
    for i, obj in enumerate(spec.objects):
        _check_mesh(spec.resolve(obj.mesh), allowed, f"{p}: field 'objects[{i}].mesh'")
    scenes: list[DatasetScene] = []
    seen: dict[str, int] = {}
    for i, ref in enumerate(spec.scenes):
        folder = None
        if ref.dir is not None:
            folder = _scene_folder(spec.resolve(ref.dir), allowed_scenes, f"{p}: field 'scenes[{i}].dir'")
            scene_file, where = SceneDir(folder).spec_path, f"scenes[{i}].dir"
            scene = merge_scene_spec(spec, scene_file, mesh_dirs, own_folder=folder)
        else:
            assert ref.spec is not None  # SceneRef: exactly one of the two
            scene_file, where = spec.resolve(ref.spec), f"scenes[{i}].spec"
            _confine(scene_file, allowed, f"{p}: field '{where}'")
            if not scene_file.is_file():
                raise SpecError(f"{p}: field '{where}': scene spec not found: {scene_file}")
            scene = merge_scene_spec(spec, scene_file, mesh_dirs)
        if scene.name in seen:
            raise SpecError(f"{p}: field '{where}': scene name {scene.name!r} ({scene_file}) "
                            f"is already used by scenes[{seen[scene.name]}]; scene names must be unique")
        seen[scene.name] = i
        ids = spec.obj_ids()
        scenes.append(DatasetScene(i + 1, scene, scene_file, {o.name: ids[o.name] for o in scene.objects}, folder))
    return Dataset(spec, tuple(scenes))


def _scene_folder(folder: Path, allowed: tuple[Path, ...], where: str) -> Path:
    """The captured scene directory ``folder``, resolved, once it is a scene directory inside ``allowed``:
    ``dataset run`` trains and exports into it where it lies, so only the user (``--scene-dir``) widens that."""
    if not folder.is_dir():
        raise SpecError(f"{where}: scene directory not found: {folder}")
    _confine(folder, allowed, where, flag="--scene-dir")
    if not SceneDir(folder).spec_path.is_file():
        raise SpecError(f"{where}: {folder} is not a scene directory (no scene.yaml); make it with 'brave6d init'")
    return folder.resolve()


def merge_scene_spec(dataset: DatasetSpec, scene_file: Path, mesh_dirs: Sequence[Path | str] = (),
                     own_folder: Path | None = None) -> SceneSpec:
    """The scene spec of ``scene_file`` with its objects completed from the dataset's library.

    Library meshes enter the merged spec as absolute paths. A field the scene gives must equal
    the library's; an unknown object name is an error naming the scene file and the field. Its
    meshes must lie inside the dataset's folder or ``mesh_dirs``, like the library's, or inside
    ``own_folder`` (a captured scene directory, whose ``scene.yaml`` names its copied meshes).
    """
    data = read_yaml(scene_file, error=SpecError)
    if not isinstance(data, dict):
        raise SpecError(f"{scene_file}: the spec must be a YAML mapping at the top level, got {type(data).__name__}")
    library = {o.name: o for o in dataset.objects}
    items = data.get("objects", [])
    given: list[set[str]] = []
    if isinstance(items, list):
        merged_items = []
        for i, item in enumerate(items):
            name = item.get("name") if isinstance(item, dict) else None
            if not isinstance(name, str):
                merged_items.append(item)  # the scene spec's own validation names the problem
                given.append(set())
                continue
            if name not in library:
                raise SpecError(f"{scene_file}: field 'objects[{i}].name': unknown object {name!r}; "
                                f"the library of {dataset.source} has {sorted(library)}")
            lib = library[name].model_dump(mode="json", exclude={"name"})
            lib["mesh"] = str(dataset.resolve(library[name].mesh).resolve())
            merged_items.append({**lib, **item})
            given.append(set(item) & set(LIBRARY_FIELDS))
        data = {**data, "objects": merged_items}
    scene = parse_scene_spec(data, scene_file, check_files=False)  # nothing it names is opened yet
    allowed = _allowed_folders(dataset, mesh_dirs) + ((own_folder,) if own_folder is not None else ())
    for field, named in named_files(scene):  # every file it names, before any is read
        _check_mesh(named, allowed, f"{scene_file}: field '{field}'", sidecars=field.endswith(".mesh"))
    check_named_files(scene, scene_file)
    for i, (obj, fields) in enumerate(zip(scene.objects, given)):
        for name in sorted(fields):
            _check_same(dataset, library[obj.name], scene, obj, name, f"{scene_file}: field 'objects[{i}].{name}'")
    return scene


def _allowed_folders(dataset: DatasetSpec, mesh_dirs: Sequence[Path | str]) -> tuple[Path, ...]:
    """The folders a dataset may name files in: its own (first), then the user's ``mesh_dirs``."""
    return (dataset.base_dir.resolve(), *_flag_folders(mesh_dirs, "--mesh-dir"))


def _flag_folders(folders: Sequence[Path | str], flag: str) -> tuple[Path, ...]:
    """The user's ``flag`` folders, resolved; one that is not a folder is an error naming it."""
    for d in folders:
        if not Path(d).is_dir():
            raise SpecError(f"{flag} {d}: not a folder")
    return tuple(Path(d).resolve() for d in folders)


def _confine(path: Path, allowed: tuple[Path, ...], where: str, travels_with: Path | None = None,
             flag: str = "--mesh-dir") -> None:
    """SpecError naming ``where`` unless ``path`` (symlinks resolved) lies inside one of ``allowed``
    (the dataset's folder, then the user's ``flag`` folders)."""
    real = path.resolve()
    if any(real.is_relative_to(folder) for folder in allowed):
        return
    shown = str(path) if real == path else f"{path} (that is {real})"
    if travels_with is not None:
        shown += f", which travels with the mesh {travels_with.name},"
    extra = f" and the {flag} folders {', '.join(map(str, allowed[1:]))}" if len(allowed) > 1 else ""
    raise SpecError(f"{where}: {shown} lies outside {allowed[0]} (the dataset's folder){extra}; a dataset names "
                    f"only files inside its folder: move it there, or allow its folder with {flag} DIR")


def _check_mesh(path: Path, allowed: tuple[Path, ...], where: str, sidecars: bool = True) -> None:
    """The file a field names (a mesh, the board's dictionary file) and, for a mesh (``sidecars``),
    the files that travel with it (:func:`brave6d.core.layout.mesh_files`) lie inside ``allowed``."""
    _confine(path, allowed, where)
    if not path.is_file():
        raise SpecError(f"{where}: file not found: {path}")
    real = path.resolve()
    for sibling in mesh_files(real) if sidecars else ():
        _confine(sibling, allowed, where, travels_with=real)


def _check_same(dataset: DatasetSpec, lib: LibraryObject, scene: SceneSpec, obj: ObjectSpec, name: str,
                where: str) -> None:
    if name == "mesh":
        a, b = dataset.resolve(lib.mesh).resolve(), scene.resolve(obj.mesh).resolve()
        if a == b or file_sha256(a) == file_sha256(b):
            return
        raise SpecError(f"{where}: {obj.mesh} is not the library's mesh for {obj.name!r} ({a}); "
                        "leave 'mesh' out to take the library's")
    mine, theirs = getattr(obj, name), getattr(lib, name)
    if mine != theirs:
        shown = theirs.value if isinstance(theirs, Category) else theirs
        raise SpecError(f"{where}: differs from the library entry {obj.name!r} in {dataset.source} "
                        f"(library: {shown!r}); leave it out to take the library's")


def scene_fingerprint(spec: SceneSpec, obj_ids: dict[str, int]) -> str:
    """A digest of what a scene directory is made from: the merged spec (meshes by content) and
    the obj_ids. Equal fingerprints mean a finished stage of that scene is still valid."""
    data = spec.model_dump(mode="json", exclude={"source"})
    for key in ("static_meshes", "objects"):
        for item, model in zip(data.get(key, []), getattr(spec, key)):
            item["mesh"] = file_sha256(spec.resolve(model.mesh).resolve())
    if spec.board.dictionary_file is not None:  # the board's markers are in the file: its content counts
        data["board"]["dictionary_file"] = file_sha256(spec.board.dictionary_file)
    text = json.dumps({"spec": data, "obj_ids": obj_ids}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def dataset_to_yaml(spec: DatasetSpec) -> str:
    """Serialise a dataset spec back to YAML (paths as written, enums as strings)."""
    return yaml.safe_dump(spec.model_dump(mode="json", exclude={"source"}), sort_keys=False)

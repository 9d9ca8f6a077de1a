"""What a synthetic split is made from: the object library (with BOP ``obj_id``s), the camera,
the capture distances and elevations and the simulated-camera effects.

``DATASET_OR_SCENE`` is a ``dataset.yaml`` (read through :mod:`brave6d.core.dataset_spec`: the library
gives the objects and their ``obj_id``s, the first scene the camera, rings and effects) or a scene
spec (read through :mod:`brave6d.core.spec`: its objects numbered by sorted name, as the single-scene
demo numbers them).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from brave6d.core.atomic import file_sha256
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import SpecError
from brave6d.core.spec import EffectsSpec, SceneSpec
from brave6d.core.yaml_io import read_yaml


@dataclass(frozen=True)
class SynthObject:
    """One library object: BOP ``obj_id``, name, mesh file and its scale to metres."""

    obj_id: int
    name: str
    mesh: Path
    scale: float


@dataclass(frozen=True)
class SynthSource:
    """Everything the split takes from the dataset or scene spec (see the module docstring).

    ``camera`` is the undistorted pinhole camera of the images; ``effects`` the camera-side
    effects that the spec lists (``lens_distortion`` is left out: BOP images are pinhole images,
    as the test split's undistorted frames are).
    """

    path: Path
    name: str
    objects: tuple[SynthObject, ...]
    camera: PinholeCamera
    depth_range: tuple[float, float]
    distance_range_m: tuple[float, float]
    elevation_range_deg: tuple[float, float]
    effects: EffectsSpec

    def fingerprint(self) -> str:
        """A digest of the spec file and every mesh (content): equal digests, equal inputs."""
        h = hashlib.sha256(file_sha256(self.path).encode())
        for o in self.objects:
            h.update(f"{o.obj_id}:{o.name}:{o.scale}:{file_sha256(o.mesh)}".encode())
        return h.hexdigest()[:16]

    def with_size(self, width: int | None, height: int | None) -> SynthSource:
        """The same source with images of ``width`` x ``height`` (same horizontal field of view, square
        pixels as before, principal point at the same relative place)."""
        if width is None and height is None:
            return self
        w = int(width) if width is not None else self.camera.width
        h = int(height) if height is not None else self.camera.height
        if w < 8 or h < 8:
            raise SpecError(f"synth: image size {w}x{h} is too small (at least 8x8)")
        c = self.camera
        s = w / c.width  # keep the horizontal field of view and square pixels; the height crops or extends
        camera = PinholeCamera(w, h, c.fx * s, c.fy * s, (c.cx + 0.5) * s - 0.5, (c.cy + 0.5) / c.height * h - 0.5)
        return SynthSource(self.path, self.name, self.objects, camera, self.depth_range,
                           self.distance_range_m, self.elevation_range_deg, self.effects)


def load_synth_source(path: Path | str, mesh_dirs: Sequence[Path | str] = (),
                      scene_dirs: Sequence[Path | str] = ()) -> SynthSource:
    """Read a ``dataset.yaml`` or a scene spec (see the module docstring); errors name the file.

    ``mesh_dirs`` / ``scene_dirs``: for a ``dataset.yaml``, folders besides its own that its meshes
    / captured scene directories may lie in (``--mesh-dir`` / ``--scene-dir``;
    :func:`brave6d.core.dataset_spec.load_dataset_spec`).
    """
    p = Path(path)
    if not p.is_file():
        raise SpecError(f"{p}: dataset or scene spec not found")
    data = read_yaml(p, error=SpecError)
    if isinstance(data, dict) and "scenes" in data and "capture" not in data:
        return _from_dataset(p, mesh_dirs, scene_dirs)
    return _from_scene(p)


def _from_dataset(path: Path, mesh_dirs: Sequence[Path | str], scene_dirs: Sequence[Path | str]) -> SynthSource:
    from brave6d.core.dataset_spec import load_dataset_spec

    dataset = load_dataset_spec(path, mesh_dirs, scene_dirs)
    spec = dataset.spec
    ids = spec.obj_ids()
    objects = tuple(SynthObject(ids[o.name], o.name, spec.resolve(o.mesh).resolve(), float(o.scale))
                    for o in spec.objects)
    return _with_scene(path, spec.name, objects, dataset.scenes[0].spec)


def _from_scene(path: Path) -> SynthSource:
    from brave6d.core.spec import load_scene_spec

    scene = load_scene_spec(path)
    if not scene.objects:
        raise SpecError(f"{path}: field 'objects': the scene has no objects to synthesise")
    ordered = sorted(scene.objects, key=lambda o: o.name)
    objects = tuple(SynthObject(i, o.name, scene.resolve(o.mesh).resolve(), float(o.scale))
                    for i, o in enumerate(ordered, start=1))
    return _with_scene(path, scene.name, objects, scene)


def _with_scene(path: Path, name: str, objects: tuple[SynthObject, ...], scene: SceneSpec) -> SynthSource:
    sim = scene.simulation
    effects = EffectsSpec() if sim is None else sim.effects.model_copy(update={"lens_distortion": None})
    cap = scene.capture
    return SynthSource(path.resolve(), name, objects, scene.camera.pinhole().without_distortion(),
                       (scene.camera.depth_min_m, scene.camera.depth_max_m),
                       (min(cap.distances_m), max(cap.distances_m)),
                       (cap.min_elevation_deg, cap.max_elevation_deg), effects)

"""Domain randomisation of one synthetic image: which library objects, their resting poses among
distractors (simple primitives) on a textured support plane, the light, the background and the
camera pose. Image ``i``'s randomness depends only on ``(seed, i)``: one generator per image.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.core.transforms import look_at, transform_points
from brave6d.synth.placement import RestingPoses, place_on_plane, resting_poses
from brave6d.synth.source import SynthSource

#: Side of the square support plane (m): wider than any view at 50 cm, so its edge is rarely seen.
PLANE_SIZE_M = 3.0
_TEXTURE_PX = 64


@dataclass(frozen=True)
class Randomization:
    """How the images vary (the defaults suit table-top objects of 2-10 cm)."""

    min_objects: int = 1
    max_objects: int = 6
    max_distractors: int = 6
    area_radius_m: float = 0.08
    clearance_m: float = 0.002
    distractor_size_m: tuple[float, float] = (0.01, 0.05)
    ambient: tuple[float, float] = (0.15, 0.6)
    light_elevation_deg: tuple[float, float] = (30.0, 90.0)
    target_jitter_m: float = 0.01

    def __post_init__(self) -> None:
        if not 1 <= self.min_objects <= self.max_objects or self.max_distractors < 0:
            raise BraveError(f"synth: objects per image {self.min_objects}..{self.max_objects} and distractors "
                             f"<= {self.max_distractors} are out of range")

    def to_json(self) -> dict[str, object]:
        return asdict(self)


@dataclass(frozen=True)
class Body:
    """A mesh in its model frame (metres) with its appearance, as capture's ``MeshPart`` lists."""

    name: str
    parts: tuple[object, ...]  # brave6d.capture.MeshPart, model frame

    @cached_property
    def vertices(self) -> NDArray[np.float64]:
        return np.concatenate([p.vertices for p in self.parts])  # type: ignore[attr-defined]

    @cached_property
    def faces(self) -> NDArray[np.int64]:
        offsets = np.cumsum([0] + [len(p.vertices) for p in self.parts])  # type: ignore[attr-defined]
        return np.concatenate([p.faces + o for p, o in zip(self.parts, offsets)])  # type: ignore[attr-defined]

    @cached_property
    def rest(self) -> RestingPoses:
        return resting_poses(self.vertices, self.name)


class LibraryAssets:
    """The library's meshes loaded once per process (model frame, metres)."""

    def __init__(self, source: SynthSource) -> None:
        from brave6d.capture import load_mesh_parts

        self.source = source
        self.bodies = tuple(Body(o.name, tuple(load_mesh_parts(o.mesh, o.scale, np.eye(4), 1, o.name)))
                            for o in source.objects)


@dataclass(frozen=True)
class ImageScene:
    """Everything random about one image. ``targets``: ``(library index, world_T_model)`` of the
    annotated objects; ``distractors``: ``(Body, world_T_model)``; ``plane``: the support plane
    as one textured ``MeshPart`` (world frame, z = 0)."""

    index: int
    targets: tuple[tuple[int, NDArray[np.float64]], ...]
    distractors: tuple[tuple[Body, NDArray[np.float64]], ...]
    plane: object
    world_T_cam: NDArray[np.float64]
    light_direction: tuple[float, float, float]
    ambient: float
    background_rgb: tuple[int, int, int]


def image_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of image ``index`` (independent of every other image and of the worker)."""
    return np.random.default_rng([int(seed), int(index), 0x5E7])


def sample_image_scene(assets: LibraryAssets, seed: int, index: int,
                       settings: Randomization = Randomization()) -> ImageScene:
    """Draw image ``index``'s scene (see the module docstring)."""
    rng = image_rng(seed, index)
    source = assets.source
    n_lib = len(assets.bodies)
    count = int(rng.integers(min(settings.min_objects, n_lib), min(settings.max_objects, n_lib) + 1))
    chosen = [int(i) for i in rng.choice(n_lib, size=count, replace=False)]
    distractors = [_primitive(rng, settings, j) for j in range(int(rng.integers(0, settings.max_distractors + 1)))]
    bodies = [assets.bodies[i] for i in chosen] + distractors
    placement = place_on_plane([(b.vertices, b.rest) for b in bodies], rng, settings.area_radius_m,
                               settings.clearance_m)
    targets = tuple((i, T) for i, T in zip(chosen, placement.poses[:count]) if T is not None)
    placed = tuple((b, T) for b, T in zip(distractors, placement.poses[count:]) if T is not None)
    world_T_cam = _camera_pose(rng, source, settings, [transform_points(T, assets.bodies[i].vertices)
                                                       for i, T in targets])
    elevation = np.radians(rng.uniform(*settings.light_elevation_deg))
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    light = (-np.cos(elevation) * np.cos(azimuth), -np.cos(elevation) * np.sin(azimuth), -np.sin(elevation))
    ambient = float(rng.uniform(*settings.ambient))
    background = tuple(int(c) for c in rng.integers(0, 256, size=3))
    return ImageScene(index, targets, placed, _plane(rng), world_T_cam, tuple(float(x) for x in light), ambient,
                      background)  # type: ignore[arg-type]


def _camera_pose(rng: np.random.Generator, source: SynthSource, settings: Randomization,
                 target_points: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """A camera over the capture distances and elevations, looking at the objects' centre."""
    centre = np.concatenate(target_points).mean(axis=0) if target_points else np.zeros(3)
    aim = centre + rng.normal(0.0, settings.target_jitter_m, size=3)
    distance = rng.uniform(*source.distance_range_m)
    elevation = np.radians(rng.uniform(*source.elevation_range_deg))
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    eye = aim + distance * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                     np.sin(elevation)])
    return look_at(eye, aim)


def _primitive(rng: np.random.Generator, settings: Randomization, j: int) -> Body:
    """A random box, cylinder, cone or sphere with a random colour per face or a uniform one."""
    import trimesh

    from brave6d.capture import MeshPart

    lo, hi = settings.distractor_size_m
    kind = int(rng.integers(0, 4))
    a, b, c = (float(x) for x in rng.uniform(lo, hi, size=3))
    if kind == 0:
        mesh = trimesh.creation.box(extents=(a, b, c))
    elif kind == 1:
        mesh = trimesh.creation.cylinder(radius=a / 2, height=b, sections=24)
    elif kind == 2:
        mesh = trimesh.creation.cone(radius=a / 2, height=b, sections=24)
    else:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=a / 2)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    base = rng.integers(0, 256, size=3)
    if rng.uniform() < 0.5:
        colors = np.clip(base + rng.integers(-40, 41, size=(len(faces), 3)), 0, 255).astype(np.uint8)
    else:
        colors = np.repeat(base[None].astype(np.uint8), len(faces), axis=0)
    part = MeshPart(name=f"distractor_{j}", segment_id=1, vertices=np.asarray(mesh.vertices, dtype=np.float64),
                    faces=faces, face_colors=colors, source="<synth distractor>")
    return Body(part.name, (part,))


def _plane(rng: np.random.Generator) -> object:
    """The support plane z = 0: a square with a random procedural texture, repeated a random number of times."""
    from brave6d.capture import MeshPart

    half = PLANE_SIZE_M / 2
    corners = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
    repeats = float(rng.uniform(10.0, 80.0))
    uv = (corners[:, :2] + half) / PLANE_SIZE_M * repeats
    return MeshPart(name="support_plane", segment_id=1, vertices=corners, faces=np.array([[0, 1, 2], [0, 2, 3]]),
                    uv=uv, texture=random_texture(rng), source="<synth plane>")


def random_texture(rng: np.random.Generator, size: int = _TEXTURE_PX) -> NDArray[np.uint8]:
    """A tileable texture: checker, stripes, smooth noise or a plain colour, in two random colours."""
    c0, c1 = (rng.integers(0, 256, size=3).astype(np.float64) for _ in range(2))
    kind = int(rng.integers(0, 4))
    y, x = np.mgrid[0:size, 0:size] / size
    if kind == 0:
        cells = int(rng.integers(2, 9))
        w = ((np.floor(x * cells) + np.floor(y * cells)) % 2).astype(np.float64)
    elif kind == 1:
        cycles = int(rng.integers(1, 9))
        w = 0.5 + 0.5 * np.sin(2 * np.pi * cycles * (x if rng.uniform() < 0.5 else y))
    elif kind == 2:
        coarse = rng.uniform(0.0, 1.0, size=(8, 8))
        w = np.kron(coarse, np.ones((size // 8, size // 8)))
        import cv2

        pad = size // 2  # blur the tiled texture so that it stays seamless
        w = cv2.GaussianBlur(np.pad(w, pad, mode="wrap"), (0, 0), size / 16)[pad:-pad, pad:-pad]
    else:
        w = np.zeros((size, size))
    noise = rng.normal(0.0, 6.0, size=(size, size, 1))
    image = c0 * (1 - w[..., None]) + c1 * w[..., None] + noise
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


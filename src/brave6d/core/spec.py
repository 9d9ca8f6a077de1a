"""The scene spec: one YAML file validated into typed objects.

A spec describes what a scene directory is made from: the target, the capture rings, the
collision boxes, the annotated objects and static meshes, the robot, the camera, the ChArUco
board and, for simulated scenes, the simulator's truth and the effects it applies. Every bad
value raises :class:`~brave6d.core.errors.SpecError` with one line naming the file and the field.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_serializer,
    model_validator,
)

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import SpecError, validation_error_field
from brave6d.core.names import FolderName
from brave6d.core.transforms import make_transform, rpy_deg_to_matrix
from brave6d.core.yaml_io import read_yaml

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
FiniteVec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


class _Strict(BaseModel):
    """Base: unknown keys are errors (a typo must not be silently ignored)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Pose(_Strict):
    """A rigid pose: translation ``xyz`` (m) and extrinsic roll-pitch-yaw ``rpy_deg`` (scipy 'xyz')."""

    xyz: FiniteVec3 = (0.0, 0.0, 0.0)
    rpy_deg: FiniteVec3 = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """The 4x4 ``parent_T_this`` transform."""
        return make_transform(rpy_deg_to_matrix(self.rpy_deg), self.xyz)


class Category(str, Enum):
    industry = "industry"
    household = "household"
    laboratory = "laboratory"
    toys_office = "toys_office"
    mixed = "mixed"


# ----------------------------------------------------------------------------- capture
class CaptureSpec(_Strict):
    """Rings of viewpoints on spherical caps around ``target``."""

    target: FiniteVec3
    distances_m: list[PositiveFloat] = Field(default_factory=lambda: [0.20, 0.30, 0.40, 0.50], min_length=1)
    views_per_distance: Annotated[int, Field(ge=1, le=10000)] = 90
    min_elevation_deg: Annotated[float, Field(ge=0, le=90)] = 20.0
    max_elevation_deg: Annotated[float, Field(ge=0, le=90)] = 85.0
    azimuth_range_deg: tuple[FiniteFloat, FiniteFloat] = (-180.0, 180.0)
    settle_time_s: NonNegFloat = 0.2
    depth: bool = True

    @model_validator(mode="after")
    def _check_ranges(self) -> CaptureSpec:
        if self.min_elevation_deg >= self.max_elevation_deg:
            raise ValueError("min_elevation_deg must be below max_elevation_deg")
        lo, hi = self.azimuth_range_deg
        if not lo < hi or hi - lo > 360.0:
            raise ValueError("azimuth_range_deg must be [lo, hi] with lo < hi and a span of at most 360")
        if len(set(self.distances_m)) != len(self.distances_m):
            raise ValueError("distances_m has duplicates")
        return self


class BoxSpec(_Strict):
    """An oriented box: centre and orientation in the world frame, full edge lengths ``size``."""

    name: str = Field(min_length=1)
    center: FiniteVec3
    size: tuple[PositiveFloat, PositiveFloat, PositiveFloat]
    rpy_deg: FiniteVec3 = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """``world_T_box`` (box frame at the centre, axes along the edges)."""
        return make_transform(rpy_deg_to_matrix(self.rpy_deg), self.center)


class WorkspaceSpec(_Strict):
    """Axis-aligned bounds (world frame) that a camera must stay inside."""

    min: FiniteVec3
    max: FiniteVec3

    @model_validator(mode="after")
    def _check(self) -> WorkspaceSpec:
        if any(lo >= hi for lo, hi in zip(self.min, self.max)):
            raise ValueError(f"min {list(self.min)} must be below max {list(self.max)} on every axis")
        return self


# ----------------------------------------------------------------------------- meshes
class SymmetrySpec(_Strict):
    """BOP-style symmetries of an object model (model frame)."""

    continuous_axes: list[FiniteVec3] = Field(default_factory=list)
    discrete: list[list[FiniteFloat]] = Field(default_factory=list, description="flattened 4x4, metres")

    @field_validator("discrete")
    @classmethod
    def _sixteen(cls, value: list[list[float]]) -> list[list[float]]:
        for i, m in enumerate(value):
            if len(m) != 16:
                raise ValueError(f"discrete[{i}] must have 16 numbers (row-major 4x4), got {len(m)}")
        return value


#: The mesh formats a spec may name (what trimesh loads by the file's extension).
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf")


class MeshSpec(_Strict):
    """A mesh placed in the world: file (relative to the spec), unit scale to metres, pose."""

    name: str = Field(min_length=1)
    mesh: Path
    scale: PositiveFloat = 1.0
    pose: Pose = Pose()

    @field_validator("mesh")
    @classmethod
    def _mesh_format(cls, value: Path) -> Path:
        if value.suffix.lower() not in MESH_SUFFIXES:
            raise ValueError(f"{str(value)[:100]!r} is not a mesh file (a {', '.join(MESH_SUFFIXES)} file is required)")
        return value


class ObjectSpec(MeshSpec):
    """An annotated object (a benchmark target); its name is a folder name (a dataset's ``objects/<name>/``)."""

    name: FolderName
    category: Category
    description: str = ""
    symmetry: SymmetrySpec | None = None


# ----------------------------------------------------------------------------- hardware
class RobotSpec(_Strict):
    """The arm. Speeds/accelerations are what moveL/moveJ receive."""

    model: Literal["ur3e", "ur5e", "ur10e", "ur16e"] = "ur5e"
    linear_speed: Annotated[float, Field(gt=0, le=1.0)] = 0.25
    linear_acceleration: Annotated[float, Field(gt=0, le=5.0)] = 1.2
    joint_speed: Annotated[float, Field(gt=0, le=3.2)] = 1.05
    joint_acceleration: Annotated[float, Field(gt=0, le=40.0)] = 1.4
    home_joints_deg: tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat] = (
        0.0, -90.0, 90.0, -90.0, -90.0, 0.0)
    tcp_T_camera_guess: Pose | None = Field(
        default=None, description="rough mounting of the camera on the flange, for planning")


class CameraSpec(_Strict):
    """Image size and intrinsics: either ``hfov_deg`` or ``fx``/``fy`` (+ optional ``cx``/``cy``)."""

    model: str = "oak"
    width: Annotated[int, Field(ge=16, le=8192)] = 640
    height: Annotated[int, Field(ge=16, le=8192)] = 400
    hfov_deg: Annotated[float, Field(gt=1, lt=179)] | None = None
    fx: PositiveFloat | None = None
    fy: PositiveFloat | None = None
    cx: FiniteFloat | None = None
    cy: FiniteFloat | None = None
    dist: list[FiniteFloat] = Field(default_factory=list)
    depth_min_m: PositiveFloat = 0.1
    depth_max_m: PositiveFloat = 4.0

    @model_validator(mode="after")
    def _check(self) -> CameraSpec:
        if self.hfov_deg is None and (self.fx is None or self.fy is None):
            raise ValueError("give either hfov_deg or both fx and fy")
        if self.hfov_deg is not None and self.fx is not None:
            raise ValueError("give hfov_deg or fx/fy, not both")
        if len(self.dist) not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"dist needs 0, 4, 5, 8, 12 or 14 coefficients, got {len(self.dist)}")
        if self.depth_min_m >= self.depth_max_m:
            raise ValueError("depth_min_m must be below depth_max_m")
        return self

    def pinhole(self) -> PinholeCamera:
        """The nominal intrinsics (the simulator's truth; a real camera reports its own)."""
        if self.hfov_deg is not None:
            return PinholeCamera.from_hfov(self.width, self.height, self.hfov_deg, self.dist)
        cx = self.cx if self.cx is not None else (self.width - 1) / 2.0
        cy = self.cy if self.cy is not None else (self.height - 1) / 2.0
        assert self.fx is not None and self.fy is not None
        return PinholeCamera(self.width, self.height, self.fx, self.fy, cx, cy, tuple(self.dist))


#: The validation context key that leaves every file a spec names unopened (its meshes, the board's
#: dictionary file): a caller that must first check where they lie (a dataset,
#: :func:`brave6d.core.dataset_spec.merge_scene_spec`) then calls :func:`check_named_files`.
FILES_LATER = "files_later"


class BoardSpec(_Strict):
    """A ChArUco board; ``pose`` is where it lies in the world (``world_T_board``)."""

    squares_x: Annotated[int, Field(ge=3, le=50)] = 7
    squares_y: Annotated[int, Field(ge=3, le=50)] = 5
    square_length_m: PositiveFloat = 0.03
    marker_length_m: PositiveFloat = 0.022
    #: A predefined OpenCV name, or ``custom:MARKERSxBITS:SEED`` (``cv2.aruco.extendDictionary``).
    dictionary: str = "DICT_5X5_100"
    #: An OpenCV dictionary file (``Dictionary.writeDictionary``); replaces ``dictionary``. In a
    #: scene spec a relative path is relative to the spec file (and stored resolved).
    dictionary_file: Path | None = None
    legacy_pattern: bool = False
    pose: Pose = Pose()

    @model_validator(mode="after")
    def _check(self, info: ValidationInfo) -> BoardSpec:
        if self.marker_length_m >= self.square_length_m:
            raise ValueError("marker_length_m must be smaller than square_length_m")
        # local: keeps spec loading light for the CLI's --help (the module loads OpenCV)
        from brave6d.core.aruco_dictionary import check_dictionary

        if self.dictionary_file is not None and "dictionary" in self.model_fields_set:
            raise ValueError("give dictionary or dictionary_file, not both")
        check_dictionary(self.dictionary)
        if not (info.context or {}).get(FILES_LATER):
            self.check_markers()
        return self

    def check_markers(self) -> None:
        """ValueError unless the dictionary (its file read now, when it has one) holds a marker for
        every white square of the board."""
        from brave6d.core.aruco_dictionary import aruco_dictionary

        needed = self.squares_x * self.squares_y // 2
        have = int(aruco_dictionary(self.dictionary, self.dictionary_file).bytesList.shape[0])
        if have < needed:
            raise ValueError(f"a {self.squares_x} x {self.squares_y} ChArUco board has {needed} markers, "
                             f"its dictionary ({self.dictionary_label}) only {have}")

    @model_serializer(mode="wrap")
    def _omit_no_file(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """No ``dictionary_file`` key when there is none (boards dump and fingerprint as before it
        existed), no ``dictionary`` key when there is one (the dump validates again)."""
        data = handler(self)
        data.pop("dictionary_file" if self.dictionary_file is None else "dictionary", None)
        return data

    @property
    def dictionary_label(self) -> str:
        """The dictionary in words: its name, ``custom dictionary of N markers ...`` or its file."""
        from brave6d.core.aruco_dictionary import describe_dictionary

        return describe_dictionary(self.dictionary, self.dictionary_file)


# ----------------------------------------------------------------------------- simulation effects
class SensorNoise(_Strict):
    """Gaussian read noise plus shot noise on 8-bit RGB."""

    sigma: NonNegFloat = 2.0
    shot_noise: NonNegFloat = 0.0


class MotionBlur(_Strict):
    """Blur along the image motion of the camera during the exposure."""

    exposure_s: PositiveFloat = 0.01
    residual_speed_m_s: NonNegFloat = 0.01


class DefocusBlur(_Strict):
    """Disc blur growing with the distance from the focus plane."""

    focus_distance_m: PositiveFloat = 0.35
    aperture_px: NonNegFloat = 2.0


class LensDistortion(_Strict):
    """OpenCV distortion applied to rendered images (truth for intrinsics calibration)."""

    dist: list[FiniteFloat] = Field(default_factory=lambda: [0.05, -0.1, 0.0, 0.0, 0.0])


class Vignetting(_Strict):
    """Radial fall-off ``1 - strength * r^2`` (r = 1 at the image corner)."""

    strength: Annotated[float, Field(ge=0, le=1)] = 0.3


class ExposureChange(_Strict):
    """Per-frame gain drawn log-uniformly in [1/max_gain, max_gain]."""

    max_gain: Annotated[float, Field(ge=1.0, le=4.0)] = 1.2


class DepthNoise(_Strict):
    """Depth noise sigma = a + b * z^2 (metres), stereo-like."""

    sigma_at_1m: NonNegFloat = 0.002
    sigma_const: NonNegFloat = 0.0005
    dropout: Annotated[float, Field(ge=0, le=1)] = 0.0


class RobotPoseError(_Strict):
    """Difference between the reported and the actual TCP pose (repeatability)."""

    translation_sigma_m: NonNegFloat = 0.0001
    rotation_sigma_deg: NonNegFloat = 0.01


class TimeOffset(_Strict):
    """Image time stamp lags the robot pose time stamp by ``offset_s`` while the arm still moves."""

    offset_s: FiniteFloat = 0.02


class EffectsSpec(_Strict):
    """Which simulation effects run; an effect that is absent (null) is never applied."""

    sensor_noise: SensorNoise | None = None
    motion_blur: MotionBlur | None = None
    defocus_blur: DefocusBlur | None = None
    lens_distortion: LensDistortion | None = None
    vignetting: Vignetting | None = None
    exposure_change: ExposureChange | None = None
    depth_noise: DepthNoise | None = None
    robot_pose_error: RobotPoseError | None = None
    time_offset: TimeOffset | None = None

    def enabled(self) -> list[str]:
        """Names of the listed effects, in declaration order."""
        return [name for name in type(self).model_fields if getattr(self, name) is not None]


class SimulationSpec(_Strict):
    """The simulator's ground truth and effects (ignored for real hardware)."""

    true_tcp_T_camera: Pose
    seed: int = 0
    light_direction: FiniteVec3 = (0.3, -0.2, -1.0)
    ambient: Annotated[float, Field(ge=0, le=1)] = 0.35
    background_rgb: tuple[int, int, int] = (200, 200, 205)
    effects: EffectsSpec = EffectsSpec()


# ----------------------------------------------------------------------------- the scene
class SceneSpec(_Strict):
    """A whole scene. Relative mesh paths are resolved against the spec file's folder."""

    name: FolderName  # WORKDIR/scenes/<name>/, status/<name>.json, report/<name>/
    category: Category = Category.mixed
    description: str = ""
    capture: CaptureSpec
    workspace: WorkspaceSpec
    collision_boxes: list[BoxSpec] = Field(default_factory=list)
    static_meshes: list[MeshSpec] = Field(default_factory=list)
    objects: list[ObjectSpec] = Field(default_factory=list)
    robot: RobotSpec = RobotSpec()
    camera: CameraSpec = CameraSpec(hfov_deg=70.0)
    board: BoardSpec = BoardSpec()
    simulation: SimulationSpec | None = None

    source: Path | None = Field(default=None, exclude=True, description="file this spec was read from")

    @model_validator(mode="before")
    @classmethod
    def _resolve_dictionary_file(cls, data: Any) -> Any:
        """A relative ``board.dictionary_file`` names a file beside the spec: made absolute before
        the board is checked, so the spec still finds it once copied into a scene directory."""
        board = data.get("board") if isinstance(data, dict) else None
        name = board.get("dictionary_file") if isinstance(board, dict) else None
        if not isinstance(name, str | Path) or Path(name).is_absolute():
            return data
        base = Path(data["source"]).parent if isinstance(data.get("source"), str | Path) else Path.cwd()
        return {**data, "board": {**board, "dictionary_file": str(base / name)}}

    @model_validator(mode="after")
    def _unique_names(self) -> SceneSpec:
        for label, items in (("objects", self.objects), ("static_meshes", self.static_meshes),
                             ("collision_boxes", self.collision_boxes)):
            names = [item.name for item in items]
            dupes = sorted({n for n in names if names.count(n) > 1})
            if dupes:
                raise ValueError(f"{label}: duplicate names {dupes}")
        return self

    @property
    def base_dir(self) -> Path:
        """Folder that relative paths are resolved against."""
        return self.source.parent if self.source is not None else Path.cwd()

    def resolve(self, path: Path) -> Path:
        """Absolute path of a file named in the spec."""
        return path if path.is_absolute() else (self.base_dir / path)


# ----------------------------------------------------------------------------- loading
def parse_scene_spec(data: Any, source: Path | str = "<memory>", check_files: bool = True) -> SceneSpec:
    """Validate a parsed YAML mapping into a :class:`SceneSpec` (errors name ``source`` and the field).
    ``check_files=False``: no file the spec names is opened (the meshes' presence, the board's
    dictionary file) until :func:`check_named_files`."""
    src = Path(source)
    if not isinstance(data, dict):
        raise SpecError(f"{src}: the spec must be a YAML mapping at the top level, got {type(data).__name__}")
    try:
        spec = SceneSpec.model_validate({**data, "source": None if str(source) == "<memory>" else src.resolve()},
                                        context=None if check_files else {FILES_LATER: True})
    except ValidationError as exc:
        field_path, msg = validation_error_field(exc.errors(include_url=False))
        field_path = field_path or "<root>"
        raise SpecError(f"{src}: field '{field_path}': {msg}") from None
    if check_files:
        _check_mesh_files(spec, src)
    return spec


def mesh_fields(spec: SceneSpec) -> list[tuple[str, Path]]:
    """Every mesh the spec names: ``(field, path)``, e.g. ``("objects[2].mesh", /abs/cup.ply)``
    (the path resolved against the spec's folder, symlinks not resolved)."""
    return [(f"{label}[{i}].mesh", spec.resolve(item.mesh))
            for label, items in (("static_meshes", spec.static_meshes), ("objects", spec.objects))
            for i, item in enumerate(items)]


def named_files(spec: SceneSpec) -> list[tuple[str, Path]]:
    """Every file the spec names, ``(field, path)``: its meshes (:func:`mesh_fields`) and the
    board's dictionary file (``board.dictionary_file``, already absolute)."""
    named = mesh_fields(spec)
    if spec.board.dictionary_file is not None:
        named.append(("board.dictionary_file", spec.board.dictionary_file))
    return named


def check_named_files(spec: SceneSpec, src: Path | str) -> SceneSpec:
    """What :func:`parse_scene_spec` with ``check_files=False`` left unopened, opened now: the board's
    dictionary file is read and must hold the board's markers (SpecError naming ``src`` and the field)."""
    try:
        spec.board.check_markers()
    except ValueError as exc:
        raise SpecError(f"{src}: field 'board': {exc}") from None
    return spec


def _check_mesh_files(spec: SceneSpec, src: Path) -> None:
    for field, path in mesh_fields(spec):
        if not path.is_file():
            raise SpecError(f"{src}: field '{field}': file not found: {path}")


def load_scene_spec(path: Path | str, check_files: bool = True) -> SceneSpec:
    """Read and validate a scene spec YAML file (duplicate keys and absurd nesting are errors)."""
    p = Path(path)
    if not p.is_file():
        raise SpecError(f"{p}: scene spec not found")
    return parse_scene_spec(read_yaml(p, error=SpecError), p, check_files=check_files)


def spec_to_yaml(spec: SceneSpec) -> str:
    """Serialise a spec back to YAML (paths as written, enums as strings)."""
    return yaml.safe_dump(spec.model_dump(mode="json", exclude={"source"}), sort_keys=False)


"""The scene-directory layout and the frame record of ``capture/frames.jsonl``.

Each stage reads what earlier stages wrote and writes its own sub-folder; the paths live
here so that no stage needs to know another stage's internals.
"""

from __future__ import annotations

import filecmp
import hashlib
import logging
import os
import shutil
import tempfile
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from brave6d.core.atomic import atomic_write_text, staged_folder
from brave6d.core.errors import DataError, NonRigidTransformError, validation_error_field
from brave6d.core.json_input import parse_json
from brave6d.core.spec import SceneSpec, load_scene_spec, spec_to_yaml
from brave6d.core.transforms import check_rigid

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CaptureLayout:
    """Paths of one capture folder: the scene capture or the calibration board capture."""

    root: Path

    @property
    def plan_path(self) -> Path:
        return self.root / "plan.json"

    @property
    def plan_plot_path(self) -> Path:
        return self.root / "plan.png"

    @property
    def frames_path(self) -> Path:
        return self.root / "frames.jsonl"

    @property
    def camera_path(self) -> Path:
        return self.root / "camera.json"

    @property
    def rgb_dir(self) -> Path:
        return self.root / "rgb"

    @property
    def depth_dir(self) -> Path:
        return self.root / "depth"

    @property
    def sim_truth_dir(self) -> Path:
        """Simulator ground truth (object-id buffers, true poses) for tests only: no stage reads it."""
        return self.root / "sim_truth"

    def file(self, relative: str) -> Path:
        """A file a frame record names (``rgb``, ``depth``: relative to this capture folder)."""
        return self.root / relative

    @property
    def sim_object_ids_dir(self) -> Path:
        """The simulator's object-id buffers (tests only)."""
        return self.sim_truth_dir / "object_ids"

    def sim_object_ids_path(self, index: int) -> Path:
        """The simulator's object-id buffer (uint16 PNG) of frame ``index`` (tests only)."""
        return self.sim_object_ids_dir / f"{index:06d}.png"

    def sim_pose_path(self, index: int) -> Path:
        """The simulator's true poses of frame ``index`` (tests only)."""
        return self.sim_truth_dir / "poses" / f"{index:06d}.json"

    def frames(self) -> list[FrameRecord]:
        """All complete frame records."""
        return FrameLog(self.frames_path).read()


@dataclass(frozen=True)
class SceneDir:
    """Paths of one scene directory (the scene-directory contract in docs/ARCHITECTURE.md).

    Every path of a scene directory is built here: a stage's folder and each file in it that a
    module names. A folder with a format of its own names its inside through its owner module
    (the bundle: ``brave6d.serve``; the BOP export: ``brave6d.annotation``; the undistorted
    cache: ``brave6d.core.undistort``). ``tests/test_scene_paths.py`` finds paths built by hand.
    """

    root: Path

    def __init__(self, root: Path | str) -> None:
        object.__setattr__(self, "root", Path(root))

    # top level
    @property
    def spec_path(self) -> Path:
        return self.root / "scene.yaml"

    # capture/
    @property
    def capture(self) -> CaptureLayout:
        """The scene capture (``capture/``)."""
        return CaptureLayout(self.root / "capture")

    @property
    def board_capture(self) -> CaptureLayout:
        """The ChArUco board capture used for calibration (``calibration/board_capture/``)."""
        return CaptureLayout(self.calibration_dir / "board_capture")

    @property
    def capture_dir(self) -> Path:
        return self.capture.root

    @property
    def plan_path(self) -> Path:
        return self.capture.plan_path

    @property
    def frames_path(self) -> Path:
        return self.capture.frames_path

    @property
    def camera_path(self) -> Path:
        return self.capture.camera_path

    @property
    def rgb_dir(self) -> Path:
        return self.capture.rgb_dir

    @property
    def depth_dir(self) -> Path:
        return self.capture.depth_dir

    @property
    def import_record_path(self) -> Path:
        """What ``brave6d import`` brought in from a capture made elsewhere, and how (its world, scale, up)."""
        return self.capture.root / "import.json"

    @property
    def imported_points_path(self) -> Path:
        """The sparse points an imported capture brought (PLY, world frame, metres): the pose check's reference."""
        return self.capture.root / "imported_points.ply"

    # calibration/
    @property
    def calibration_dir(self) -> Path:
        return self.root / "calibration"

    @property
    def intrinsics_path(self) -> Path:
        return self.calibration_dir / "intrinsics.json"

    @property
    def handeye_path(self) -> Path:
        return self.calibration_dir / "handeye.json"

    @property
    def board_pdf_path(self) -> Path:
        """The printable ChArUco board (``brave6d calibrate --board-pdf``)."""
        return self.calibration_dir / "board.pdf"

    @property
    def assets_dir(self) -> Path:
        """The spec's meshes, copied beside it by :func:`init_scene_dir`."""
        return self.root / "assets"

    def asset_path(self, name: str) -> Path:
        """A mesh file ``name`` (relative, posix) under :attr:`assets_dir`."""
        return self.assets_dir / name

    # undistorted/ (brave6d.core.undistort's cache: its inside is that module's)
    @property
    def undistorted_dir(self) -> Path:
        return self.root / "undistorted"

    # sparse/ (training's COLMAP model)
    @property
    def sparse_dir(self) -> Path:
        return self.root / "sparse"

    @property
    def sparse_model_dir(self) -> Path:
        """The COLMAP model (binary) that initialises training."""
        return self.sparse_dir / "0"

    @property
    def sparse_stamp_path(self) -> Path:
        """What the COLMAP model was made from (training reuses it when nothing changed)."""
        return self.sparse_dir / "stamp.json"

    @property
    def sparse_holdout_path(self) -> Path:
        """The image names of the COLMAP model that were held out of training (COLMAP's bookkeeping;
        the split itself is :attr:`holdout_split_path`)."""
        return self.sparse_dir / "holdout.txt"

    # splat/ (training)
    @property
    def splat_dir(self) -> Path:
        return self.root / "splat"

    @property
    def splat_ply_path(self) -> Path:
        """The trained Gaussians (Inria PLY layout)."""
        return self.splat_dir / "point_cloud.ply"

    @property
    def splat_viewer_ply_path(self) -> Path:
        """The same Gaussians for other 3DGS viewers: the 3D filter baked into scales and opacities,
        no ``filter_3d`` property (``brave6d.training.write_viewer_ply``)."""
        return self.splat_dir / "point_cloud_viewer.ply"

    @property
    def metrics_path(self) -> Path:
        """The training's metrics (``brave6d.training``'s ``metrics.json``)."""
        return self.splat_dir / "metrics.json"

    @property
    def holdout_split_path(self) -> Path:
        """The views held out of training (``brave6d.training.read_holdout`` is its one reader)."""
        return self.splat_dir / "holdout.json"

    @property
    def holdout_images_dir(self) -> Path:
        """One side-by-side PNG (render | ground truth) per held-out view."""
        return self.splat_dir / "holdout"

    @property
    def curves_path(self) -> Path:
        return self.splat_dir / "curves.png"

    @property
    def checkpoints_dir(self) -> Path:
        return self.splat_dir / "checkpoints"

    @property
    def benchmark_training_path(self) -> Path:
        """Where ``benchmarks/training.py`` writes its JSON by default (read by the report)."""
        return self.splat_dir / "benchmark_training.json"

    @property
    def time_to_quality_path(self) -> Path:
        """Where ``benchmarks/time_to_quality.py`` writes its JSON by default (read by the report)."""
        return self.splat_dir / "time_to_quality.json"

    # annotation/
    @property
    def annotation_dir(self) -> Path:
        return self.root / "annotation"

    @property
    def objects_path(self) -> Path:
        """The annotation (``brave6d.annotation``'s ``objects.json``)."""
        return self.annotation_dir / "objects.json"

    @property
    def alignment_path(self) -> Path:
        return self.annotation_dir / "alignment.json"

    @property
    def annotation_meshes_dir(self) -> Path:
        return self.annotation_dir / "meshes"

    @property
    def bop_dir(self) -> Path:
        """The BOP export (its inside: ``brave6d.annotation``'s ``BopLayout``)."""
        return self.annotation_dir / "bop"

    # bundle/ (its inside: brave6d.serve.bundle)
    @property
    def bundle_dir(self) -> Path:
        return self.root / "bundle"

    # ------------------------------------------------------------------ helpers
    def load_spec(self) -> SceneSpec:
        """The validated ``scene.yaml`` of this directory."""
        return load_scene_spec(self.spec_path)

    def frames(self) -> list[FrameRecord]:
        """All complete frame records of the scene capture."""
        return self.capture.frames()


def init_scene_dir(root: Path | str, spec_file: Path | str) -> SceneDir:
    """Create ``root`` from a spec file: copies the spec and the mesh files it names.

    The copied ``scene.yaml`` names the meshes relative to the scene directory, so the folder is
    self-contained and can be moved to another machine. Each mesh lands where
    :func:`asset_paths` puts it, so two different meshes never share a file.

    Nothing is left behind on failure: a new (or empty) ``root`` is built in a staging folder and
    renamed into place at the end; into an existing scene directory the assets and ``scene.yaml``
    are first made and checked in a staging folder inside it, then moved in (``scene.yaml`` last).
    """
    spec = load_scene_spec(spec_file)
    scene = SceneDir(root)
    if scene.root.exists() and not scene.root.is_dir():
        raise DataError(f"{scene.root}: is a file, not a scene directory")
    if not scene.root.is_dir() or next(scene.root.iterdir(), None) is None:
        with staged_folder(scene.root) as staging:
            _write_scene_files(SceneDir(staging), spec)
        return scene
    with tempfile.TemporaryDirectory(dir=scene.root, prefix=".init-") as tmp:
        staged = SceneDir(tmp)
        _write_scene_files(staged, spec)
        made = sorted(p for p in staged.assets_dir.rglob("*") if p.is_file())
        for path in made:
            target = scene.asset_path(path.relative_to(staged.assets_dir).as_posix())
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, target)
        os.replace(staged.spec_path, scene.spec_path)
    return scene


def _write_scene_files(scene: SceneDir, spec: SceneSpec) -> None:
    """``scene.yaml`` and ``assets/`` of ``spec`` in ``scene`` (the meshes and a board's dictionary file
    copied, the copy checked)."""
    placed = asset_paths(spec)
    rewritten: dict[str, list[dict]] = {}
    data = spec.model_dump(mode="json", exclude={"source"})
    for key in ("static_meshes", "objects"):
        items = data.get(key, [])
        for item, model in zip(items, getattr(spec, key)):
            src = spec.resolve(model.mesh).resolve()
            dst = scene.asset_path(placed[src])
            _copy_mesh_with_sidecars(src, dst)
            item["mesh"] = dst.relative_to(scene.root).as_posix()
        rewritten[key] = items
    data.update(rewritten)
    if spec.board.dictionary_file is not None:  # the board's ArUco dictionary travels like a mesh
        dictionary = scene.asset_path(f"board/{spec.board.dictionary_file.name}")
        dictionary.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(spec.board.dictionary_file, dictionary)
        data["board"]["dictionary_file"] = dictionary.relative_to(scene.root).as_posix()
    import yaml

    atomic_write_text(scene.spec_path, yaml.safe_dump(data, sort_keys=False))
    load_scene_spec(scene.spec_path)  # the copy must validate exactly like the source


def mesh_files(src: Path) -> list[Path]:
    """The mesh and the files beside it that share its stem (OBJ ``.mtl``, textures), sorted.

    These travel together: an OBJ names its ``.mtl`` and the ``.mtl`` its texture by file name.
    """
    return sorted(p for p in src.parent.iterdir() if p.name.startswith(src.stem + ".") and p.is_file())


def _content_digest(files: list[Path]) -> str:
    """SHA-256 over the files' names and contents: equal digests mean interchangeable assets."""
    digest = hashlib.sha256()
    for path in files:
        with path.open("rb") as fh:
            digest.update(path.name.encode() + b"\0" + hashlib.file_digest(fh, "sha256").digest())
    return digest.hexdigest()


def asset_paths(spec: SceneSpec) -> dict[Path, str]:
    """Where each mesh file of ``spec`` (resolved absolute path) goes under ``assets/``.

    A mesh keeps its file name (``assets/cube.ply``) unless another mesh with the same stem
    (compared without case) but other content (its own file or a sidecar differs) is in the
    spec; then every such mesh goes to ``assets/<stem>-<digest>/<file name>``, ``digest`` being
    the first 12 hex digits of the SHA-256 of its files. Names depend only on the files, so
    the same spec always gives the same names, and identical meshes share one.
    """
    sources = {spec.resolve(m.mesh).resolve() for m in [*spec.static_meshes, *spec.objects]}
    digests = {src: _content_digest(mesh_files(src)) for src in sources}
    variants: dict[str, set[str]] = defaultdict(set)
    for src, digest in digests.items():
        variants[src.stem.casefold()].add(digest)
    return {src: src.name if len(variants[src.stem.casefold()]) == 1 else f"{src.stem}-{digests[src][:12]}/{src.name}"
            for src in sources}


def _copy_mesh_with_sidecars(src: Path, dst: Path) -> None:
    """Copy a mesh and its sidecars (:func:`mesh_files`) into ``dst``'s folder, unless already equal."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    for sibling in mesh_files(src):
        target = dst.parent / sibling.name
        if not (target.is_file() and filecmp.cmp(sibling, target, shallow=False)):
            shutil.copy2(sibling, target)


def write_spec(scene: SceneDir, spec: SceneSpec) -> Path:
    """Write ``spec`` as the scene directory's ``scene.yaml`` (atomically)."""
    return atomic_write_text(scene.spec_path, spec_to_yaml(spec))


# ----------------------------------------------------------------------------- frame records
Matrix4List = Annotated[list[list[float]], Field(min_length=4, max_length=4)]


class FrameRecord(BaseModel):
    """One captured frame: image files (relative to ``capture/``) and the robot state."""

    model_config = ConfigDict(extra="allow", frozen=True)

    index: Annotated[int, Field(ge=0)]
    view_id: str
    distance_level: Annotated[int, Field(ge=0)]
    distance_m: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    rgb: str
    depth: str | None = None
    base_T_tcp: Matrix4List
    joints: Annotated[list[Annotated[float, Field(allow_inf_nan=False)]], Field(min_length=6, max_length=6)]
    timestamp: Annotated[float, Field(allow_inf_nan=False)]

    @field_validator("base_T_tcp")
    @classmethod
    def _rigid(cls, value: list[list[float]]) -> list[list[float]]:
        try:
            check_rigid(value, "base_T_tcp")
        except NonRigidTransformError as exc:
            raise ValueError(str(exc)) from None
        return value

    @property
    def base_T_tcp_matrix(self) -> np.ndarray:
        return np.asarray(self.base_T_tcp, dtype=np.float64)


class FrameLog:
    """Append-only ``frames.jsonl``: one JSON record per line, each append fsync'ed.

    A process killed mid-append leaves at most a partial last line; :meth:`read` drops it with a
    warning (that frame is simply captured again on resume). A corrupt line elsewhere is an error
    naming the line, since silently skipping it would lose a frame.
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)

    def read(self) -> list[FrameRecord]:
        """All complete records, in file order."""
        return list(self._iter())

    def _iter(self) -> Iterator[FrameRecord]:
        if not self.path.exists():
            return
        raw = self.path.read_bytes()
        lines = raw.split(b"\n")
        complete = lines[:-1]
        tail = lines[-1]
        if tail.strip():
            log.warning("%s: ignoring an incomplete last line (interrupted write)", self.path)
        for number, line in enumerate(complete, start=1):
            if not line.strip():
                continue
            try:
                yield FrameRecord.model_validate(parse_json(line, f"{self.path}:{number}: not a JSON record"))
            except ValidationError as exc:
                where, msg = validation_error_field(exc.errors(include_url=False), dotted=True)
                raise DataError(f"{self.path}:{number}: field '{where}': {msg}") from None

    def append(self, record: FrameRecord) -> None:
        """Append one record durably (single write + fsync)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._drop_partial_tail()
        line = (record.model_dump_json() + "\n").encode("utf-8")
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
            os.fsync(fd)
        finally:
            os.close(fd)

    def _drop_partial_tail(self) -> None:
        if not self.path.exists() or self.path.stat().st_size == 0:
            return
        with open(self.path, "rb") as handle:
            handle.seek(-1, os.SEEK_END)
            if handle.read(1) == b"\n":
                return
        raw = self.path.read_bytes()
        atomic_write_text(self.path, raw[: raw.rfind(b"\n") + 1].decode("utf-8"))

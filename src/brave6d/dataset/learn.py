"""The dataset's learned model: one per object library, trained once for every scene of the dataset.

A dataset has one object library (:mod:`brave6d.core.dataset_spec`), so a run trains one model of
it, whatever the number of scenes. :class:`LibraryLearnJob` (a submitit ``Checkpointable``, run by
the same executor as the scene jobs: on a cluster it gets a node of its own) renders a synthetic
``train_pbr`` of the library (``brave6d.synth``) and trains the learned estimator on it
(``brave6d.evaluation.learned.learn_and_card``, the demo's ``learn`` stage's call). Everything lives in
``WORKDIR/learned/``:

- ``library.yaml``: what the split is rendered from: the library (its meshes in ``WORKDIR/objects/``)
  and the first scene (camera, capture rings, effects), nothing else of ``dataset.yaml``; so a scene
  appended to the dataset, a new version or another ``cluster`` block changes nothing here;
- ``models/``: the library's BOP models (mm, ``models_info.json``), what the model trains against;
- ``synth/``: the split (resumable, image by image);
- ``model/``: ``model.pt``, ``card.json``, ``MODEL_CARD.md`` (``release build`` ships them);
- ``status.json``: the step's record (``running`` / ``done`` / ``failed``, the options' fingerprint,
  figures), written only by the job; ``learn.lock``: held while the job runs.

Resumable like the scenes: a step recorded ``done`` for the same fingerprint (library.yaml, the
library's meshes, preset, images, image size, device) is not run again (no job); a stopped job
continues the split where it stopped and the training from its checkpoint; a finished model whose
inputs' checksum is unchanged is reused (the training's own reuse key).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import submitit

from brave6d.core.atomic import atomic_write_text, file_sha256, read_json
from brave6d.core.errors import BraveError, DataError
from brave6d.core.locks import FileLock, LockHeld
from brave6d.core.progress import Stopwatch

log = logging.getLogger(__name__)

#: ``WORKDIR/learned/`` and what it holds (module docstring).
LEARNED_DIR = "learned"
LIBRARY_SPEC = "library.yaml"
STATUS_FORMAT = "brave6d-dataset-learn-status/1"
#: The defaults of a full run and of a ``--quick`` one (the demo's: ``brave6d.evaluation.learned`` demo stage).
DEFAULT_PRESET, DEFAULT_IMAGES = "fast", 300
QUICK_PRESET, QUICK_IMAGES, QUICK_SIZE = "tiny", 24, (320, 200)


def learned_root(workdir: Path) -> Path:
    """``WORKDIR/learned``."""
    return Path(workdir) / LEARNED_DIR


def learned_model_dir(workdir: Path) -> Path:
    """``WORKDIR/learned/model``: the dataset's trained model (``model.pt`` and its card)."""
    return learned_root(workdir) / "model"


@dataclass(frozen=True)
class LearnOptions:
    """The learn step of a run: ``preset`` (a learn preset's name), ``images`` (train_pbr images),
    ``width`` / ``height`` (None: the first scene's camera), ``seed`` of the split."""

    preset: str = DEFAULT_PRESET
    images: int = DEFAULT_IMAGES
    width: int | None = None
    height: int | None = None
    seed: int = 0

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def learn_options(cluster: Any, quick: bool, *, skip: bool = False, preset: str | None = None,
                  images: int | None = None) -> LearnOptions | None:
    """The run's learn step from the flags (``--no-learn``, ``--learn-preset``, ``--learn-images``), else the
    ``cluster`` block's ``learn`` / ``learn_preset`` / ``learn_images``, else the defaults (``--quick``: the
    tiny preset on 24 small images); None: no learn step. An unknown preset is an error naming where it came from."""
    from brave6d.evaluation.learned import get_learn_preset

    if skip or not cluster.learn:
        return None
    name = preset if preset is not None else cluster.learn_preset
    try:
        get_learn_preset(name if name is not None else DEFAULT_PRESET)
    except BraveError as exc:
        raise BraveError(f"{'--learn-preset' if preset is not None else 'cluster.learn_preset'}: {exc}") from None
    count = images if images is not None else cluster.learn_images
    if count is not None and count < 1:
        raise BraveError(f"--learn-images: at least 1 image is needed, got {count}")
    if quick:
        return LearnOptions(name or QUICK_PRESET, count or QUICK_IMAGES, *QUICK_SIZE)
    return LearnOptions(name or DEFAULT_PRESET, count or DEFAULT_IMAGES)


def write_library_spec(workdir: Path) -> Path:
    """``WORKDIR/learned/library.yaml`` from ``WORKDIR/dataset.yaml`` (module docstring); rewritten only
    when its text changes."""
    import yaml

    from brave6d.core.yaml_io import read_yaml

    workdir = Path(workdir)
    data = read_yaml(workdir / "dataset.yaml", error=DataError)
    objects = [{**o, "mesh": f"../{o['mesh']}"} for o in data["objects"]]
    first = data["scenes"][0]
    scene = {"dir": first["dir"]} if "dir" in first else {"spec": f"../{first['spec']}"}
    text = yaml.safe_dump({"name": data["name"], "version": "library", "license": "see ../dataset.yaml",
                           "citation": "see ../dataset.yaml", "objects": objects, "scenes": [scene]}, sort_keys=False)
    path = learned_root(workdir) / LIBRARY_SPEC
    if not (path.is_file() and path.read_text(encoding="utf-8") == text):
        atomic_write_text(path, text)
    return path


def learn_fingerprint(workdir: Path, options: LearnOptions, device: str) -> str:
    """What the step's outputs depend on: ``library.yaml``, the library's meshes, the options and the device."""
    from brave6d.core.dataset_spec import load_dataset_spec

    spec_path = learned_root(workdir) / LIBRARY_SPEC
    dataset = _load_library(workdir, load_dataset_spec)
    h = hashlib.sha256(file_sha256(spec_path).encode())
    for o in dataset.spec.objects:
        h.update(f"{o.name}:{file_sha256(dataset.spec.resolve(o.mesh))}".encode())
    h.update(json.dumps({**options.to_json(), "device": device}, sort_keys=True).encode())
    return h.hexdigest()[:16]


def read_learn_status(workdir: Path) -> dict[str, Any]:
    """``WORKDIR/learned/status.json`` (``{}`` before the step's first run)."""
    path = learned_root(workdir) / "status.json"
    if not path.is_file():
        return {}
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != STATUS_FORMAT:
        raise DataError(f"{path}: not a learn status record (expected format {STATUS_FORMAT!r})")
    return data


def learn_is_done(workdir: Path, fingerprint: str) -> bool:
    """The step is recorded done for ``fingerprint`` and its model and card are there."""
    status = read_learn_status(workdir)
    model = learned_model_dir(workdir)
    return (status.get("state") == "done" and status.get("fingerprint") == fingerprint
            and (model / "model.pt").is_file() and (model / "card.json").is_file())


def _mark(workdir: Path, state: str, fingerprint: str, **details: Any) -> None:
    from brave6d.core.atomic import atomic_write_json
    from brave6d.core.locks import Process

    record: dict[str, Any] = {"format": STATUS_FORMAT, "state": state, "fingerprint": fingerprint,
                              "at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    if state == "running":
        record.update(Process.current().to_json())
    record.update(details)
    atomic_write_json(learned_root(workdir) / "status.json", record)


def _load_library(workdir: Path, load: Any) -> Any:
    """``library.yaml`` loaded with the work directory's folders allowed (its meshes and first scene
    lie in ``WORKDIR``; a captured first scene where it lies)."""
    path = learned_root(workdir) / LIBRARY_SPEC
    return load(path, **_allowed(workdir))


def _allowed(workdir: Path) -> dict[str, tuple[Path, ...]]:
    from brave6d.core.yaml_io import read_yaml

    data = read_yaml(learned_root(workdir) / LIBRARY_SPEC, error=DataError)
    dirs = tuple(Path(s["dir"]) for s in data["scenes"] if "dir" in s)
    return {"mesh_dirs": (Path(workdir),), "scene_dirs": dirs}


@dataclass(frozen=True)
class LearnOutcome:
    """How the step ended: its error (None: done) and its figures; ``busy``: the live job already running it."""

    error: str | None = None
    figures: dict[str, Any] | None = None
    busy: str | None = None


class LibraryLearnJob(submitit.helpers.Checkpointable):
    """Render the library's train_pbr and train its model (module docstring); never raises for the
    step's failure: the outcome and ``status.json`` carry the error."""

    def __init__(self, workdir: Path, options: LearnOptions, device: str = "auto", fingerprint: str = "") -> None:
        self.workdir, self.options, self.device, self.fingerprint = Path(workdir), options, device, fingerprint

    def __call__(self) -> LearnOutcome:
        from brave6d.core.runtime import prepare_process

        prepare_process()
        lock = FileLock(learned_root(self.workdir) / "learn.lock", "dataset learned model")
        try:
            lock.acquire()
        except LockHeld as exc:
            return LearnOutcome(busy=exc.holder.describe())
        with lock:
            return self._run()

    def _run(self) -> LearnOutcome:
        from brave6d.evaluation.learned import get_learn_preset

        previous = read_learn_status(self.workdir)
        resume = previous.get("fingerprint") == self.fingerprint  # a checkpoint of these very options
        _mark(self.workdir, "running", self.fingerprint, options=self.options.to_json())
        with Stopwatch() as watch:
            try:
                figures = learn_library(self.workdir, get_learn_preset(self.options.preset), self.options,
                                        self.device, resume=resume)
            except Exception as exc:  # noqa: BLE001 - recorded and reported; the scenes are not affected
                error = str(exc) if isinstance(exc, BraveError) else f"{type(exc).__name__}: {exc}"
                if not isinstance(exc, BraveError):
                    log.error("learned model:\n%s", traceback.format_exc())
                line = error.splitlines()[0] if error else type(exc).__name__
                _mark(self.workdir, "failed", self.fingerprint, seconds=round(watch.seconds, 1), error=line)
                return LearnOutcome(error=error)
        _mark(self.workdir, "done", self.fingerprint, seconds=round(watch.seconds, 1), figures=figures,
              options=self.options.to_json())
        return LearnOutcome(figures=figures)


def learn_library(workdir: Path, preset: Any, options: LearnOptions, device: str = "auto",
                  resume: bool = False) -> dict[str, Any]:
    """The step itself (module docstring), with a :class:`~brave6d.evaluation.learned.LearnPreset`
    object (the tests shorten ``tiny``); returns its figures."""
    from brave6d.annotation import write_bop_models
    from brave6d.core.dataset_spec import load_dataset_spec
    from brave6d.evaluation.learned import learn_and_card
    from brave6d.synth import SynthOptions, synthesize

    root = learned_root(workdir)
    spec_path = write_library_spec(workdir)
    library = _load_library(workdir, load_dataset_spec).spec
    ids = library.obj_ids()
    models = write_bop_models(root / "models", [(ids[o.name], library.resolve(o.mesh).resolve(), float(o.scale),
                                                 o.symmetry) for o in library.objects])
    t0 = time.perf_counter()
    allowed = _allowed(workdir)
    synth = synthesize(spec_path, root / "synth",
                       SynthOptions(images=options.images, seed=options.seed, workers=min(4, os.cpu_count() or 1),
                                    width=options.width, height=options.height, **allowed))
    synth_seconds = time.perf_counter() - t0
    card = learn_and_card(root / "synth", models, learned_model_dir(workdir), preset, device, resume=resume,
                          show_progress=False)
    held = card.get("heldout") or {}
    recall = held.get("detection_recall_iou50", {})
    return {"objects": len(card["objects"]), "train_pbr images": options.images, "rendered": synth.rendered,
            "synth s": round(synth_seconds, 1), "train s": card["train_seconds"], "preset": preset.name,
            "held-out recall min": min(recall.values()) if recall else "n/a",
            "held-out AR true box": held.get("pose_ar", {}).get("true_box_rgb", "n/a")}

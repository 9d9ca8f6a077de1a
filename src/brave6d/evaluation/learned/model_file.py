"""The trained estimator on disk, owned here: ``MODEL_DIR/model.pt`` (weights and what inference
needs to know about the objects), ``checkpoint.pt`` (a run in progress) and ``card.json`` /
``MODEL_CARD.md`` (:mod:`brave6d.evaluation.learned.card`).

Both ``.pt`` files hold tensors, numbers and strings only and are read with
``torch.load(weights_only=True)``: a model file from elsewhere cannot run code.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError

FORMAT = "brave6d-learned/1"
MODEL = "model.pt"
CHECKPOINT = "checkpoint.pt"


@dataclass(frozen=True)
class ObjectNorm:
    """What inference needs of an object: its class index and the centre / radius (mm) that
    normalise its coordinates, and its diameter (mm)."""

    obj_id: int
    class_index: int
    centre_mm: NDArray[np.float64]
    radius_mm: float
    diameter_mm: float


@dataclass
class LearnedModel:
    """A trained detector and coordinate net with their settings (``preset``: the preset's fields)."""

    preset: dict[str, Any]
    objects: dict[int, ObjectNorm]
    detector_state: dict[str, Any]
    pose_state: dict[str, Any]
    inputs_key: str  # digest of what it was trained from (train_pbr, models, preset, seed)

    @property
    def classes(self) -> list[int]:
        return sorted(self.objects, key=lambda o: self.objects[o].class_index)


def save_torch(path: Path, payload: dict[str, Any]) -> Path:
    """``torch.save`` written atomically."""
    import torch

    from brave6d.core.atomic import atomic_write_bytes

    buf = io.BytesIO()
    torch.save(payload, buf)
    return atomic_write_bytes(path, buf.getvalue())


def load_torch(path: Path) -> dict[str, Any]:
    """A ``.pt`` file read as tensors only; a clear error names the file otherwise."""
    import torch

    if not path.is_file():
        raise DataError(f"{path}: not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a damaged or foreign file
        raise DataError(f"{path}: not a readable learned-model file ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise DataError(f"{path}: not a {FORMAT} file (field 'format' is "
                        f"{payload.get('format') if isinstance(payload, dict) else type(payload).__name__!r})")
    return payload


def write_model(model_dir: Path, model: LearnedModel) -> Path:
    """Write ``model_dir/model.pt``."""
    objects = {str(o.obj_id): {"class_index": o.class_index, "centre_mm": [float(x) for x in o.centre_mm],
                               "radius_mm": o.radius_mm, "diameter_mm": o.diameter_mm}
               for o in model.objects.values()}
    return save_torch(model_dir / MODEL, {"format": FORMAT, "preset": model.preset, "objects": objects,
                                          "detector": model.detector_state, "pose": model.pose_state,
                                          "inputs_key": model.inputs_key})


def read_model(model_dir: Path | str) -> LearnedModel:
    """Read ``model_dir/model.pt`` (``model_dir`` may also name the file itself)."""
    path = Path(model_dir)
    path = path if path.is_file() else path / MODEL
    payload = load_torch(path)
    try:
        objects = {int(k): ObjectNorm(int(k), int(v["class_index"]), np.asarray(v["centre_mm"], dtype=np.float64),
                                      float(v["radius_mm"]), float(v["diameter_mm"]))
                   for k, v in payload["objects"].items()}
        model = LearnedModel(dict(payload["preset"]), objects, payload["detector"], payload["pose"],
                             str(payload["inputs_key"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{path}: malformed learned model ({type(exc).__name__}: {exc})") from None
    if sorted(o.class_index for o in objects.values()) != list(range(len(objects))) or not objects:
        raise DataError(f"{path}: field 'objects': class indices must be 0..{len(objects) - 1}")
    return model

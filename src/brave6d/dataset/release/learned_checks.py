"""What ``release verify`` checks of a release's learned model beyond its checksums: the card's
schema, the preset's types and bounds, and that the weights load into their networks.

``brave6d serve RELEASE`` never opens the model, so verify is the only check a downloaded model
gets before the learned agents, ``learn heldout`` or the report use it. Its card and preset come
from the release's author: a field of the wrong type ends those in a traceback, a width of a
million allocates terabytes, weights of another shape fail only when an agent starts. So:

- :func:`check_card`: ``card.json`` against :class:`LearnedCard` (every field the readers use, its
  type and range; extra fields are let through);
- :func:`check_preset`: the preset (the card's, and the model's own, which must be the same) field by
  field against :data:`PRESET_BOUNDS` (exact types: an integer field takes no float or boolean),
  then :class:`~brave6d.evaluation.learned.LearnPreset`'s own checks (multiples of 16, ...);
- :func:`check_weights`: the detector and the coordinate net built on the CPU at the preset's widths
  (bounded first) and the weights loaded into them strictly (every tensor present, of its shape),
  every tensor finite.

Each refusal is a :class:`~brave6d.dataset.release.source.ReleaseError` in one line naming the
member and the field.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from brave6d.core.errors import BraveError, validation_error_field
from brave6d.dataset.release.source import ReleaseError

#: The most classes (objects) a learned model of a release may have.
MAX_CLASSES = 10_000

#: (type, low, high) of every preset field a release may carry. The widths bound the networks'
#: size (channels; ``paper`` uses 32), the image sizes the memory of a batch (``paper``: 640).
PRESET_BOUNDS: dict[str, tuple[type, float, float]] = {
    "work_width": (int, 64, 4096), "crop_source_width": (int, 64, 8192), "crop_px": (int, 32, 512), "crop_px_min": (int, 32, 512),
    "detector_steps": (int, 1, 10**8), "detector_batch": (int, 1, 4096), "detector_patch": (int, 16, 2048),
    "detector_lr": (float, 1e-12, 10.0), "detector_width": (int, 1, 256),
    "pose_steps": (int, 1, 10**8), "pose_batch": (int, 1, 4096), "pose_lr": (float, 1e-12, 10.0),
    "pose_width": (int, 1, 256), "heldout_every": (int, 2, 10**6), "checkpoint_every": (int, 1, 10**8),
    "seed": (int, 0, 2**63 - 1), "fp32_step_share": (float, 1e-6, 1.0),
}
#: Bounds of a preset field this table does not know (a field added after it was written).
_OTHER_INT, _OTHER_FLOAT = (int, 0, 10**9), (float, 0.0, 1e9)
#: The preset fields the readers index (the estimator, ``learn heldout``, the card's text).
REQUIRED_PRESET = ("name", "work_width", "crop_px", "detector_steps", "detector_batch", "detector_width",
                   "pose_steps", "pose_batch", "pose_width", "heldout_every", "seed")

Hex64 = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
Count = Annotated[int, Field(ge=0, le=10**9, strict=True)]
Number = Annotated[float, Field(allow_inf_nan=False)]
Text = Annotated[str, Field(max_length=4096)]
Key = Annotated[str, Field(max_length=64)]
Figures = Annotated[dict[Key, Number | None], Field(max_length=MAX_CLASSES)]
VARIANTS = ("true_box_rgb", "true_box_depth", "detected_rgb", "detected_depth")


class _Loose(BaseModel):
    """Fields typed as the readers use them; fields it does not name are let through."""

    model_config = ConfigDict(extra="allow", strict=True)


class HeldoutFigures(_Loose):
    """The card's ``heldout`` block (:meth:`brave6d.evaluation.learned.HeldoutScores.to_json`)."""

    images: Count
    instances: Count
    detection_recall_iou50: Figures
    detection_ap_iou50: Figures
    pose_ar: dict[Key, Number | None] = Field(max_length=64)
    pose_ar_per_object: dict[Key, Figures] = Field(max_length=64)
    detection_threshold: Number
    seconds_per_estimate: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    detect_widths: Annotated[list[Annotated[int, Field(ge=1, le=100_000)]], Field(max_length=64)] | None = None
    refusals: dict[Key, dict[Key, Count]] | None = None
    source: Text | None = None
    source_sha256: Hex64 | None = None
    whole_split: bool | None = None


class LearnedCard(_Loose):
    """``card.json`` (:func:`brave6d.evaluation.learned.card.card_fields`), as a release may hold it."""

    format: str
    train_pbr: Text
    train_pbr_sha256: Hex64
    images: Count
    heldout_images: Count
    trained_on_images: Count
    objects: Annotated[list[Annotated[int, Field(ge=1, lt=2**31)]], Field(min_length=1, max_length=MAX_CLASSES)]
    preset: dict[Key, Any] = Field(max_length=256)
    device: Annotated[str, Field(max_length=200)]
    machine: Annotated[str, Field(max_length=200)]
    seconds: dict[Key, Annotated[float, Field(ge=0, allow_inf_nan=False)]] = Field(max_length=64)
    train_seconds: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    final_loss: dict[Key, Number | None] = Field(max_length=64)
    model_sha256: Hex64
    heldout: HeldoutFigures | None = None


def check_card(card: Any, shown: str) -> LearnedCard:
    """``card`` (the parsed ``card.json``) against :class:`LearnedCard` and its preset
    (:func:`check_preset`); ReleaseError naming ``shown`` and the field."""
    try:
        model = LearnedCard.model_validate(card)
    except ValidationError as exc:
        field, message = validation_error_field(exc.errors(include_url=False))
        raise ReleaseError(f"{shown}: field '{field or '<root>'}': {message}") from None
    if len(set(model.objects)) != len(model.objects):
        raise ReleaseError(f"{shown}: field 'objects': an object is listed twice ({model.objects})")
    if model.heldout is not None:
        for variant in VARIANTS:
            if variant not in model.heldout.pose_ar or variant not in model.heldout.pose_ar_per_object:
                raise ReleaseError(f"{shown}: field 'heldout.pose_ar': the figures of {variant!r} are missing")
    check_preset(model.preset, shown)
    return model


def check_preset(preset: Any, shown: str) -> Any:
    """The :class:`~brave6d.evaluation.learned.LearnPreset` a release's ``preset`` dict describes,
    each field of the exact type and within :data:`PRESET_BOUNDS`; ReleaseError naming ``shown`` (the
    member) and the field."""
    from brave6d.evaluation.learned import LearnPreset

    where = f"{shown}: field 'preset'"
    if not isinstance(preset, dict):
        raise ReleaseError(f"{where}: an object of the preset's fields is required, got {type(preset).__name__}")
    missing = [name for name in REQUIRED_PRESET if name not in preset]
    if missing:
        raise ReleaseError(f"{where}: the preset lacks {', '.join(missing)}")
    declared = {f.name: f for f in dataclasses.fields(LearnPreset)}
    known: dict[str, Any] = {}
    for name, value in preset.items():
        if name not in declared:
            continue  # a field of another version: no reader of this one uses it
        known[name] = value
        if declared[name].type in ("str", str):
            if not isinstance(value, str) or not 0 < len(value) <= 100:
                raise ReleaseError(f"{shown}: field 'preset.{name}': a name of 1..100 characters is required, got "
                                   f"{_shown(value)}")
            continue
        kind, low, high = PRESET_BOUNDS.get(name, _OTHER_FLOAT if declared[name].type in ("float", float) else _OTHER_INT)
        exact = isinstance(value, int) and not isinstance(value, bool) if kind is int else \
            isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if not exact or not low <= value <= high:
            what = f"an integer in {low}..{high}" if kind is int else f"a number in {low:g}..{high:g}"
            raise ReleaseError(f"{shown}: field 'preset.{name}': {what} is required, got {_shown(value)}")
    try:
        return LearnPreset(**known)
    except (BraveError, TypeError, ValueError) as exc:
        raise ReleaseError(f"{where}: {exc}") from None


def check_weights(model: Any, shown: str) -> None:
    """Build the model's networks on the CPU at its preset's widths (bounded by :func:`check_preset`
    first) and load its weights into them strictly; every tensor finite. ReleaseError naming ``shown``."""
    import torch

    from brave6d.evaluation.learned import LearnedEstimator

    check_preset(model.preset, shown)
    if not 1 <= len(model.objects) <= MAX_CLASSES:
        raise ReleaseError(f"{shown}: field 'objects': 1..{MAX_CLASSES} objects are required, got {len(model.objects)}")
    for part, state in (("detector", model.detector_state), ("pose", model.pose_state)):
        if not isinstance(state, dict) or not all(isinstance(t, torch.Tensor) for t in state.values()):
            raise ReleaseError(f"{shown}: field '{part}': a dict of tensors (the network's weights) is required")
        for key, tensor in state.items():
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                raise ReleaseError(f"{shown}: field '{part}': tensor {str(key)[:80]!r} holds NaN or inf")
    try:
        LearnedEstimator(model, device="cpu")  # the networks at the preset's widths, weights loaded strictly
    except (RuntimeError, KeyError, TypeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0][:300] if str(exc).strip() else type(exc).__name__
        raise ReleaseError(f"{shown}: the weights do not fit the networks of its preset ({first})") from None


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else f"{type(value).__name__} of {len(text)} characters"

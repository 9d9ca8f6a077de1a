"""The holdout split: which captured views are held out of training, and ``splat/holdout.json``.

The rule follows the paper's protocol: 10% of the views of every distance level, chosen
deterministically (evenly spaced in capture order), at least one per level with two or more
views (:func:`holdout_split`). Training applies it to all recorded frames and writes the views
it held out once, with its metrics (:func:`write_holdout`; a frame skipped as bad is not
listed). Every other stage reads the split through :func:`read_holdout` and nothing else: the
bundle export, the report, the release (through the bundle).

A scene trained before ``holdout.json`` existed has none; :func:`read_holdout` then applies the
same rule to the capture's frames (with a warning), which gives the split that training used
unless it skipped a bad held-out frame.

This module is light (no torch), so a stage that only reads the split does not load training.
"""

from __future__ import annotations

import logging
import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.core.errors import DataError, validation_error_field
from brave6d.core.layout import FrameRecord, SceneDir

log = logging.getLogger(__name__)

HOLDOUT_FORMAT = "brave6d-holdout/1"
HOLDOUT_FRACTION = 0.10
HOLDOUT_PROTOCOL = "10% of the views of each distance level, evenly spaced in capture order"


# ----------------------------------------------------------------------------- the rule
def holdout_split(records: Sequence[FrameRecord], fraction: float = HOLDOUT_FRACTION) -> tuple[list[int], list[int]]:
    """``(train_indices, test_indices)`` (frame ``index`` values), stratified by distance level.

    Per level with n views (in capture-index order): ``round(fraction * n)`` test views, at
    least one when n >= 2 (never all of them), at evenly spaced positions
    ``floor((k + 0.5) * n / n_test)``.
    """
    by_level: dict[int, list[int]] = defaultdict(list)
    for r in records:
        by_level[r.distance_level].append(r.index)
    test: list[int] = []
    for level in sorted(by_level):
        idx = sorted(by_level[level])
        n = len(idx)
        n_test = math.floor(fraction * n + 0.5)
        if n >= 2:
            n_test = min(max(n_test, 1), n - 1)
        else:
            n_test = 0
        test.extend(idx[math.floor((k + 0.5) * n / n_test)] for k in range(n_test))
    test_set = set(test)
    train = sorted(r.index for r in records if r.index not in test_set)
    return train, sorted(test_set)


# ----------------------------------------------------------------------------- the file
class _View(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    index: Annotated[int, Field(ge=0)]
    view_id: str


class _HoldoutFile(BaseModel):
    model_config = ConfigDict(extra="ignore")

    format: Literal["brave6d-holdout/1"]
    protocol: str = HOLDOUT_PROTOCOL
    views: list[_View]


class _Identified(Protocol):
    @property
    def index(self) -> int: ...

    @property
    def view_id(self) -> str: ...


@dataclass(frozen=True)
class HeldOutView:
    """One view held out of training: its frame ``index`` and ``view_id`` in ``capture/frames.jsonl``."""

    index: int
    view_id: str


@dataclass(frozen=True)
class HoldoutSplit:
    """The views held out of a scene's training, in frame order.

    ``recorded``: read from ``splat/holdout.json``; False when the scene was trained before that
    file existed and the split was made again by :func:`holdout_split` from the capture.
    """

    views: tuple[HeldOutView, ...]
    recorded: bool = True

    @property
    def indices(self) -> list[int]:
        return [v.index for v in self.views]


def write_holdout(scene: SceneDir, views: Iterable[_Identified]) -> Path:
    """Write ``splat/holdout.json`` (atomically): the views a training held out (anything with
    ``index`` and ``view_id``: training views, frame records)."""
    listed = sorted({(int(v.index), str(v.view_id)) for v in views})
    return atomic_write_json(scene.holdout_split_path, {
        "format": HOLDOUT_FORMAT, "protocol": HOLDOUT_PROTOCOL,
        "views": [{"index": index, "view_id": view_id} for index, view_id in listed]})


def read_holdout(scene: SceneDir) -> HoldoutSplit:
    """The views held out of ``scene``'s training: ``splat/holdout.json``, else (a scene trained
    before that file) :func:`holdout_split` applied to the capture's frames, with a warning.

    A malformed file, or a frame index listed twice, is a :class:`DataError` naming the file and
    the field; neither the file nor a capture: a :class:`DataError` naming both.
    """
    path = scene.holdout_split_path
    if not path.is_file():
        return _recomputed(scene)
    data = read_json(path)
    if not isinstance(data, dict):
        raise DataError(f"{path}: a holdout split must be a JSON object, got {type(data).__name__}")
    try:
        parsed = _HoldoutFile.model_validate(data)
    except ValidationError as exc:
        loc, msg = validation_error_field(exc.errors(include_url=False))
        raise DataError(f"{path}: field '{loc or '<root>'}': {msg}") from None
    seen: set[int] = set()
    for i, v in enumerate(parsed.views):
        if v.index in seen:
            raise DataError(f"{path}: field 'views[{i}].index': frame {v.index} is listed twice")
        seen.add(v.index)
    return HoldoutSplit(tuple(sorted((HeldOutView(v.index, v.view_id) for v in parsed.views),
                                     key=lambda v: v.index)))


def _recomputed(scene: SceneDir) -> HoldoutSplit:
    if not scene.frames_path.is_file():
        raise DataError(f"{scene.holdout_split_path}: no holdout split, and no capture ({scene.frames_path}) to "
                        "make it from; train the scene first")
    records = scene.frames()
    _, test = holdout_split(records)
    log.warning("%s: missing (the scene was trained before the split was recorded); using the trainer's rule "
                "on %s (%s)", scene.holdout_split_path, scene.frames_path, HOLDOUT_PROTOCOL)
    wanted = set(test)
    return HoldoutSplit(tuple(HeldOutView(r.index, r.view_id) for r in sorted(records, key=lambda r: r.index)
                              if r.index in wanted), recorded=False)

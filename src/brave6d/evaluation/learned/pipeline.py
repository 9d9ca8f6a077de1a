"""Train, score the held-out images and write the card: what ``brave6d learn train``, the demo's
stage and a dataset run do in one call."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from brave6d.evaluation.learned.presets import LearnPreset

log = logging.getLogger(__name__)


def learn_and_card(train_pbr: Path | str, models_dir: Path | str, out: Path | str, preset: LearnPreset,
                   device: str = "auto", resume: bool = False, heldout: bool = True,
                   show_progress: bool = True) -> dict[str, Any]:
    """Train (or reuse) the model in ``out``, score it on the held-out images, write and return its card.
    A reused model keeps its card when the card is there."""
    from brave6d.core.atomic import file_sha256
    from brave6d.evaluation.learned.card import CARD, card_fields, read_card, write_card
    from brave6d.evaluation.learned.model_file import MODEL
    from brave6d.evaluation.learned.training import train_learned

    out = Path(out)
    result = train_learned(train_pbr, models_dir, out, preset, device, resume, show_progress)
    data = result.data
    assert data is not None
    if not result.trained and (out / CARD).is_file():
        card = read_card(out)
        assert result.model is not None  # a model reused, not trained, is always read
        if not heldout or _heldout_is_current(card, result.model):
            return card
        log.info("%s: the card's held-out figures were scored with other inference settings; scoring again", out)
        card.pop("format", None)
        card["heldout"] = _heldout(out, data, models_dir, show_progress)
        write_card(out, card)
        return read_card(out)
    scores = _heldout(out, data, models_dir, show_progress) if heldout else None
    import torch

    fields = card_fields(Path(train_pbr), data.digest, len(data.images), len(data.split(True)), data.classes,
                         dict(result.model.preset) if result.model is not None else preset.to_json(),  # as it ran
                         "cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available())
                         else "cpu", result.seconds, result.losses, file_sha256(out / MODEL), scores)
    write_card(out, fields)
    return read_card(out)


def heldout_only(model_dir: Path | str, train_pbr: Path | str, models_dir: Path | str,
                 detect_scales: tuple[float, ...] | None = None) -> dict[str, Any]:
    """Score ``model_dir`` on ``train_pbr``'s held-out images and update its card (``detect_scales``:
    the detector's input widths, default the estimator's)."""
    from brave6d.evaluation.learned.card import read_card, write_card
    from brave6d.evaluation.learned.data import load_training_data
    from brave6d.evaluation.learned.model_file import read_model

    model = read_model(model_dir)
    data = load_training_data(train_pbr, models_dir, int(model.preset["work_width"]), int(model.preset["heldout_every"]),
                              crop_width=int(model.preset.get("crop_source_width", model.preset["work_width"])))
    card = read_card(model_dir)
    card.pop("format", None)
    card["heldout"] = _heldout(Path(model_dir), data, models_dir, True, detect_scales)
    write_card(Path(model_dir), card)
    return read_card(model_dir)


def _heldout_is_current(card: dict[str, Any], model: Any) -> bool:
    """Whether the card's held-out figures were scored as the estimator of ``model`` (a
    :class:`LearnedModel` in memory) now detects (its input widths)."""
    from brave6d.evaluation.learned.inference import LearnedEstimator

    h = card.get("heldout")
    return isinstance(h, dict) and h.get("detect_widths") == LearnedEstimator(model).detect_widths


def _heldout(model_dir: Path, data: Any, models_dir: Path | str, show_progress: bool,
             detect_scales: tuple[float, ...] | None = None) -> dict[str, Any]:
    from brave6d.evaluation.learned.heldout import score_heldout
    from brave6d.evaluation.learned.inference import LearnedEstimator

    estimator = LearnedEstimator.load(model_dir, models_dir=models_dir)
    if detect_scales is not None:
        estimator.detect_scales = tuple(detect_scales)
    return score_heldout(estimator, data, models_dir, show_progress=show_progress).to_json()

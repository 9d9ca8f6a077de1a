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
                   show_progress: bool = True, heldout_pbr: Path | str | None = None) -> dict[str, Any]:
    """Train (or reuse) the model in ``out``, score it on the held-out images, write and return its card.
    ``heldout_pbr``: a split rendered apart (another seed), every image of which is scored instead of
    ``train_pbr``'s held-out slice (more images than the slice: steadier figures). A reused model
    keeps its card when the card is there and was scored as the estimator now works."""
    from brave6d.core.atomic import file_sha256
    from brave6d.evaluation.learned.card import CARD, card_fields, read_card, write_card
    from brave6d.evaluation.learned.data import scene_folders, split_digest
    from brave6d.evaluation.learned.model_file import MODEL
    from brave6d.evaluation.learned.training import train_learned

    out = Path(out)
    result = train_learned(train_pbr, models_dir, out, preset, device, resume, show_progress)
    data = result.data
    assert data is not None
    ran = dict(result.model.preset) if result.model is not None else preset.to_json()  # the preset as it ran
    # the split scored: its checksum tells whether a card is current; it is read only to be scored
    source_digest = data.digest if heldout_pbr is None else split_digest(scene_folders(heldout_pbr)[0].parent)[0]
    whole = source_digest != data.digest  # a split the model never saw: every image counts

    def score() -> dict[str, Any]:
        return _heldout(out, _heldout_data(data, heldout_pbr, models_dir, ran, show_progress), models_dir,
                        show_progress, whole=whole)

    if not result.trained and (out / CARD).is_file():
        card = read_card(out)
        assert result.model is not None  # a model reused, not trained, is always read
        if not heldout or _heldout_is_current(card, result.model, source_digest):
            return card
        log.info("%s: the card's held-out figures were scored on other images or with other inference settings; "
                 "scoring again", out)
        card.pop("format", None)
        card["heldout"] = score()
        write_card(out, card)
        return read_card(out)
    scores = score() if heldout else None
    import torch

    fields = card_fields(Path(train_pbr), data.digest, len(data.images), len(data.split(True)), data.classes,
                         ran,
                         "cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available())
                         else "cpu", result.seconds, result.losses, file_sha256(out / MODEL), scores)
    write_card(out, fields)
    return read_card(out)


def _heldout_data(data: Any, heldout_pbr: Path | str | None, models_dir: Path | str, preset: dict[str, Any],
                  show_progress: bool) -> Any:
    """The images the held-out figures are scored on: ``data`` (its held-out slice) without
    ``heldout_pbr``, else that split read as the model reads images."""
    from brave6d.evaluation.learned.data import load_training_data

    if heldout_pbr is None:
        return data
    return load_training_data(heldout_pbr, models_dir, int(preset["work_width"]), int(preset["heldout_every"]),
                              show_progress=show_progress,
                              crop_width=int(preset.get("crop_source_width", preset["work_width"])))


def heldout_only(model_dir: Path | str, train_pbr: Path | str, models_dir: Path | str,
                 detect_scales: tuple[float, ...] | None = None) -> dict[str, Any]:
    """Score ``model_dir`` on ``train_pbr`` and update its card (``detect_scales``: the detector's
    input widths, default the estimator's): on its held-out slice when it is the split the model
    trained on, else on every image (a split the model never saw)."""
    from brave6d.evaluation.learned.card import read_card, write_card
    from brave6d.evaluation.learned.model_file import read_model

    model = read_model(model_dir)
    data = _heldout_data(None, train_pbr, models_dir, model.preset, True)
    card = read_card(model_dir)
    card.pop("format", None)
    card["heldout"] = _heldout(Path(model_dir), data, models_dir, True, detect_scales,
                               whole=data.digest != card.get("train_pbr_sha256"))
    write_card(Path(model_dir), card)
    return read_card(model_dir)


def _heldout_is_current(card: dict[str, Any], model: Any, source_digest: str) -> bool:
    """Whether the card's held-out figures were scored on the split of checksum ``source_digest`` as
    the estimator of ``model`` (a :class:`LearnedModel` in memory) now works: its detector's input
    widths, the detection threshold, the coordinate net's crop zooms and the PnP."""
    from brave6d.evaluation.learned.presets import DETECTION_THRESHOLD
    from brave6d.evaluation.learned.inference import LearnedEstimator, pnp_method

    h = card.get("heldout")
    estimator = LearnedEstimator(model)
    return (isinstance(h, dict) and h.get("detect_widths") == estimator.detect_widths
            and h.get("detection_threshold") == DETECTION_THRESHOLD
            and h.get("crop_zooms") == [float(z) for z in estimator.crop_zooms]
            and h.get("pnp") == pnp_method()
            and h.get("source_sha256", card.get("train_pbr_sha256")) == source_digest)


def _heldout(model_dir: Path, data: Any, models_dir: Path | str, show_progress: bool,
             detect_scales: tuple[float, ...] | None = None, whole: bool = False) -> dict[str, Any]:
    """The held-out figures (JSON) of ``data``: its held-out slice, or every image when ``whole`` (a
    split the model never trained on), with where they come from."""
    from brave6d.evaluation.learned.heldout import score_heldout
    from brave6d.evaluation.learned.inference import LearnedEstimator

    estimator = LearnedEstimator.load(model_dir, models_dir=models_dir)
    if detect_scales is not None:
        estimator.detect_scales = tuple(detect_scales)
    images = list(range(len(data.images))) if whole else None
    scored = score_heldout(estimator, data, models_dir, show_progress=show_progress, images=images).to_json()
    return {**scored, "source": str(data.root), "source_sha256": data.digest, "whole_split": whole}

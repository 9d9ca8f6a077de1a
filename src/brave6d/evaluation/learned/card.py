"""The model card beside the weights, owned here: ``card.json`` (what a release and the report read)
and ``MODEL_CARD.md`` (what a person reads): the train_pbr it saw (images, checksum), the objects,
the preset and steps, the time and device, and the held-out figures."""

from __future__ import annotations

import math
import platform
from pathlib import Path
from typing import Any

from brave6d.core.errors import DataError

CARD = "card.json"
CARD_MD = "MODEL_CARD.md"
CARD_FORMAT = "brave6d-learned-card/1"


def write_card(model_dir: Path, fields: dict[str, Any]) -> Path:
    """Write ``card.json`` and ``MODEL_CARD.md`` of ``model_dir`` from ``fields`` (see :func:`card_fields`)."""
    from brave6d.core.atomic import atomic_write_json, atomic_write_text

    card = {"format": CARD_FORMAT, **fields}
    atomic_write_json(model_dir / CARD, card)
    atomic_write_text(model_dir / CARD_MD, card_markdown(card))
    return model_dir / CARD


def read_card(model_dir: Path | str) -> dict[str, Any]:
    """``card.json`` of a model folder."""
    from brave6d.core.atomic import read_json

    path = Path(model_dir) / CARD
    card = read_json(path)
    if not isinstance(card, dict) or card.get("format") != CARD_FORMAT:
        raise DataError(f"{path}: field 'format': not a {CARD_FORMAT} card")
    return card


def training_seconds(seconds: dict[str, float]) -> float:
    """Wall-clock seconds of training (the phases may run at once): ``training`` when recorded, else
    the phases' sum."""
    if "training" in seconds:
        return float(seconds["training"])
    return float(sum(v for k, v in seconds.items() if k in ("detector", "pose")))


def card_fields(train_pbr: Path, digest: str, images: int, heldout_images: int, objects: list[int], preset: dict[str, Any],
                device: str, seconds: dict[str, float], losses: dict[str, float], model_sha256: str,
                heldout: dict[str, Any] | None) -> dict[str, Any]:
    """The card's content (JSON-ready)."""
    return {"train_pbr": str(train_pbr), "train_pbr_sha256": digest, "images": images,
            "heldout_images": heldout_images, "trained_on_images": images - heldout_images,
            "objects": objects, "preset": preset, "device": device, "machine": platform.machine(),
            "seconds": {k: round(v, 2) for k, v in seconds.items()},
            "train_seconds": round(training_seconds(seconds), 2),
            "final_loss": losses, "model_sha256": model_sha256, "heldout": heldout}


def _f(x: Any) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3f}"


def card_markdown(card: dict[str, Any]) -> str:
    """The human-readable card."""
    p = card["preset"]
    lines = ["# Learned estimator: model card", "",
             "A CenterNet-style detector and a GDR-Net-style coordinate network (robust PnP), trained from "
             "scratch on the dataset's own synthetic train_pbr; no pretrained weights.", "",
             f"- train_pbr: `{card['train_pbr']}`, {card['images']} images (sha256 `{card['train_pbr_sha256'][:16]}...`), "
             f"{card['trained_on_images']} trained on, {card['heldout_images']} held out (every "
             f"{p['heldout_every']}th)",
             f"- objects (obj_id): {', '.join(map(str, card['objects']))}",
             f"- preset `{p['name']}`: detector {p['detector_steps']} steps x {p['detector_batch']} images at "
             f"{p['work_width']} px wide; coordinate net {p['pose_steps']} steps x {p['pose_batch']} crops of "
             f"{_crop_sizes(p)} px; seed {p['seed']}; {p.get('precision', 'fp32')}",
             f"- trained on {card['device']} ({card['machine']}) in {card['train_seconds']:.0f} s "
             f"(detector {card['seconds'].get('detector', 0):.0f} s, coordinate net {card['seconds'].get('pose', 0):.0f} s)",
             f"- weights: `model.pt`, sha256 `{card['model_sha256']}`", ""]
    h = card.get("heldout")
    if h:
        where = (f"every image of `{h.get('source')}` (sha256 `{str(h.get('source_sha256'))[:16]}...`), a split "
                 "rendered apart that the model never trained on" if h.get("whole_split")
                 else "the train_pbr's held-out slice, never trained on")
        lines += [f"## Held-out train_pbr ({h['images']} images, {h['instances']} instances)", "",
                  f"Scored on {where}.", "",
                  "| obj_id | detection recall @ IoU 0.5 | AP @ IoU 0.5 | AR, true box | AR, true box + depth | "
                  "AR, detected box | AR, detected + depth |", "|---|---|---|---|---|---|---|"]
        for o in card["objects"]:
            k = str(o)
            per = h["pose_ar_per_object"]
            lines.append(f"| {o} | {_f(h['detection_recall_iou50'].get(k))} | {_f(h['detection_ap_iou50'].get(k))} | "
                         f"{_f(per['true_box_rgb'].get(k))} | {_f(per['true_box_depth'].get(k))} | "
                         f"{_f(per['detected_rgb'].get(k))} | {_f(per['detected_depth'].get(k))} |")
        ar = h["pose_ar"]
        lines += [f"| all | | | {_f(ar['true_box_rgb'])} | {_f(ar['true_box_depth'])} | {_f(ar['detected_rgb'])} | "
                  f"{_f(ar['detected_depth'])} |", "",
                  f"Recall counts detections scoring >= {h['detection_threshold']} (the detector looking at each image "
                  f"{' and '.join(map(str, h.get('detect_widths') or ['?']))} px wide); AR is BOP19's (VSD, MSSD, "
                  f"MSPD). Median time per pose estimate: {h['seconds_per_estimate'] * 1000:.1f} ms."]
        refused = {v: c for v, c in h.get("refusals", {}).items() if c}
        if refused:
            lines += ["", "Refused estimates: " + "; ".join(
                f"{v}: " + ", ".join(f"{n} {cause}" for cause, n in sorted(c.items())) for v, c in refused.items())]
    return "\n".join(lines) + "\n"


def _crop_sizes(preset: dict[str, Any]) -> str:
    """The coordinate net's crop size, or the range its crops follow their boxes in."""
    smallest = preset.get("crop_px_min", preset["crop_px"])
    return str(preset["crop_px"]) if smallest == preset["crop_px"] else f"{smallest}-{preset['crop_px']}"

"""The dataset's learned model in a release: pack ``WORKDIR/learned/model/`` (``brave6d dataset run``'s
learn step, :mod:`brave6d.dataset.learn`) as ``<name>_learned.zip`` when the work directory has one, and
verify that zip.

The zip holds ``learned/model.pt``, ``learned/card.json`` and ``learned/MODEL_CARD.md`` (unzipped
into ``<name>/`` it is a model folder the learned agents load). The manifest's ``learned_model``
entry records the zip, the model's and the card's SHA-256, the preset, the objects and the
train_pbr it was trained on (images, SHA-256). Build refuses a model whose card does not match it
(the card's ``model_sha256``, objects outside the library); verify checks the model against the
manifest and the card, the card's schema and its preset's bounds, and reads the model (tensors
only) to check its objects and preset are the card's and its weights load into their networks on the
CPU (:mod:`brave6d.dataset.release.learned_checks`). Every error names the file.
"""

from __future__ import annotations

import hashlib
import tempfile
from pathlib import Path
from typing import Any

from brave6d.core.atomic import file_sha256
from brave6d.core.errors import DataError
from brave6d.dataset.release.learned_checks import check_card, check_weights
from brave6d.dataset.release.source import ReleaseError
from brave6d.dataset.release.zips import open_zip

#: The folder inside the zip, and its files.
LEARNED = "learned"
MODEL, CARD_JSON, CARD_MD = "model.pt", "card.json", "MODEL_CARD.md"
MEMBERS = (MODEL, CARD_JSON, CARD_MD)


def learned_zip(name: str) -> str:
    """``<name>_learned.zip``: ``learned/`` (the dataset's learned model and its card)."""
    return f"{name}_learned.zip"


def learned_model(workdir: Path) -> Path | None:
    """``WORKDIR/learned/model`` when it holds a ``model.pt``, else None."""
    from brave6d.dataset.learn import learned_model_dir

    folder = learned_model_dir(Path(workdir))
    return folder if (folder / MODEL).is_file() else None


def _read_card(path: Path, shown: str) -> dict[str, Any]:
    from brave6d.evaluation.learned import read_card

    try:
        card = read_card(path.parent)
    except DataError as exc:
        raise ReleaseError(str(exc).replace(str(path), shown)) from None
    if not isinstance(card.get("model_sha256"), str) or not isinstance(card.get("objects"), list):
        raise ReleaseError(f"{shown}: fields 'model_sha256' and 'objects' are required")
    check_card(card, shown)  # every field's type and range, the preset's bounds
    return card


def learned_entry(folder: Path, library: set[int], zip_name: str) -> tuple[list[tuple[Path, str]], dict[str, Any]]:
    """``(file, member)`` of the model folder's files and the manifest's ``learned_model`` entry, after
    checking that the card matches the model and names only library objects."""
    for name in MEMBERS:
        if not (folder / name).is_file():
            raise ReleaseError(f"{folder / name}: missing beside {folder / MODEL}; run 'brave6d dataset run' again "
                               "(it writes the card)")
    card = _read_card(folder / CARD_JSON, str(folder / CARD_JSON))
    digest = file_sha256(folder / MODEL)
    if card["model_sha256"] != digest:
        raise ReleaseError(f"{folder / MODEL}: sha256 {digest[:12]}... differs from its card's model_sha256 "
                           f"({card['model_sha256'][:12]}..., {folder / CARD_JSON}): the model was altered or the "
                           "card is another model's; run 'brave6d dataset run' again")
    outside = sorted(set(card["objects"]) - library)
    if outside:
        raise ReleaseError(f"{folder / CARD_JSON}: objects {outside} are not in the dataset's object library")
    entry = {"zip": zip_name, "model_sha256": digest, "card_sha256": file_sha256(folder / CARD_JSON),
             "preset": card.get("preset", {}).get("name"), "objects": card["objects"],
             "train_pbr_images": card.get("images"), "train_pbr_sha256": card.get("train_pbr_sha256")}
    return [(folder / name, f"{LEARNED}/{name}") for name in MEMBERS], entry


def check_learned_zip(path: Path, entry: Any, library: set[int], manifest_name: str) -> str:
    """Verify a release's ``<name>_learned.zip`` against the manifest's ``learned_model`` ``entry``
    and the card inside; returns the model's preset name."""
    from brave6d.evaluation.learned import read_model

    if not isinstance(entry, dict) or not isinstance(entry.get("model_sha256"), str) \
            or not isinstance(entry.get("objects"), list):
        raise ReleaseError(f"{manifest_name}: field 'learned_model': 'model_sha256' and 'objects' are required")
    with open_zip(path, inside=LEARNED, shown=path.name) as zf, \
            tempfile.TemporaryDirectory(prefix="brave6d-verify-learned-") as tmp:
        wanted = {f"{LEARNED}/{n}" for n in MEMBERS}
        for member in sorted(set(zf.names) - wanted):
            raise ReleaseError(f"{path.name}: member {member}: not a file of a learned model folder ({', '.join(MEMBERS)})")
        for member in sorted(wanted - set(zf.names)):
            raise ReleaseError(f"{path.name}:{member}: missing")
        shown_model = f"{path.name}:{LEARNED}/{MODEL}"
        digest = hashlib.sha256()
        for piece in zf.chunks(f"{LEARNED}/{MODEL}"):
            digest.update(piece)
        if digest.hexdigest() != entry["model_sha256"]:
            raise ReleaseError(f"{shown_model}: sha256 {digest.hexdigest()[:12]}... does not match {manifest_name}'s "
                               f"learned_model.model_sha256 ({entry['model_sha256'][:12]}...); the model was altered")
        shown_card = f"{path.name}:{LEARNED}/{CARD_JSON}"
        card = zf.run_reader(lambda p: _read_card(p, shown_card), f"{LEARNED}/{CARD_JSON}", Path(tmp))
        if card["model_sha256"] != entry["model_sha256"]:
            raise ReleaseError(f"{shown_card}: model_sha256 {card['model_sha256'][:12]}... is not {LEARNED}/{MODEL}'s "
                               f"({entry['model_sha256'][:12]}...); the card is another model's")
        if sorted(card["objects"]) != sorted(entry["objects"]) or not set(card["objects"]) <= library:
            raise ReleaseError(f"{shown_card}: objects {card['objects']} differ from {manifest_name}'s learned_model "
                               f"({entry['objects']}) or lie outside the object library")
        zf.extract(Path(tmp), [f"{LEARNED}/{MODEL}"], strip=LEARNED)
        try:
            model = read_model(Path(tmp) / MODEL)
        except DataError as exc:
            raise ReleaseError(str(exc).replace(str(Path(tmp) / MODEL), shown_model)) from None
        if sorted(model.objects) != sorted(card["objects"]):
            raise ReleaseError(f"{shown_model}: holds objects {sorted(model.objects)}, its card says {card['objects']}")
        if model.preset != card["preset"]:
            raise ReleaseError(f"{shown_model}: its preset differs from its card's ({shown_card}, field 'preset')")
        check_weights(model, shown_model)  # the networks built on the CPU, the weights loaded into them
        zf.check_unread()
    return str(card.get("preset", {}).get("name"))

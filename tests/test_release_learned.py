"""A release ships the dataset's learned model (issue 43, item 6): ``<name>_learned.zip`` with the model,
its card and their checksums in the manifest; ``release verify`` rejects a model that was altered, a
card that is another model's and a missing zip, naming the file; build refuses a model its card
does not describe."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from learned_helpers import untrained_model
from test_release import NAME, _resum, _rewrite_zip, workdir  # noqa: F401 - test_release's two-scene dataset

from brave6d.core.atomic import file_sha256
from brave6d.dataset.release import ReleaseError, build_release, read_manifest, verify_release
from brave6d.evaluation.learned import get_learn_preset, write_card
from brave6d.evaluation.learned.card import card_fields
from brave6d.evaluation.learned.model_file import write_model

pytestmark = pytest.mark.slow  # test_release's fixture (~10 s) and a few builds
ZIP = f"{NAME}_learned.zip"


@pytest.fixture(scope="module")
def work(workdir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:  # noqa: F811
    """test_release's dataset with a model in WORKDIR/learned/model (library objects 1-3), as
    ``dataset run``'s learn step leaves it."""
    root = Path(shutil.copytree(workdir, tmp_path_factory.mktemp("learned") / "work"))
    model_dir = root / "learned" / "model"
    model_dir.mkdir(parents=True)
    preset = get_learn_preset("tiny")
    write_model(model_dir, untrained_model(preset, [1, 2, 3]))
    write_card(model_dir, card_fields(root / "learned" / "synth", "0" * 64, 10, 1, [1, 2, 3], preset.to_json(),
                                      "cpu", {"detector": 1.0, "pose": 1.0}, {}, file_sha256(model_dir / "model.pt"),
                                      None))
    return root


@pytest.fixture(scope="module")
def release(work: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("release") / "out"
    build_release(work, out)
    return out


def test_release_ships_the_model_with_its_card_and_checksum(release: Path, work: Path) -> None:
    entry = read_manifest(release / "manifest.json")["learned_model"]
    assert entry["zip"] == ZIP and entry["preset"] == "tiny" and entry["objects"] == [1, 2, 3]
    assert entry["model_sha256"] == file_sha256(work / "learned" / "model" / "model.pt")
    assert ZIP in (release / "SHA256SUMS").read_text() and ZIP in (release / "README.md").read_text()
    assert verify_release(release).learned_model == "tiny"


def test_verify_rejects_an_altered_model_naming_it(release: Path, tmp_path: Path) -> None:
    copy = Path(shutil.copytree(release, tmp_path / "copy"))
    with pytest.raises(ReleaseError, match=rf"{ZIP}: sha256 .* does not match SHA256SUMS"):
        (copy / ZIP).write_bytes((copy / ZIP).read_bytes()[:-10] + b"0123456789")
        verify_release(copy)
    shutil.copyfile(release / ZIP, copy / ZIP)  # re-packed with other weights and SHA256SUMS recomputed
    _rewrite_zip(copy / ZIP, replace={"learned/model.pt": (release / ZIP).read_bytes()[:64]})
    _resum(copy)
    with pytest.raises(ReleaseError, match=rf"{ZIP}:learned/model.pt: sha256 .* does not match manifest.json"):
        verify_release(copy)


def test_verify_rejects_another_models_card_and_a_missing_zip(release: Path, tmp_path: Path) -> None:
    copy = Path(shutil.copytree(release, tmp_path / "copy"))
    card = json.loads(_member(release / ZIP, "learned/card.json"))
    _rewrite_zip(copy / ZIP, replace={"learned/card.json": json.dumps({**card, "model_sha256": "f" * 64}).encode()})
    _resum(copy)
    with pytest.raises(ReleaseError, match=rf"{ZIP}:learned/card.json: model_sha256 ffffffffffff.* is not"):
        verify_release(copy)
    (copy / ZIP).unlink()
    _resum_without(copy, ZIP)
    with pytest.raises(ReleaseError, match=rf"{ZIP}: required by manifest.json \(learned_model\)"):
        verify_release(copy)


def test_build_refuses_a_model_its_card_does_not_describe(work: Path, tmp_path: Path) -> None:
    spoiled = Path(shutil.copytree(work, tmp_path / "work"))
    model = spoiled / "learned" / "model" / "model.pt"
    model.write_bytes(model.read_bytes() + b"\0")
    with pytest.raises(ReleaseError, match=rf"{model}: sha256 .* differs from its card's model_sha256"):
        build_release(spoiled, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def _member(path: Path, name: str) -> bytes:
    import zipfile

    with zipfile.ZipFile(path) as zf:
        return zf.read(name)


def _resum_without(root: Path, name: str) -> None:
    sums = root / "SHA256SUMS"
    sums.write_text("".join(line for line in sums.read_text().splitlines(keepends=True) if not line.endswith(f"  {name}\n")))


# ============================================================================= issue 65, class 5: the model past its weights
def _replant(release: Path, tmp_path: Path, preset_changes: dict | None = None, card_changes: dict | None = None,
             model_changes=None) -> Path:  # type: ignore[no-untyped-def]
    """A copy of ``release`` whose learned model and card are remade as a hostile author would: the
    model's preset and the card changed, the model re-signed in its card, the manifest and SHA256SUMS."""
    from dataclasses import replace

    from brave6d.evaluation.learned import read_model

    copy = Path(shutil.copytree(release, tmp_path / "copy"))
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "model.pt").write_bytes(_member(release / ZIP, "learned/model.pt"))
    model = read_model(folder)
    model = replace(model, preset={**model.preset, **(preset_changes or {})})
    if model_changes is not None:
        model = model_changes(model)
    write_model(folder, model)
    digest = file_sha256(folder / "model.pt")
    card = json.loads(_member(release / ZIP, "learned/card.json"))
    card = {**card, "model_sha256": digest, "preset": model.preset, **(card_changes or {})}
    _rewrite_zip(copy / ZIP, replace={"learned/model.pt": (folder / "model.pt").read_bytes(),
                                      "learned/card.json": json.dumps(card).encode()})
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["learned_model"]["model_sha256"] = digest
    (copy / "manifest.json").write_text(json.dumps(manifest))
    _resum(copy)
    return copy


def _refused(copy: Path, says: str) -> str:
    with pytest.raises(ReleaseError) as info:
        verify_release(copy)
    message = str(info.value)
    assert says in message and "\n" not in message, message
    return message


@pytest.mark.parametrize("changes, says", [
    ({"images": "10"}, "field 'images'"),
    ({"objects": [1, "2", 3]}, "field 'objects[1]'"),
    ({"seconds": {"pose": -1.0}}, "field 'seconds.pose'"),
    ({"heldout": {"images": 3}}, "field 'heldout."),
    ({"train_pbr_sha256": "x"}, "field 'train_pbr_sha256'"),
])
def test_verify_refuses_a_card_whose_fields_have_the_wrong_types(release: Path, tmp_path: Path, changes: dict,
                                                                 says: str) -> None:
    """The card's readers (the report, the text card, ``learn heldout``) took such a card to a traceback."""
    _refused(_replant(release, tmp_path, card_changes=changes), says)


@pytest.mark.parametrize("changes, says", [
    ({"work_width": 10**6}, "field 'preset.work_width': an integer in 64..4096"),
    ({"detector_width": 4096}, "field 'preset.detector_width'"),
    ({"crop_px": 65536}, "field 'preset.crop_px'"),
    ({"heldout_every": 0}, "field 'preset.heldout_every'"),
    ({"work_width": 320.0}, "field 'preset.work_width'"),
    ({"pose_lr": True}, "field 'preset.pose_lr'"),
    ({"crop_px": 40}, "multiples of 16"),
])
def test_verify_refuses_a_preset_out_of_its_bounds(release: Path, tmp_path: Path, changes: dict, says: str) -> None:
    """Presets that made ``learn heldout`` allocate 32 GB or 1.9 TB, or divide by zero."""
    _refused(_replant(release, tmp_path, preset_changes=changes), says)


def test_verify_loads_the_weights_into_their_networks(release: Path, tmp_path: Path) -> None:
    """Weights of another width fit no network of the preset: loading failed only when an agent started."""
    from dataclasses import replace

    from brave6d.evaluation.learned import get_learn_preset

    other = untrained_model(get_learn_preset("tiny").with_overrides(pose_width=16), [1, 2, 3])
    copy = _replant(release, tmp_path, model_changes=lambda m: replace(m, pose_state=other.pose_state))
    _refused(copy, "the weights do not fit the networks of its preset")


def test_verify_refuses_weights_holding_nan(release: Path, tmp_path: Path) -> None:
    import torch

    def spoil(model):  # type: ignore[no-untyped-def]
        state = dict(model.detector_state)
        key = next(k for k, t in state.items() if t.is_floating_point())
        state[key] = torch.full_like(state[key], float("nan"))
        from dataclasses import replace

        return replace(model, detector_state=state)

    _refused(_replant(release, tmp_path, model_changes=spoil), "holds NaN or inf")


def test_verify_refuses_a_card_whose_preset_is_not_the_models(release: Path, tmp_path: Path) -> None:
    card = json.loads(_member(release / ZIP, "learned/card.json"))
    copy = _replant(release, tmp_path, card_changes={"preset": {**card["preset"], "seed": 7}})
    _refused(copy, "its preset differs from its card's")

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

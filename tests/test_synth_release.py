"""A dataset work directory with a synthetic split (``brave6d synth WORKDIR/dataset.yaml WORKDIR/synth``):
``release build`` packs ``<name>_train_pbr.zip`` and ``release verify`` checks it."""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import pytest
from test_release import NAME, _make_scene, _resum, _rewrite_zip, _write_dataset

from brave6d.dataset.release import ReleaseError, build_release, verify_release
from brave6d.synth import SynthOptions, synthesize

pytestmark = pytest.mark.slow  # two exported, bundled scenes and a release (~15 s)


@pytest.fixture(scope="module")
def release(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("dataset")
    _make_scene(root / "scenes" / "scene_a", 4, depth=True, psnr=27.5)
    _make_scene(root / "scenes" / "scene_b", 3, depth=False, psnr=None)
    _write_dataset(root, ["cube_red", "cube_blue"])
    synthesize(root / "dataset.yaml", root / "synth", SynthOptions(images=3, width=64, height=48))
    out = tmp_path_factory.mktemp("release") / "out"
    build_release(root, out)
    return out


def test_the_release_packs_and_verifies_the_synthetic_split(release: Path) -> None:
    zip_path = release / f"{NAME}_train_pbr.zip"
    with zipfile.ZipFile(zip_path) as zf:
        names = set(zf.namelist())
    assert {"train_pbr/000000/scene_gt.json", "train_pbr/000000/rgb/000002.png",
            "train_pbr/000000/mask_visib/000000_000000.png"} <= names
    assert f"{NAME}_train_pbr.zip" in (release / "SHA256SUMS").read_text()
    assert f"{NAME}_train_pbr.zip" in (release / "README.md").read_text()
    assert verify_release(release).train_pbr_images == 3


def test_verify_names_a_missing_synthetic_mask(release: Path, tmp_path: Path) -> None:
    copy = Path(shutil.copytree(release, tmp_path / "copy"))
    _rewrite_zip(copy / f"{NAME}_train_pbr.zip", drop="train_pbr/000000/mask/000001_000000.png")
    _resum(copy)
    with pytest.raises(ReleaseError, match=r"train_pbr/000000/mask/000001_000000.png: missing"):
        verify_release(copy)


def test_a_zipped_scene_estimates_the_memory_of_its_unpacked_bundle(release: Path, tmp_path: Path) -> None:
    """The serving budget sees the same bytes whether a scene comes zipped (estimated from the zip's
    directory) or unpacked (from its manifest): the reference geometry counts in both."""
    from brave6d.dataset.release import release_scene_sources
    from brave6d.serve import REFERENCE, bundle_scene_source

    sources = release_scene_sources(release, tmp_path / "cache")
    assert any((s.locate() / REFERENCE).is_file() for s in sources)  # the case this test is about
    for source in sources:
        assert source.memory_bytes == bundle_scene_source(source.locate()).memory_bytes, source.name

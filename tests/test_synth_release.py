"""A dataset work directory with a synthetic split (``brave6d synth WORKDIR/dataset.yaml WORKDIR/synth``):
``release build`` packs ``<name>_train_pbr.zip`` and ``release verify`` checks it."""

from __future__ import annotations

import json
import shutil
import tempfile
import zipfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_release import NAME, _make_scene, _resum, _rewrite_zip, _write_dataset

from brave6d.dataset.release import ReleaseError, build_release, verify_release
from brave6d.synth import SynthOptions, synthesize

pytestmark = pytest.mark.slow  # two exported, bundled scenes and a release (~15 s)


#: The shipped train_pbr in BlenderProc's conventions (JPEG rgb/, depth_scale 0.1).
BLENDERPROC_SAMPLE = Path(__file__).resolve().parent.parent / "data" / "samples" / "blenderproc_train_pbr" / "train_pbr"


_WORKDIRS: dict[Path, Path] = {}


def _synth_workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two exported, bundled scenes and a synthetic split (brave6d's PNG + mm), made once per session."""
    if tmp_path_factory.getbasetemp() in _WORKDIRS:
        return _WORKDIRS[tmp_path_factory.getbasetemp()]
    root = tmp_path_factory.mktemp("dataset")
    _make_scene(root / "scenes" / "scene_a", 4, depth=True, psnr=27.5)
    _make_scene(root / "scenes" / "scene_b", 3, depth=False, psnr=None)
    _write_dataset(root, ["cube_red", "cube_blue"])
    synthesize(root / "dataset.yaml", root / "synth", SynthOptions(images=3, width=64, height=48))
    _WORKDIRS[tmp_path_factory.getbasetemp()] = root
    return root


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _synth_workdir(tmp_path_factory)


@pytest.fixture(scope="module")
def release(tmp_path_factory: pytest.TempPathFactory) -> Path:  # self-contained: test_release_hostile_zips imports it
    out = tmp_path_factory.mktemp("release") / "out"
    build_release(_synth_workdir(tmp_path_factory), out)
    return out


def _with_blenderproc_split(workdir: Path, into: Path) -> Path:
    """A copy of the work directory whose synthetic split is the shipped BlenderProc sample, its
    obj_ids 3 and 4 (the demo's, which this dataset lacks) relabelled 1 and 2 (the release checks
    that each obj_id has a model, not what the images show)."""
    root = Path(shutil.copytree(workdir, into, ignore=shutil.ignore_patterns("synth")))
    split = Path(shutil.copytree(BLENDERPROC_SAMPLE, root / "synth" / "train_pbr"))
    gt_file = split / "000000" / "scene_gt.json"
    gt = json.loads(gt_file.read_text())
    for instances in gt.values():
        for g in instances:
            g["obj_id"] = {3: 1, 4: 2}.get(g["obj_id"], g["obj_id"])
    gt_file.write_text(json.dumps(gt))
    return root


@pytest.fixture(scope="module")
def blenderproc_workdir(workdir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _with_blenderproc_split(workdir, tmp_path_factory.mktemp("bp") / "dataset")


def test_a_blenderproc_split_builds_and_verifies(blenderproc_workdir: Path, tmp_path: Path) -> None:
    """JPEG colour and depth in 0.1 mm (depth_scale 0.1), as read_bop_split reads them, are packed as
    they are and verify, every JPEG decoded."""
    out = tmp_path / "out"
    build_release(blenderproc_workdir, out)
    with zipfile.ZipFile(out / f"{NAME}_train_pbr.zip") as zf:
        names = set(zf.namelist())
        cameras = json.loads(zf.read("train_pbr/000000/scene_camera.json"))
        assert zf.read("train_pbr/000000/rgb/000004.jpg") == (BLENDERPROC_SAMPLE / "000000/rgb/000004.jpg").read_bytes()
    assert not any(n.startswith("train_pbr/000000/rgb/") and n.endswith(".png") for n in names)
    assert {c["depth_scale"] for c in cameras.values()} == {0.1}
    assert "train_pbr/000000/scene_gt_coco.json" in names  # BlenderProc's COCO masks travel with it
    assert verify_release(out).train_pbr_images == 20
    # a damaged JPEG (its end cut off, the zip's CRC recomputed) is found by verify's decoding
    copy = Path(shutil.copytree(out, tmp_path / "copy"))
    member = "train_pbr/000000/rgb/000007.jpg"
    with zipfile.ZipFile(copy / f"{NAME}_train_pbr.zip") as zf:
        data = zf.read(member)
    _rewrite_zip(copy / f"{NAME}_train_pbr.zip", replace={member: data[:len(data) // 2]})
    _resum(copy)
    with pytest.raises(ReleaseError, match=rf"{member}: JPEG cut short"):
        verify_release(copy)


def test_a_damaged_coco_file_is_refused_naming_it(blenderproc_workdir: Path, tmp_path: Path) -> None:
    """BlenderProc's scene_gt_coco.json is packed (the sample's: its RLE checked on build); one whose
    runs do not cover its image is named with the annotation and field."""
    root = _with_blenderproc_split(blenderproc_workdir, tmp_path / "coco")
    coco_file = root / "synth" / "train_pbr" / "000000" / "scene_gt_coco.json"
    coco = json.loads(coco_file.read_text())
    coco["annotations"][2]["segmentation"]["counts"][-1] += 1
    coco_file.write_text(json.dumps(coco))
    with pytest.raises(ReleaseError) as err:
        build_release(root, tmp_path / "out")
    assert str(err.value) == (f"{coco_file}: annotations[2] segmentation: the runs cover 64001 pixels, the mask "
                              "has 200 x 320 = 64000")
    assert not (tmp_path / "out").exists()


def test_a_gray_split_is_refused_in_one_line(blenderproc_workdir: Path, tmp_path: Path) -> None:
    root = _with_blenderproc_split(blenderproc_workdir, tmp_path / "gray")
    scene = root / "synth" / "train_pbr" / "000000"
    (scene / "rgb").rename(scene / "gray")
    with pytest.raises(ReleaseError) as err:
        build_release(root, tmp_path / "out")
    assert str(err.value) == (f"{scene / 'gray'}: grey images (gray/) are not packed: the synthetic split needs "
                              "colour images in rgb/ (.png or .jpg or .jpeg)")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("stray", ["notes.txt", "tmp"])
def test_build_refuses_what_is_not_a_scene_folder_in_the_split(workdir: Path, tmp_path: Path, stray: str) -> None:
    """A file or a non-six-digit folder beside train_pbr/000000 is named by build; it used to be packed
    (a file) and then refused by verify as lying outside train_pbr/XXXXXX/, or read as a scene (a folder)."""
    root = Path(shutil.copytree(workdir, tmp_path / "stray"))
    path = root / "synth" / "train_pbr" / stray
    if stray.endswith(".txt"):
        path.write_text("the user's notes")
    else:
        path.mkdir()
        (path / "x.png").write_bytes(b"")
    with pytest.raises(ReleaseError) as err:
        build_release(root, tmp_path / "out")
    assert str(err.value).startswith(f"{path}: not a scene folder (six digits) of the synthetic split")
    assert path.exists() and not (tmp_path / "out").exists()


def test_a_split_without_depth_scale_is_refused_naming_the_image(workdir: Path, tmp_path: Path) -> None:
    """brave6d's own PNG + mm split with one image's depth_scale gone: its depth's unit is unknown
    (packed as it was before: a user would read it as mm)."""
    root = Path(shutil.copytree(workdir, tmp_path / "noscale"))
    cam_file = root / "synth" / "train_pbr" / "000000" / "scene_camera.json"
    cameras = json.loads(cam_file.read_text())
    assert {c["depth_scale"] for c in cameras.values()} == {1.0}
    del cameras["2"]["depth_scale"]
    cam_file.write_text(json.dumps(cameras))
    with pytest.raises(ReleaseError, match=r"scene_camera.json: image 2: missing 'depth_scale'") as err:
        build_release(root, tmp_path / "out")
    assert "\n" not in str(err.value)


def test_verify_refuses_a_gray_split(release: Path, tmp_path: Path) -> None:
    copy = Path(shutil.copytree(release, tmp_path / "copy"))
    path = copy / f"{NAME}_train_pbr.zip"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(path.with_suffix(".tmp"), "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            info.filename = info.filename.replace("/rgb/", "/gray/")
            dst.writestr(info, data)
    path.with_suffix(".tmp").replace(path)
    _resum(copy)
    with pytest.raises(ReleaseError, match=rf"{NAME}_train_pbr.zip:train_pbr/000000/gray: grey images \(gray/\) "
                                           "are not packed"):
        verify_release(copy)


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


def _edited(data: bytes, edits: dict[int, int]) -> bytes:
    out = bytearray(data)
    for i, value in edits.items():
        out[i] = value
    return bytes(out)


def _jpeg_cases() -> st.SearchStrategy[bytes]:
    """A real JPEG of the sample cut anywhere, with bytes changed, or any bytes at all."""
    real = (BLENDERPROC_SAMPLE / "000000" / "rgb" / "000003.jpg").read_bytes()
    cut = st.integers(0, len(real)).map(lambda n: real[:n])
    flipped = st.lists(st.tuples(st.integers(0, len(real) - 1), st.integers(0, 255)), min_size=1, max_size=8).map(
        lambda edits: _edited(real, dict(edits)))
    # the SOF0 segment's height and width bytes (after the marker, length and precision): a huge size declared
    sof = real.index(b"\xff\xc0") + 5
    huge = st.integers(20000, 65535).map(lambda n: real[:sof] + n.to_bytes(2, "big") * 2 + real[sof + 4:])
    return st.one_of(cut, flipped, huge, st.binary(max_size=600))


@settings(max_examples=80, deadline=None)
@given(data=_jpeg_cases())
def test_any_jpeg_bytes_pass_both_checks_as_an_image_or_are_refused_in_one_line(data: bytes) -> None:
    """Build's header check and verify's decoding of an ``rgb/`` JPEG: a (width, height) within the
    pixel limit that both agree on, or a ReleaseError of one line naming the image; never another
    exception, never a decode of a huge declared size (refused from the header)."""
    from brave6d.core.png_check import MAX_PIXELS
    from brave6d.dataset.release.images import check_jpeg_file
    from brave6d.dataset.release.zips import open_zip

    with tempfile.TemporaryDirectory() as tmp:
        file = Path(tmp) / "rgb" / "000000.jpg"
        file.parent.mkdir()
        file.write_bytes(data)
        with zipfile.ZipFile(Path(tmp) / "x.zip", "w") as zf:
            zf.writestr("train_pbr/000000/rgb/000000.jpg", data)
        answers = []
        for check in (lambda: check_jpeg_file(file),
                      lambda: _decode_one(open_zip(Path(tmp) / "x.zip", inside="train_pbr", shown="x.zip"), tmp)):
            try:
                answers.append(check())
            except ReleaseError as exc:
                assert "\n" not in str(exc) and ("000000.jpg" in str(exc)), str(exc)
                answers.append(None)
        for size in answers:
            assert size is None or (0 < size[0] * size[1] <= MAX_PIXELS)
        if answers[1] is not None:  # what verify decodes, build's header check accepted, at the same size
            assert answers[0] == answers[1]
        if len(data) > 200 and data[:3] == b"\xff\xd8\xff" and answers[0] is not None and answers[0][0] >= 20000:
            raise AssertionError("a huge declared size passed the header check")


def _decode_one(zf: object, tmp: str) -> tuple[int, int] | None:
    from brave6d.dataset.release.images import decode_zip_jpegs

    with zf:  # type: ignore[attr-defined]
        count, size = decode_zip_jpegs(zf, "train_pbr/000000", Path(tmp))  # type: ignore[arg-type]
    assert count == 1
    return size

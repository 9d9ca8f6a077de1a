"""``brave6d synth`` resumes over damaged images (issue #32, item 10): an image whose record exists
but whose PNGs are truncated, replaced or missing, or whose record is malformed, is rendered again
(same bytes as a clean run); the PNG check finds every truncation."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_synth import _scene_yaml, _tree

from brave6d.synth import SynthOptions, synthesize
from brave6d.core.png_check import CHECKS, png_problem

ROOT = Path(__file__).resolve().parent.parent
IMAGES = 6


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("synth-damage")
    spec = _scene_yaml(folder, 64, 48)
    out = folder / "clean"
    synthesize(spec, out, SynthOptions(images=IMAGES, seed=0))
    return spec, out


def _inodes(out: Path) -> dict[str, int]:
    return {p.relative_to(out).as_posix(): p.stat().st_ino for p in (out / "train_pbr").rglob("*.png")}


def _rerendered(before: dict[str, int], after: dict[str, int]) -> set[int]:
    """Images whose PNGs were written again (an atomic write gives the file a new inode)."""
    return {int(Path(name).name[:6]) for name, ino in after.items() if before.get(name) != ino}


@pytest.mark.parametrize("check", CHECKS)
def test_resume_renders_again_exactly_the_damaged_images(clean: tuple[Path, Path], tmp_path: Path,
                                                         check: str) -> None:
    spec, first = clean
    out = tmp_path / "damaged"
    shutil.copytree(first, out)
    folder = out / "train_pbr" / "000000"
    rgb = folder / "rgb" / "000001.png"
    rgb.write_bytes(rgb.read_bytes()[:100])  # an RGB cut to 100 bytes
    masks = sorted((folder / "mask").glob("000003_*.png"))
    masks[-1].write_bytes(b"this is not a PNG file\n" * 8)  # a mask that is not a PNG
    (folder / "depth" / "000004.png").unlink()  # a depth image gone
    before = _inodes(out)
    result = synthesize(spec, out, SynthOptions(images=IMAGES, seed=0, resume_check=check))
    assert _tree(out) == _tree(first)
    assert _rerendered(before, _inodes(out)) == {1, 3, 4}
    assert (result.rendered, result.skipped, result.repaired) == (3, IMAGES - 3, 3)
    assert result.repair_reason is not None and "rgb/000001.png" in result.repair_reason
    again = synthesize(spec, out, SynthOptions(images=IMAGES, seed=0, resume_check=check))
    assert (again.rendered, again.repaired) == (0, 0)


def test_a_malformed_record_is_rendered_again_not_an_error(clean: tuple[Path, Path], tmp_path: Path) -> None:
    spec, first = clean
    out = tmp_path / "records"
    shutil.copytree(first, out)
    (out / "work" / "000002.json").write_text("{")  # not JSON
    (out / "work" / "000005.json").write_text('{"scene_camera": {}}\n')  # fields missing
    before = _inodes(out)
    result = synthesize(spec, out, SynthOptions(images=IMAGES, seed=0))
    assert _tree(out) == _tree(first)
    assert _rerendered(before, _inodes(out)) == {2, 5}
    assert result.repaired == 2 and result.repair_reason is not None and "000002.json" in result.repair_reason


def _png(kind: str, seed: int, width: int, height: int) -> bytes:
    rng = np.random.default_rng(seed)
    if kind == "rgb":
        img = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    elif kind == "depth":
        img = rng.integers(0, 65536, (height, width), dtype=np.uint16)
    else:
        img = (rng.random((height, width)) < 0.3).astype(np.uint8) * 255
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


kinds = st.sampled_from(["rgb", "depth", "mask"])
sizes = st.tuples(st.integers(8, 40), st.integers(8, 40))


@settings(max_examples=80)
@given(kinds, st.integers(0, 2 ** 32 - 1), sizes, st.data())
def test_every_truncation_of_a_valid_png_is_found_by_every_check(kind: str, seed: int, size: tuple[int, int],
                                                                 data: st.DataObject) -> None:
    blob = _png(kind, seed, *size)
    for check in CHECKS:
        assert png_problem(blob, kind, size, check) is None, check
    cut = data.draw(st.integers(0, len(blob) - 1))
    for check in CHECKS:
        problem = png_problem(blob[:cut], kind, size, check)
        assert problem is not None, (check, cut, len(blob))


@settings(max_examples=80)
@given(kinds, st.integers(0, 2 ** 32 - 1), sizes, st.data())
def test_a_changed_byte_is_found_by_the_crc_and_decode_checks(kind: str, seed: int, size: tuple[int, int],
                                                              data: st.DataObject) -> None:
    blob = bytearray(_png(kind, seed, *size))
    at = data.draw(st.integers(0, len(blob) - 1))
    blob[at] ^= data.draw(st.integers(1, 255))
    for check in ("crc", "decode"):
        assert png_problem(bytes(blob), kind, size, check) is not None, (check, at)


def test_a_valid_png_of_the_wrong_size_or_kind_is_refused() -> None:
    for check in CHECKS:
        assert "32x24" in (png_problem(_png("rgb", 0, 32, 24), "rgb", (64, 48), check) or "")
        assert "16-bit" in (png_problem(_png("mask", 0, 32, 24), "depth", (32, 24), check) or "")
        assert png_problem(_png("depth", 0, 32, 24), "rgb", (32, 24), check) is not None


@pytest.mark.slow  # a CLI process
def test_cli_says_how_many_images_were_rendered_again_and_why(clean: tuple[Path, Path], tmp_path: Path) -> None:
    spec, first = clean
    out = tmp_path / "cli"
    shutil.copytree(first, out)
    rgb = out / "train_pbr" / "000000" / "rgb" / "000002.png"
    rgb.write_bytes(rgb.read_bytes()[:100])
    run = subprocess.run([sys.executable, "-m", "brave6d.cli", "synth", str(spec), str(out), "--images", str(IMAGES)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "(1 rendered, 5 already complete)" in run.stdout
    assert f"1 image(s) written before were damaged and rendered again; first: {rgb}: truncated" in run.stdout
    assert _tree(out) == _tree(first)


@pytest.mark.slow
def test_the_resume_check_flag_chooses_the_level(clean: tuple[Path, Path], tmp_path: Path) -> None:
    """``brave6d synth --resume-check``: a byte changed inside an RGB image (same length) passes the
    ``header`` level and is kept; the default ``crc`` finds it and renders the image again."""
    spec, first = clean
    out = tmp_path / "flipped"
    shutil.copytree(first, out)
    rgb = out / "train_pbr" / "000000" / "rgb" / "000002.png"
    data = bytearray(rgb.read_bytes())
    data[len(data) // 2] ^= 0x01
    rgb.write_bytes(bytes(data))
    cmd = [sys.executable, "-m", "brave6d.cli", "synth", str(spec), str(out), "--images", str(IMAGES)]
    kept = subprocess.run([*cmd, "--resume-check", "header"], capture_output=True, text=True, timeout=300)
    assert kept.returncode == 0, kept.stderr
    assert rgb.read_bytes() == bytes(data) and "damaged" not in kept.stdout
    redone = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert redone.returncode == 0, redone.stderr
    assert "1 image(s) written before were damaged" in redone.stdout and "rgb/000002.png" in redone.stdout
    assert _tree(out) == _tree(first)
    bad = subprocess.run([*cmd, "--resume-check", "md5"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--resume-check" in bad.stderr

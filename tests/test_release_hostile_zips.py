"""A downloaded release is untrusted input (issue #32): every zip member must resolve inside its
destination, size caps hold from the headers and while streaming, every image decodes, the serve
cache folder is checked at start and a tampered cache is unpacked again from the verified zip.

The fast tests craft small zips by hand; the slow ones alter a real release (two scenes and a
synthetic split, built once for the module) the way a hostile author or a careless lab would."""

from __future__ import annotations

import errno
import os
import json
import shutil
import stat
import struct
import tempfile
import warnings
import zipfile
import zlib
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_synth_release import release  # noqa: F401  (the module fixture: two scenes and a synthetic split)

from brave6d.core.atomic import write_png
from brave6d.dataset.release import ReleaseError, release_scene_sources, verify_release

NAME = "synthset"
GIB = 1 << 30
MIB = 1 << 20


# ----------------------------------------------------------------------------- crafting zips
def _zip(path: Path, members: list[tuple[zipfile.ZipInfo | str, bytes]], mode: str = "w") -> Path:
    """Write ``members`` as given: a ZipInfo's name is written byte for byte (even a NUL, which
    ZipInfo's constructor would cut off), duplicates included."""
    with warnings.catch_warnings(), zipfile.ZipFile(path, mode) as zf:
        warnings.simplefilter("ignore")  # "Duplicate name"
        for info, data in members:
            if isinstance(info, str):
                name, info = info, zipfile.ZipInfo(info)
                info.filename = name  # keep NUL and backslashes as they are
                info.external_attr = 0o644 << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data)
    return path


def _info(name: str, mode: int) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.filename = name
    info.external_attr = mode << 16
    return info


def _stream_zeros(path: Path, member: str, total: int, mode: str = "w", level: int = 1) -> Path:
    """A member of ``total`` zero bytes, streamed (never in memory): deflate level 1 packs 1 GiB
    into about 4.7 MB (ratio ~230:1), the issue's "6 MB zip holding 1 GiB"."""
    block = bytes(4 * MIB)
    with zipfile.ZipFile(path, mode, compression=zipfile.ZIP_DEFLATED, compresslevel=level) as zf:
        with zf.open(member, "w", force_zip64=total > 2 * GIB) as out:
            for _ in range(total // len(block)):
                out.write(block)
    return path


def _declare(path: Path, member: str, size: int, crc: int) -> None:
    """Make the headers of ``member`` lie: they declare ``size`` bytes with CRC ``crc`` (the
    deflated data stays what it was)."""
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        local = zf.getinfo(member).header_offset
    struct.pack_into("<I", data, local + 14, crc)
    struct.pack_into("<I", data, local + 22, size)
    at = data.find(b"PK\x01\x02")
    while at >= 0:
        n = struct.unpack_from("<H", data, at + 28)[0]
        if bytes(data[at + 46:at + 46 + n]) == member.encode():
            struct.pack_into("<I", data, at + 16, crc)
            struct.pack_into("<I", data, at + 24, size)
        at = data.find(b"PK\x01\x02", at + 4)
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def bomb(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A ~4.7 MB zip holding 1 GiB of zeros in one deflated member."""
    return _stream_zeros(tmp_path_factory.mktemp("bomb") / "bomb.zip", "bundles/000001/zeros.bin", GIB)


def _files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if not p.is_dir()] if folder.exists() else []


# ----------------------------------------------------------------------------- member names (item 1)
_PARTS = ["a", "b.png", "000001", "..", ".", "", "C:", "c:x", "a\\b", "\\", "\x00", "x\ny", "\x7f", " ", "é",
          "~", "\u202e", "n" * 256, "..."]
_NAMES = st.one_of(st.text(st.characters(blacklist_categories=("Cs",)), max_size=30),
                   st.lists(st.sampled_from(_PARTS), min_size=1, max_size=5).map("/".join),
                   st.lists(st.sampled_from(_PARTS), min_size=1, max_size=4).map(lambda p: "/" + "/".join(p)))


@given(name=_NAMES)
def test_member_name_validator(name: str) -> None:
    """Accepted names always resolve inside the destination (on POSIX and Windows); a rejected one
    is refused by the reader with an error naming the zip and the member."""
    from brave6d.dataset.release.zips import member_name_problem, open_zip

    problem = member_name_problem(name)
    if problem is None:
        dest = "/dest/folder"
        assert os.path.normpath(os.path.join(dest, name)).startswith(dest + "/"), name
        win = PureWindowsPath("C:/dest") / name
        assert not PureWindowsPath(name).anchor and ".." not in win.parts and "\\" not in name
        assert all(part not in ("", ".", "..") for part in PurePosixPath(name).parts) and name.isprintable()
        with tempfile.TemporaryDirectory() as tmp:  # and the unpacker writes it there
            dest = Path(tmp) / "dest"
            dest.mkdir()
            with open_zip(_zip(Path(tmp) / "ok.zip", [(name, b"" if name.endswith("/") else b"x")])) as zf:
                written = zf.extract(dest)
            assert written == ([] if name.endswith("/") else [dest / name])
            assert [p for p in Path(tmp).iterdir() if p != dest] == [Path(tmp) / "ok.zip"]  # nothing beside dest
        return
    with tempfile.TemporaryDirectory() as tmp:
        path = _zip(Path(tmp) / "names.zip", [(name, b"x")])
        with pytest.raises(ReleaseError) as info:
            open_zip(path)
        message = str(info.value)
        assert str(path) in message and "\n" not in message
        assert (name if name.isprintable() else repr(name)) in message


HOSTILE = {
    "absolute": [("/etc/evil", b"x")],
    "dotdot": [("bundles/000001/../../evil", b"x")],
    "empty part": [("bundles/000001//abs/evil", b"x")],
    "dot part": [("bundles/000001/./evil", b"x")],
    "drive letter": [("C:/evil", b"x")],
    "backslash": [("bundles\\000001\\evil", b"x")],
    "NUL": [("bundles/000001/evil\x00.png", b"x")],
    "control character": [("bundles/000001/ev\nil", b"x")],
    "symlink": [(_info("bundles/000001/link", stat.S_IFLNK | 0o777), b"/etc/passwd")],
    "device": [(_info("bundles/000001/dev", stat.S_IFCHR | 0o666), b"")],
    "duplicate": [("bundles/000001/a.json", b"1"), ("bundles/000001/a.json", b"2")],
    "duplicate ignoring case": [("bundles/000001/A.json", b"1"), ("bundles/000001/a.json", b"2")],
    "folder disguised as a file": [(_info("bundles/000001/dir", stat.S_IFDIR | 0o755), b"")],
    "file that is also a folder": [("bundles/000001/a", b"1"), ("bundles/000001/a/b", b"2")],
    "outside the zip's folder": [("bundles/000002/scene.json", b"{}")],
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_members_are_refused_before_anything_is_written(case: str, tmp_path: Path) -> None:
    from brave6d.dataset.release.zips import open_zip

    path = _zip(tmp_path / f"{case.replace(' ', '_')}.zip", HOSTILE[case])
    dest = tmp_path / "dest"
    dest.mkdir()
    with pytest.raises(ReleaseError) as info:
        with open_zip(path, inside="bundles/000001") as zf:
            zf.extract(dest, strip="bundles/000001")
    message = str(info.value)
    assert str(path) in message and "member" in message and "\n" not in message
    assert _files(dest) == [] and not Path("/etc/evil").exists()


def test_a_good_zip_extracts_inside_its_folder(tmp_path: Path) -> None:
    from brave6d.dataset.release.zips import open_zip, write_zip

    src = tmp_path / "a.json"
    src.write_text("{\"a\": 1}\n")
    path = write_zip(tmp_path / "ok.zip", [(src, "bundles/000001/models/a.json")], [("bundles/000001/b.txt", "hi")])
    dest = tmp_path / "dest"
    dest.mkdir()
    with open_zip(path, inside="bundles/000001") as zf:
        assert zf.names == ["bundles/000001/b.txt", "bundles/000001/models/a.json"]
        written = zf.extract(dest, strip="bundles/000001")
        assert zf.read("bundles/000001/b.txt") == b"hi"
    assert sorted(written) == [dest / "b.txt", dest / "models" / "a.json"]
    assert (dest / "models" / "a.json").read_text() == src.read_text()


# ----------------------------------------------------------------------------- size policy (item 4)
def test_a_zip_bomb_is_refused_from_the_headers(bomb: Path, tmp_path: Path) -> None:
    from brave6d.dataset.release.zips import DEFAULT_LIMITS, open_zip

    assert bomb.stat().st_size < 8 * MIB
    dest = tmp_path / "dest"
    dest.mkdir()
    with pytest.raises(ReleaseError) as info:
        with open_zip(bomb) as zf:
            zf.extract(dest)
    message = str(info.value)
    assert f"{bomb}: member bundles/000001/zeros.bin" in message
    assert "compression ratio" in message and f"{DEFAULT_LIMITS.max_ratio:g}" in message
    assert _files(dest) == []


def test_many_small_members_are_capped_by_the_whole_zips_ratio(tmp_path: Path) -> None:
    from brave6d.dataset.release.zips import open_zip

    path = tmp_path / "many.zip"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for i in range(200):  # each 1 MiB (no single member above the ratio floor): 200 MiB in ~200 kB
            zf.writestr(f"z/{i:04d}.bin", bytes(MIB))
    with pytest.raises(ReleaseError, match=rf"{path}: .*200 members .*compression ratio"):
        open_zip(path)


@pytest.mark.parametrize("field", ["max_member_bytes", "max_total_bytes", "max_members"])
def test_each_cap_names_itself(field: str, tmp_path: Path) -> None:
    from brave6d.dataset.release.zips import ZipLimits, open_zip

    path = _zip(tmp_path / "two.zip", [("d/a.bin", os.urandom(3000)), ("d/b.bin", os.urandom(3000))])
    limits = ZipLimits(**{field: {"max_member_bytes": 2000, "max_total_bytes": 4000, "max_members": 1}[field]})
    with pytest.raises(ReleaseError, match=rf"{path}: .*{field}"):
        open_zip(path, limits=limits)
    with open_zip(path) as zf:
        assert len(zf.names) == 2


def test_a_header_that_lies_about_the_size_is_stopped_while_streaming(tmp_path: Path) -> None:
    from brave6d.dataset.release.zips import open_zip

    path = tmp_path / "liar.zip"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("d/zeros.bin", bytes(64 * MIB))
    _declare(path, "d/zeros.bin", MIB, zlib.crc32(bytes(MIB)))  # says 1 MiB; holds 64 MiB
    dest = tmp_path / "dest"
    dest.mkdir()
    with open_zip(path) as zf:
        assert zf.size("d/zeros.bin") == MIB  # the headers pass: 1 MiB in 64 kB
        with pytest.raises(ReleaseError, match=rf"{path}: member d/zeros.bin: .*more than the 1048576 bytes"):
            zf.extract(dest)
        with pytest.raises(ReleaseError, match="more than the 1048576 bytes"):
            zf.read("d/zeros.bin")
    assert _files(dest) == []


def test_free_space_is_checked_before_extracting(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from brave6d.dataset.release.zips import open_zip

    path = _zip(tmp_path / "a.zip", [("d/a.bin", os.urandom(5000))])
    dest = tmp_path / "dest"
    dest.mkdir()
    real = shutil.disk_usage(dest)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real._replace(free=1000))
    with open_zip(path) as zf, pytest.raises(ReleaseError, match=rf"{dest}: .*1000 bytes free.*needs 5000 bytes"):
        zf.extract(dest)
    assert _files(dest) == []


def test_enospc_while_writing_names_the_folder_and_the_space(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from brave6d.dataset.release import zips

    path = _zip(tmp_path / "a.zip", [("d/a.bin", os.urandom(3000)), ("d/b.bin", os.urandom(5000))])
    dest = tmp_path / "dest"
    dest.mkdir()
    real_open = zips._open_output

    class Full:
        """A file on a disk that fills up after 4000 bytes (what ENOSPC looks like to a writer)."""

        written = 0

        def __init__(self, path: Path) -> None:
            self.file = real_open(path)

        def write(self, data: bytes) -> int:
            Full.written += len(data)
            if Full.written > 4000:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return self.file.write(data)

        def __enter__(self) -> Full:
            return self

        def __exit__(self, *exc: object) -> None:
            self.file.close()

    monkeypatch.setattr(zips, "_open_output", Full)
    with zips.open_zip(path) as zf, pytest.raises(ReleaseError) as info:
        zf.extract(dest)
    message = str(info.value)
    assert str(dest) in message and "no space left" in message and "8000 bytes" in message and "d/b.bin" in message
    assert _files(dest) == []  # what was written is removed


def test_overlapping_members_are_refused(tmp_path: Path) -> None:
    """A 'quoted overlap' bomb: two directory entries share one member's data."""
    from brave6d.dataset.release.zips import open_zip

    path = _zip(tmp_path / "o.zip", [("d/aa.bin", bytes(100_000))])
    data = bytearray(path.read_bytes())
    cd = data.find(b"PK\x01\x02")
    end = data.find(b"PK\x05\x06")
    entry = bytes(data[cd:end]).replace(b"d/aa.bin", b"d/bb.bin")
    eocd = bytearray(data[end:])
    struct.pack_into("<HHI", eocd, 8, 2, 2, 2 * len(entry))
    path.write_bytes(bytes(data[:end]) + entry + bytes(eocd))
    with zipfile.ZipFile(path) as zf:
        assert zf.namelist() == ["d/aa.bin", "d/bb.bin"]
    with pytest.raises(ReleaseError, match=rf"{path}: member d/bb.bin: .*overlaps"):
        open_zip(path)


# ----------------------------------------------------------------------------- PNG checks (item 10)
def _png(image: np.ndarray, tmp: Path) -> bytes:
    return write_png(tmp / "x.png", image).read_bytes()


def _noise(shape: tuple[int, ...], dtype: type = np.uint8) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 255, shape).astype(dtype)


GOOD = {"rgb": _noise((48, 64, 3)), "depth": _noise((48, 64), np.uint16) * 100, "mask": _noise((48, 64))}


@pytest.mark.parametrize("kind, image, damage, expect", [
    ("rgb", GOOD["rgb"], lambda b: b[:100], "truncated"),
    ("rgb", GOOD["rgb"], lambda b: b[:-2000] + b[-12:], "damaged|truncated"),
    ("mask", GOOD["mask"], lambda b: b"P5 64 48 255\n" + bytes(3072), "not a PNG"),
    ("depth", GOOD["mask"], lambda b: b, "16-bit"),
    ("mask", GOOD["rgb"], lambda b: b, "expected 8-bit grey"),
    ("rgb", GOOD["rgb"][:40], lambda b: b, "64x40, expected 64x48"),
])
def test_png_checks_name_the_problem(kind: str, image: np.ndarray, damage, expect: str,  # type: ignore[no-untyped-def]
                                     tmp_path: Path) -> None:
    from brave6d.dataset.release.images import decode_png

    assert decode_png(_png(GOOD[kind], tmp_path), kind, "z.zip:ok.png", (64, 48)) == (64, 48)
    with pytest.raises(ReleaseError, match=rf"z\.zip:bad\.png: .*{expect}"):
        decode_png(damage(_png(image, tmp_path)), kind, "z.zip:bad.png", (64, 48))


# ----------------------------------------------------------------------------- a real release, altered
@pytest.fixture()
def copy(release: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(release, tmp_path / "copy"))


def _resum(root: Path) -> None:
    from test_release import _resum as resum

    resum(root)


def _replace_member(zip_path: Path, member: str, data: bytes) -> None:
    from test_release import _rewrite_zip

    _rewrite_zip(zip_path, replace={member: data})


@pytest.mark.slow
def test_verify_passes_on_the_release(release: Path) -> None:
    report = verify_release(release)
    assert (report.scenes, report.images, report.train_pbr_images) == (2, 7, 3)


@pytest.mark.slow
def test_an_empty_part_member_neither_verifies_nor_writes_outside_the_cache(copy: Path, tmp_path: Path) -> None:
    evil = tmp_path / "outside" / "evil.txt"
    member = f"bundles/000001/{evil}"  # bundles/000001//tmp/.../evil.txt
    _zip(copy / f"{NAME}_bundle_000001.zip", [(member, b"pwned")], mode="a")
    _resum(copy)
    with pytest.raises(ReleaseError, match=rf"{NAME}_bundle_000001\.zip: member {member}: .*empty"):
        verify_release(copy)
    with pytest.raises(ReleaseError, match=rf"member {member}: .*empty"):
        for source in release_scene_sources(copy, tmp_path / "cache"):
            source.locate()
    assert not evil.exists() and not evil.parent.exists()


@pytest.mark.slow
def test_a_bomb_is_refused_by_verify_and_by_serve_with_nothing_written(copy: Path, tmp_path: Path) -> None:
    _stream_zeros(copy / f"{NAME}_bundle_000002.zip", "bundles/000002/models/zeros.ply", GIB, mode="a")
    _resum(copy)
    with pytest.raises(ReleaseError, match=rf"{NAME}_bundle_000002\.zip: member bundles/000002/models/zeros\.ply: "
                                           r".*compression ratio"):
        verify_release(copy)
    cache = tmp_path / "cache"
    with pytest.raises(ReleaseError, match=r"member bundles/000002/models/zeros\.ply: .*compression ratio"):
        for source in release_scene_sources(copy, cache):
            source.locate()
    assert not list(cache.rglob("*.ply"))


@pytest.mark.slow
def test_verify_catches_a_lying_header_in_the_test_zip(copy: Path) -> None:
    path = copy / f"{NAME}_test_all.zip"
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("test/000001/zeros.bin", bytes(16 * MIB))
    _declare(path, "test/000001/zeros.bin", 1000, zlib.crc32(bytes(1000)))
    _resum(copy)
    with pytest.raises(ReleaseError, match=r"test_all\.zip: member test/000001/zeros\.bin: .*more than the 1000 bytes"):
        verify_release(copy)


@pytest.mark.slow
def test_verify_refuses_a_bundle_member_its_manifest_does_not_list(copy: Path) -> None:
    _zip(copy / f"{NAME}_bundle_000001.zip", [("bundles/000001/extra.txt", b"not in the manifest")], mode="a")
    _resum(copy)
    with pytest.raises(ReleaseError, match=r"bundle_000001\.zip: member bundles/000001/extra\.txt: not listed in "
                                           r"the bundle's manifest\.json"):
        verify_release(copy)


@pytest.mark.slow
def test_verify_reads_a_bundle_manifest_through_serves_reader(copy: Path) -> None:
    """A malformed bundle ``manifest.json`` inside a release: one line naming the zip, the file and
    the field (``brave6d.serve.read_bundle_manifest``, the format's one reader), not a partial check of its own."""
    member = "bundles/000001/manifest.json"
    with zipfile.ZipFile(copy / f"{NAME}_bundle_000001.zip") as zf:
        manifest = json.loads(zf.read(member))
    manifest["files"]["splat.ply"]["bytes"] = "many"
    _replace_member(copy / f"{NAME}_bundle_000001.zip", member, json.dumps(manifest).encode())
    _resum(copy)
    with pytest.raises(ReleaseError, match=r"bundle_000001\.zip: the bundle does not load: .*bundle_000001\.zip:"
                                           r"bundles/000001/manifest\.json: field 'files\['splat\.ply'\]\.bytes'"):
        verify_release(copy)


@pytest.mark.slow
@pytest.mark.parametrize("zip_part, member, damage, expect", [
    ("test_all", "test/000001/rgb/000002.png", lambda b: b[:100], "truncated"),
    ("test_all", "test/000002/mask/000001_000000.png", lambda b: b"not a png at all" * 8, "not a PNG"),
    ("test_all", "test/000001/depth/000003.png", lambda b: None, "16-bit"),
    ("train_pbr", "train_pbr/000000/rgb/000001.png", lambda b: b[:len(b) // 2], "truncated"),
])
def test_verify_decodes_every_image(copy: Path, zip_part: str, member: str, damage, expect: str,  # type: ignore[no-untyped-def]
                                    tmp_path: Path) -> None:
    path = copy / f"{NAME}_{zip_part}.zip"
    with zipfile.ZipFile(path) as zf:
        data = damage(zf.read(member))
    if data is None:  # an 8-bit image where the depth must be 16-bit
        data = _png(np.full((240, 320), 7, np.uint8), tmp_path)
    _replace_member(path, member, data)
    _resum(copy)
    with pytest.raises(ReleaseError, match=rf"{NAME}_{zip_part}\.zip:{member}: .*{expect}"):
        verify_release(copy)


@pytest.mark.slow
def test_build_refuses_a_damaged_synthetic_image(release: Path, tmp_path: Path) -> None:
    from brave6d.dataset.release.train_pbr import train_pbr_files
    from brave6d.dataset.release.zips import open_zip

    with open_zip(release / f"{NAME}_train_pbr.zip") as zf:  # the synthetic split as `brave6d synth` wrote it
        zf.extract(tmp_path, strip=None)
    split = tmp_path / "train_pbr"
    assert len(train_pbr_files(split, {1: None, 2: None})) > 10
    victim = split / "000000" / "mask_visib" / "000001_000000.png"
    victim.write_bytes(victim.read_bytes()[:60])
    with pytest.raises(ReleaseError, match=rf"{victim}: .*truncated"):
        train_pbr_files(split, {1: None, 2: None})


# ----------------------------------------------------------------------------- the serve cache (items 7, 9)
@pytest.mark.slow
def test_a_cache_path_that_is_a_file_is_named_at_start(release: Path, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    cache.write_text("a file")
    with pytest.raises(ReleaseError, match=rf"{cache}: .*not a folder"):
        release_scene_sources(release, cache)
    made = tmp_path / "new" / "cache"
    assert len(release_scene_sources(release, made)) == 2 and made.is_dir()  # a missing folder is made


@pytest.mark.slow
def test_a_read_only_cache_is_named_at_start(release: Path, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    cache.mkdir()
    cache.chmod(0o555)
    try:
        if os.access(cache, os.W_OK):
            pytest.skip("running as root: chmod 0o555 does not stop root's writes (the next test simulates it)")
        with pytest.raises(ReleaseError, match=rf"{cache}: .*not writable"):
            release_scene_sources(release, cache)
    finally:
        cache.chmod(0o755)


@pytest.mark.slow
def test_an_unwritable_cache_is_named_at_start(release: Path, tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A read-only file system (EROFS) as every user sees it, root included."""
    cache = tmp_path / "cache"
    cache.mkdir()
    real = tempfile.mkstemp

    def mkstemp(*args: object, **kwargs: object) -> tuple[int, str]:
        if Path(str(kwargs.get("dir", ""))) == cache:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(cache))
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    with pytest.raises(ReleaseError, match=rf"{cache}: .*not writable.*[Rr]ead-only file system"):
        release_scene_sources(release, cache)


@pytest.mark.slow
def test_a_full_cache_is_named_at_start_with_the_bytes_needed(release: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    sizes = []
    for z in sorted(release.glob("*_bundle_*.zip")):
        with zipfile.ZipFile(z) as zf:
            sizes.append(sum(i.file_size for i in zf.infolist()))
    need = max(sizes)  # the largest bundle, unpacked
    cache = tmp_path / "cache"
    real = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real._replace(free=need - 1))
    with pytest.raises(ReleaseError, match=rf"{cache}: {need - 1} bytes free.*needs {need} bytes"):
        release_scene_sources(release, cache)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real._replace(free=need))
    sources = release_scene_sources(release, cache)
    assert len(sources) == 2
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real._replace(free=10))  # the disk filled up since
    with pytest.raises(ReleaseError, match=r"/bundles/000001: 10 bytes free.*needs \d+ bytes"):
        sources[0].locate()
    assert not [p for p in cache.rglob("*") if p.is_file()]


@pytest.mark.slow
def test_refresh_unpacks_a_tampered_cache_again_from_the_verified_zip(release: Path, copy: Path,
                                                                      tmp_path: Path) -> None:
    from brave6d.serve import BundleError, load_bundle

    sources = release_scene_sources(release, tmp_path / "cache")
    folder = sources[0].locate()
    objects = folder / "objects.json"
    good = objects.read_bytes()
    objects.write_bytes(good + b" ")
    with pytest.raises(BundleError):
        load_bundle(folder)
    assert sources[0].locate() == folder  # the stamp alone says "unpacked": locate does not notice
    assert sources[0].refresh is not None
    assert sources[0].refresh() == folder
    assert objects.read_bytes() == good and load_bundle(folder).objects

    # refresh re-checks the zip against SHA256SUMS: an altered zip is refused, the folder is kept
    served = release_scene_sources(copy, tmp_path / "cache2")
    folder2 = served[0].locate()
    zip_path = copy / f"{NAME}_bundle_000001.zip"
    data = bytearray(zip_path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    zip_path.write_bytes(bytes(data))
    with pytest.raises(ReleaseError, match=rf"{zip_path.name}: sha256 .* does not match SHA256SUMS"):
        served[0].refresh()
    assert load_bundle(folder2).objects


@pytest.mark.slow
def test_the_bop_toolkit_check_unpacks_with_the_safe_unpacker(copy: Path, tmp_path: Path) -> None:
    import importlib.util

    from brave6d.core.errors import DataError

    script = Path(__file__).resolve().parent.parent / "scripts" / "check_release_with_bop_toolkit.py"
    spec = importlib.util.spec_from_file_location("check_release_with_bop_toolkit", script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    base = module.unpack_release(copy, tmp_path / "good")
    assert (base / "camera.json").is_file() and (base / "models" / "models_info.json").is_file()
    assert (base / "test" / "000001" / "rgb" / "000000.png").is_file()
    evil = tmp_path / "evil.txt"
    _zip(copy / f"{NAME}_test_all.zip", [(f"test/000001/../../../../{evil}", b"x")], mode="a")
    with pytest.raises(DataError, match=r"_test_all\.zip: member test/000001/\.\./"):
        module.unpack_release(copy, tmp_path / "bad")
    assert not evil.exists()


@pytest.mark.slow
def test_a_long_name_and_version_still_serve(copy: Path, tmp_path: Path) -> None:
    """Each of name and version is checked as a folder name (read_manifest); together they may make a
    cache folder longer than one name may be, and the release still serves."""
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["version"] = "1." + "9" * 97  # 99 characters: a valid folder name on its own
    (copy / "manifest.json").write_text(json.dumps(manifest))
    _resum(copy)
    sources = release_scene_sources(copy, tmp_path / "cache")
    assert sources[0].locate().is_dir()
    (cache,) = (tmp_path / "cache").iterdir()
    assert manifest["version"] in cache.name and len(cache.name) > 100


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["symlink", "fifo", "dot-dot"])
def test_a_checksum_list_naming_a_link_a_fifo_or_a_path_outside_is_refused(copy: Path, tmp_path: Path,
                                                                           kind: str) -> None:
    """Issue 65, class 3: SHA256SUMS names pass the one rule of paths inside a folder, and each is
    opened as a regular file without following a link (a FIFO made verify wait forever; a link could
    lead to /dev/zero or to a file outside the release)."""
    from brave6d.dataset.release.formats import read_sha256sums

    sums = copy / "SHA256SUMS"
    if kind == "dot-dot":
        sums.write_text(sums.read_text() + f"{'0' * 64}  ../outside.zip\n")
        with pytest.raises(ReleaseError, match=r"file name '\.\./outside\.zip' is outside the release"):
            read_sha256sums(sums)
        return
    target = copy / "extra.bin"
    if kind == "symlink":
        (tmp_path / "secret").write_bytes(b"secret")
        target.symlink_to(tmp_path / "secret")
    else:
        os.mkfifo(target)
    sums.write_text(sums.read_text() + f"{'0' * 64}  extra.bin\n")
    with pytest.raises(ReleaseError) as info:
        verify_release(copy)
    assert "extra.bin" in str(info.value) and ("symbolic link" in str(info.value) or "FIFO" in str(info.value)
                                               or "missing" in str(info.value)), str(info.value)

"""The project's one zip module: write zips reproducibly, and read or unpack a zip that may be hostile.

Writing: every member gets the same fixed time stamp and the files are added in the order given,
so the same inputs give the same bytes (and the same ``SHA256SUMS``). PNG images are stored (they
are compressed already); everything else is deflated. A progress bar with ETA counts the bytes.

Reading: a downloaded release is untrusted, so :func:`open_zip` checks the whole central directory
before any member is read:

* every member name passes :func:`member_name_problem` (a relative POSIX path whose parts are not
  empty, ``.`` or ``..``, without backslashes, drive letters or ``:``, control or other
  non-printable characters), lies inside the expected folder, and is listed once (also ignoring
  case and Unicode normalisation, as a case-insensitive disk would); a file is never also a folder;
* members are plain files or folders (no symbolic links, devices or a folder disguised as a file),
  unencrypted, stored or deflated, and their data do not overlap;
* the sizes the headers declare respect a :class:`ZipLimits` (bytes per member and in all, member
  count, compression ratio).

Members are then streamed by this module's own reader, which counts the bytes it inflates and
stops as soon as a member holds more than its header declares (a lying header), and checks the
length and CRC at the end. :meth:`CheckedZip.extract` also checks each output path against the
resolved destination, the destination's free space before writing, never follows or replaces an
existing file, and removes what it wrote when it fails (ENOSPC included, named with the space
needed). Every error is a one-line :class:`ReleaseError` naming the zip and the member.
"""

from __future__ import annotations

import errno
import os
import shutil
import stat
import struct
import unicodedata
import zipfile
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path, PurePosixPath
from typing import BinaryIO, TypeVar

from brave6d.core.errors import DataError
from brave6d.core.names import relative_path_problem
from brave6d.core.progress import progress_bar
from brave6d.dataset.release.source import ReleaseError

_STAMP = (1980, 1, 1, 0, 0, 0)
_CHUNK = 1 << 20
_STORED = (".png", ".zip", ".jpg", ".jpeg")
_MIB, _GIB, _TIB = 1 << 20, 1 << 30, 1 << 40
T = TypeVar("T")


def write_zip(path: Path, files: Sequence[tuple[Path, str]], texts: Sequence[tuple[str, str]] = (),
              desc: str = "") -> Path:
    """Write ``path`` from ``files`` (``(source file, member name)``) and ``texts`` (``(member name, text)``)."""
    total = sum(src.stat().st_size for src, _ in files)
    bar = progress_bar(total, desc=desc or path.name, unit="B")
    bar.unit_scale = True
    try:
        with zipfile.ZipFile(path, "w", allowZip64=True) as zf:
            for name, text in texts:
                zf.writestr(_info(name), text.encode("utf-8"))
            for src, name in files:
                info = _info(name)
                with _open_no_link(src) as source:
                    info.file_size = os.fstat(source.fileno()).st_size  # lets zipfile choose ZIP64 over 2 GiB
                    with zf.open(info, "w") as dest:
                        shutil.copyfileobj(source, dest, _CHUNK)
                bar.update(info.file_size)
    finally:
        bar.close()
    return path


def _open_no_link(src: Path) -> BinaryIO:
    """``src`` opened for reading, never through a symbolic link (``O_NOFOLLOW``): what the
    caller checked is what is packed, even if the file is swapped for a link in between."""
    try:
        return open(src, "rb", opener=lambda path, flags: os.open(path, flags | os.O_NOFOLLOW))
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ReleaseError(f"{src}: is a symbolic link; a release packs only real files") from None
        raise ReleaseError(f"{src}: cannot read ({exc.strerror})") from None


def _info(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_STAMP)
    info.compress_type = zipfile.ZIP_STORED if name.lower().endswith(_STORED) else zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


# ----------------------------------------------------------------------------- the size policy
@dataclass(frozen=True)
class ZipLimits:
    """What a zip read by the project may hold; checked from the headers before anything is read
    or written, and again while streaming.

    The defaults fit a real release with room to spare: bundle zips of tens to hundreds of MB
    whose splat is at most a few GB (one member), test and ``train_pbr`` zips of many GB made of
    images of a few MB (stored: ratio 1) and JSON files. Deflate's ratios measured: real JSON 3-10:1,
    a ``scene_camera.json`` repeating one intrinsics 31-55:1, a degenerate ``scene_gt_info.json``
    (every instance invisible) 200:1, binary PLY 1.1-1.5:1 (a synthetic test splat 16:1), zeros
    230:1 at level 1 and 1030:1 at level 6 and above.
    """

    #: Uncompressed bytes of one member (a splat of a few GB fits four times over).
    max_member_bytes: int = 16 * _GIB
    #: Uncompressed bytes of all members together (test and train_pbr zips of many GB).
    max_total_bytes: int = _TIB
    #: Members in one zip (a BOP-sized train_pbr zip holds about a million).
    max_members: int = 5_000_000
    #: Uncompressed/compressed ratio of a member larger than ``ratio_floor_bytes``, and of the
    #: whole zip (its bytes against the zip file's size) when it holds more than that.
    max_ratio: float = 100.0
    #: Members up to this size are not held to ``max_ratio`` (at most 1 MiB each, however packed).
    ratio_floor_bytes: int = _MIB
    #: One member read into memory (a JSON file, an image to decode).
    max_read_bytes: int = 256 * _MIB

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 < value < float("inf"):
                raise ValueError(f"ZipLimits.{f.name}: a positive finite number is required, got {value!r}")


DEFAULT_LIMITS = ZipLimits()


# ----------------------------------------------------------------------------- member names
def member_name_problem(name: str) -> str | None:
    """Why the zip member ``name`` might land outside its destination folder, or None when it cannot
    (:func:`brave6d.core.names.relative_path_problem`; a folder member's one trailing ``/`` is allowed)."""
    return relative_path_problem(name, folder_slash=True)


def _shown(name: str) -> str:
    """A member name fit for a one-line message."""
    return name if name.isprintable() else repr(name)


def _key(name: str) -> str:
    """Names a case-insensitive, normalising file system would not tell apart."""
    return unicodedata.normalize("NFC", name.rstrip("/")).casefold()


# ----------------------------------------------------------------------------- reading
def open_zip(path: Path | str, *, inside: str | None = None, limits: ZipLimits = DEFAULT_LIMITS,
             shown: str | None = None) -> CheckedZip:
    """Open ``path`` after checking its central directory (module docstring); ``inside``: the one
    folder every member must lie in; ``shown``: how messages name the zip (default: its path)."""
    return CheckedZip(Path(path), inside, limits, shown or str(path))


class CheckedZip:
    """A zip whose directory passed every check; its members are read through a bounded stream."""

    def __init__(self, path: Path, inside: str | None, limits: ZipLimits, shown: str) -> None:
        self.path, self.limits, self.shown = path, limits, shown
        try:
            with zipfile.ZipFile(path) as zf:
                infos = zf.infolist()
            self._file: BinaryIO = open(path, "rb")
        except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
            raise ReleaseError(f"{shown}: not a readable zip ({exc})") from None
        try:
            self._infos = self._check_directory(infos, inside)
        except BaseException:
            self._file.close()
            raise
        #: The file members (folders left out), in the zip's order.
        self.names = [n for n, i in self._infos.items() if not i.is_dir()]
        self._read: set[str] = set()

    def __enter__(self) -> CheckedZip:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    def _error(self, name: str, problem: str) -> ReleaseError:
        return ReleaseError(f"{self.shown}: member {_shown(name)}: {problem}")

    def _check_directory(self, infos: list[zipfile.ZipInfo], inside: str | None) -> dict[str, zipfile.ZipInfo]:
        lim = self.limits
        if len(infos) > lim.max_members:
            raise ReleaseError(f"{self.shown}: {len(infos)} members, more than the cap of {lim.max_members} "
                               "(ZipLimits.max_members)")
        out: dict[str, zipfile.ZipInfo] = {}
        seen: dict[str, str] = {}
        total = 0
        for info in infos:
            name = info.orig_filename  # ZipInfo.filename is cut at a NUL: check what the zip says
            problem = member_name_problem(name)
            if problem is None and inside is not None and not _inside(name, inside.rstrip("/") + "/"):
                problem = f"lies outside {inside.rstrip('/')}/"
            if problem is None:
                problem = self._kind_problem(info)
            if problem is None and _key(name) in seen:
                problem = f"listed twice (as {_shown(seen[_key(name)])} too)"
            if problem is None:
                problem = self._size_problem(info)
            if problem is not None:
                raise self._error(name, problem)
            seen[_key(name)] = name
            out[name] = info
            total += info.file_size
        self._check_folders(out, seen)
        self._check_overlaps(out)
        if total > lim.max_total_bytes:
            raise ReleaseError(f"{self.shown}: {len(out)} members hold {total} bytes, more than the cap of "
                               f"{lim.max_total_bytes} (ZipLimits.max_total_bytes)")
        packed = max(1, self.path.stat().st_size)
        if total > lim.ratio_floor_bytes and total > lim.max_ratio * packed:
            raise ReleaseError(f"{self.shown}: {len(out)} members hold {total} bytes in a {packed}-byte zip: "
                               f"compression ratio {total / packed:.0f}:1 is above the cap of {lim.max_ratio:g}:1 "
                               "(ZipLimits.max_ratio)")
        return out

    @staticmethod
    def _kind_problem(info: zipfile.ZipInfo) -> str | None:
        mode = info.external_attr >> 16
        kind = stat.S_IFMT(mode)
        if stat.S_ISLNK(mode):
            return "a symbolic link (a release holds plain files only)"
        if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
            return "a special file (device, pipe or socket; a release holds plain files only)"
        if not info.is_dir() and (stat.S_ISDIR(mode) or info.external_attr & 0x10):
            return "a folder disguised as a file (its name has no trailing '/')"
        if info.is_dir() and info.file_size:
            return "a folder that holds data"
        if info.flag_bits & 0x1:
            return "encrypted"
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            return f"compression method {info.compress_type} (only stored and deflated are read)"
        if info.compress_type == zipfile.ZIP_STORED and info.compress_size != info.file_size:
            return f"stored, yet {info.compress_size} bytes hold {info.file_size}"
        return None

    def _size_problem(self, info: zipfile.ZipInfo) -> str | None:
        lim, size = self.limits, info.file_size
        if size > lim.max_member_bytes:
            return f"{size} bytes, more than the cap of {lim.max_member_bytes} (ZipLimits.max_member_bytes)"
        if size > lim.ratio_floor_bytes and size > lim.max_ratio * max(1, info.compress_size):
            return (f"{size} bytes packed into {info.compress_size}: compression ratio "
                    f"{size / max(1, info.compress_size):.0f}:1 is above the cap of {lim.max_ratio:g}:1 "
                    "(ZipLimits.max_ratio)")
        return None

    def _check_folders(self, infos: dict[str, zipfile.ZipInfo], seen: dict[str, str]) -> None:
        """No file member is also the folder of another member (``a`` and ``a/b``)."""
        for name in infos:
            parts = name.rstrip("/").split("/")
            for i in range(1, len(parts)):
                parent = seen.get(_key("/".join(parts[:i])))
                if parent is not None and not infos[parent].is_dir():
                    raise self._error(name, f"lies under {_shown(parent)}, which is a file")

    def _check_overlaps(self, infos: dict[str, zipfile.ZipInfo]) -> None:
        """Members' data never overlap (the 'overlapping files' zip bomb reuses one member's data)."""
        spans = sorted((i.header_offset, name) for name, i in infos.items())
        end, last = 0, ""
        for offset, name in spans:
            if offset < end:
                raise self._error(name, f"its data overlaps member {_shown(last)}'s")
            info = infos[name]
            end, last = offset + 30 + len(_raw_name(info)) + info.compress_size, name

    # ------------------------------------------------------------------------- streaming
    def size(self, name: str) -> int:
        """The uncompressed size the headers declare."""
        return self._get(name).file_size

    def _get(self, name: str) -> zipfile.ZipInfo:
        info = self._infos.get(name)
        if info is None or info.is_dir():
            raise ReleaseError(f"{self.shown}:{_shown(name)}: missing")
        return info

    def chunks(self, name: str) -> Iterator[bytes]:
        """The member's bytes, streamed: stops as soon as it holds more than its header declares,
        and checks its length and CRC at the end."""
        info = self._get(name)
        declared = info.file_size
        data_at = self._data_offset(info)
        inflate = zlib.decompressobj(-15) if info.compress_type == zipfile.ZIP_DEFLATED else None
        left, out, crc = info.compress_size, 0, 0
        try:
            while left or (inflate is not None and not inflate.eof):
                self._file.seek(data_at + info.compress_size - left)
                raw = self._file.read(min(_CHUNK, left))
                if left and not raw:
                    raise self._error(name, "the zip ends inside this member's data (truncated)")
                left -= len(raw)
                for piece in _inflate(inflate, raw, done=not left):
                    out += len(piece)
                    if out > declared:
                        raise self._error(name, f"holds more than the {declared} bytes its header declares")
                    crc = zlib.crc32(piece, crc)
                    yield piece
                if not left and inflate is not None and not inflate.eof:
                    raise self._error(name, "its compressed data end early (truncated)")
        except zlib.error as exc:
            raise self._error(name, f"corrupt compressed data ({exc})") from None
        if inflate is not None and inflate.unused_data:
            raise self._error(name, "data follow the end of its compressed stream")
        if out != declared:
            raise self._error(name, f"holds {out} bytes, its header declares {declared}")
        if crc != info.CRC:
            raise self._error(name, "CRC check failed (the zip is corrupt)")
        self._read.add(name)

    def _data_offset(self, info: zipfile.ZipInfo) -> int:
        """Where the member's data start, after its local header (which must agree with the directory)."""
        self._file.seek(info.header_offset)
        head = self._file.read(30)
        if len(head) != 30 or head[:4] != b"PK\x03\x04":
            raise self._error(info.orig_filename, "no local header where the directory says")
        method, name_len, extra_len = struct.unpack("<8xH16xHH", head)
        if self._file.read(name_len) != _raw_name(info) or method != info.compress_type:
            raise self._error(info.orig_filename, "its local header names another file or method than the directory")
        return info.header_offset + 30 + name_len + extra_len

    def read(self, name: str, max_bytes: int | None = None) -> bytes:
        """A whole member in memory, refused above ``max_bytes`` (default ``limits.max_read_bytes``)."""
        cap = self.limits.max_read_bytes if max_bytes is None else max_bytes
        if self.size(name) > cap:
            raise self._error(name, f"{self.size(name)} bytes, more than the {cap} read into memory "
                                    "(ZipLimits.max_read_bytes)")
        return b"".join(self.chunks(name))

    def run_reader(self, reader: Callable[[Path], T], name: str, tmp: Path) -> T:
        """Run a file reader on a member: read into memory (bounded), written alone into the folder
        ``tmp`` and removed after; a :class:`DataError` it raises names ``zip:member``, not the file."""
        path = Path(tmp) / PurePosixPath(name).name
        path.write_bytes(self.read(name))
        try:
            return reader(path)
        except DataError as exc:
            raise ReleaseError(str(exc).replace(str(path), f"{self.shown}:{name}")) from None
        finally:
            path.unlink(missing_ok=True)

    def check_unread(self) -> int:
        """Stream every member not read whole yet (length and CRC); returns how many were read now."""
        todo = [n for n in self.names if n not in self._read]
        for name in todo:
            for _ in self.chunks(name):
                pass
        return len(todo)

    # ------------------------------------------------------------------------- extracting
    def extract(self, dest: Path | str, names: Sequence[str] | None = None, strip: str | None = None) -> list[Path]:
        """Write ``names`` (default: every member) into the existing folder ``dest``, without the
        leading folder ``strip``; returns the files written. On any failure what this call wrote
        is removed (module docstring)."""
        root = Path(dest)
        base = root.resolve()
        todo = [self._get(n) for n in (self.names if names is None else names)]
        needed = sum(i.file_size for i in todo)
        check_free_space(root, needed, f"unpacking {self.shown}")
        prefix = "" if strip is None else strip.rstrip("/") + "/"
        made: list[Path] = []
        try:
            for info in todo:
                name = info.orig_filename
                if not name.startswith(prefix):
                    raise self._error(name, f"lies outside {prefix}")
                out = root / name[len(prefix):]
                if not out.resolve().is_relative_to(base) or out.resolve() == base:
                    raise self._error(name, f"resolves outside {root}")
                made += _make_parents(out.parent, root)
                made.append(out)
                with _open_output(out) as handle:
                    for piece in self.chunks(name):
                        handle.write(piece)
        except OSError as exc:
            _remove(made)
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise ReleaseError(f"{root}: no space left on the device while unpacking {self.shown}: member "
                                   f"{_shown(name)}; it needs {needed} bytes ({needed / 1e6:.1f} MB) in all") from None
            raise ReleaseError(f"{root}: cannot unpack {self.shown}: member {_shown(name)}: "
                               f"{exc.strerror or exc}") from None
        except BaseException:
            _remove(made)
            raise
        return [p for p in made if p.is_file()]


def _inside(name: str, folder: str) -> bool:
    """``name`` lies in ``folder`` (ending in ``/``), or is the folder entry of it or of a parent."""
    return name.startswith(folder) or (name.endswith("/") and folder.startswith(name))


def _raw_name(info: zipfile.ZipInfo) -> bytes:
    """The member name's bytes as the zip stores them."""
    return info.orig_filename.encode("utf-8" if info.flag_bits & 0x800 else "cp437", "surrogateescape")


def _inflate(inflate: zlib._Decompress | None, raw: bytes, done: bool) -> Iterator[bytes]:
    """Pieces of at most ``_CHUNK`` bytes from ``raw`` (stored: ``raw`` itself); never inflates
    more than one piece at a time, so a bomb is caught after ``_CHUNK`` bytes too many."""
    if inflate is None:
        yield raw
        return
    data = raw
    while data or done:
        piece = inflate.decompress(data, _CHUNK)
        data = inflate.unconsumed_tail
        if piece:
            yield piece
        elif not data:
            return
        if inflate.eof:
            return


def _make_parents(folder: Path, root: Path) -> list[Path]:
    """Make ``folder`` (inside ``root``); returns the folders made, outermost first."""
    missing = []
    while folder != root and not folder.is_dir():
        missing.append(folder)
        folder = folder.parent
    for f in reversed(missing):
        f.mkdir()
    return list(reversed(missing))


def _open_output(path: Path) -> BinaryIO:
    """A new file for writing: never an existing file, never through a symbolic link."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0),
                 0o644)
    return os.fdopen(fd, "wb")


def _remove(made: list[Path]) -> None:
    """Remove the files and (then empty) folders of a failed extraction, innermost first."""
    for p in reversed(made):
        try:
            if p.is_dir() and not p.is_symlink():
                p.rmdir()
            else:
                p.unlink()
        except OSError:
            pass


def check_free_space(folder: Path | str, needed: int, what: str) -> None:
    """Refuse (naming ``folder`` and the bytes) when ``folder``'s disk has less than ``needed`` bytes free."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError as exc:
        raise ReleaseError(f"{folder}: cannot read its free space ({exc.strerror or exc})") from None
    if free < needed:
        raise ReleaseError(f"{folder}: {free} bytes free ({free / 1e6:.1f} MB), {what} needs {needed} bytes "
                           f"({needed / 1e6:.1f} MB); free some space or choose another folder")


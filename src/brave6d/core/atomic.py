"""Atomic file writes: write a temporary file in the same folder, fsync, then rename.

A reader therefore sees either the old file or the complete new one, never a half-written
file, even when the process is killed mid-write.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import secrets
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO, TypeVar

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError
from brave6d.core.json_input import read_json_file
from brave6d.core.locks import FileLock, LockHeld, read_holder
from brave6d.core.png_check import check_image_header

log = logging.getLogger(__name__)

T = TypeVar("T")


def atomic_write(path: Path | str, write: Callable[[BinaryIO], None]) -> Path:
    """Call ``write(fileobj)`` on a temp file next to ``path`` and rename it over ``path``."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; a colleague must read what open() would let them
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
    except BaseException:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(target.parent)
    return target


def _umask() -> int:
    """The process's umask, read without changing it (``os.umask`` would, racing other threads)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def move_aside(path: Path | str, reason: str = "old") -> Path:
    """Rename ``path`` to a free ``<name>.<reason>-<YYYYmmdd-HHMMSS>[-N]`` beside it and return the new path.

    The one way any command gets user data out of its way: nothing is deleted, the rename stays on
    the same file system (instant, atomic), and two moves in the same second never collide.
    """
    source = Path(path)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    candidate = source.with_name(f"{source.name}.{reason}-{stamp}")
    n = 1
    while candidate.exists() or candidate.is_symlink():
        n += 1
        candidate = source.with_name(f"{source.name}.{reason}-{stamp}-{n}")
    os.rename(source, candidate)
    _fsync_dir(source.parent)
    return candidate


@contextmanager
def staged_folder(target: Path | str) -> Iterator[Path]:
    """Yield an empty staging folder beside ``target``; on normal exit it replaces ``target``.

    A whole folder or nothing: on an exception the staging folder is deleted and ``target`` is
    left as it was. Only use this for folders the program itself made (the previous ``target`` is
    deleted after the swap); user data is moved aside with :func:`move_aside` first.

    The staging folder ``.<name>.tmp-XXXXXXXX`` has an owner file ``.<name>.tmp-XXXXXXXX.owner``
    beside it (a :class:`brave6d.core.locks.FileLock`, made before the folder and removed after it), so
    that the next staging of ``target`` removes what a killed process left (:func:`clean_stagings`).
    """
    final = Path(target)
    final.parent.mkdir(parents=True, exist_ok=True)
    clean_stagings(final)
    staging, owner = _new_staging(final)
    try:
        try:
            yield staging
            replace_folder(staging, final)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    finally:
        owner.release()


#: A staging folder with no owner file (left by a version before owner files) is removed once it
#: is this old: no staging of this program takes a day.
ORPHAN_STAGING_S = 24 * 3600.0


def _staging_owner(staging: Path) -> Path:
    return staging.with_name(staging.name + ".owner")


def _new_staging(final: Path) -> tuple[Path, FileLock]:
    """A new staging folder beside ``final`` and the held lock that names its owner (made first)."""
    for _ in range(100):
        staging = final.with_name(f".{final.name}.tmp-{secrets.token_hex(4)}")
        owner = FileLock(_staging_owner(staging), f"staging of {final}", guarded=False)
        try:
            owner.acquire()
        except LockHeld:
            continue
        try:
            os.mkdir(staging, 0o777)  # the permissions os.mkdir gives (umask applies)
            return staging, owner
        except FileExistsError:
            owner.release()
        except BaseException:
            owner.release()
            raise
    raise DataError(f"{final.parent}: cannot make a staging folder for {final.name} (100 names taken)")


def clean_stagings(target: Path | str) -> list[Path]:
    """Remove the staging folders of ``target`` whose owner is gone; returns them.

    A staging folder whose owner still runs (on this machine: its pid; on another: its heartbeat,
    :mod:`brave6d.core.locks`) is kept. So is a staging folder without an owner file, unless it is older
    than :data:`ORPHAN_STAGING_S`. Each removal is logged with the owner and why it is gone.
    """
    final = Path(target)
    prefix = f".{final.name}.tmp-"
    removed = []
    try:
        siblings = list(final.parent.iterdir())
    except OSError:
        return removed
    for path in siblings:
        name = path.name
        if not name.startswith(prefix):
            continue
        if name.endswith(".owner"):
            holder = read_holder(path)
            why = holder.dead_because() if holder is not None else None
            if holder is None or why is None:
                continue  # released just now, or a staging still being written
            staging = path.with_name(name.removesuffix(".owner"))
            if staging.is_dir() and not staging.is_symlink():
                shutil.rmtree(staging, ignore_errors=True)
                log.warning("removed %s, the staging folder of %s, which is gone (%s)", staging, holder.describe(), why)
                removed.append(staging)
            path.unlink(missing_ok=True)
        elif path.is_dir() and not path.is_symlink() and not _staging_owner(path).exists():
            try:
                age_h = (time.time() - path.stat().st_mtime) / 3600
            except OSError:
                continue
            if age_h * 3600 > ORPHAN_STAGING_S:
                shutil.rmtree(path, ignore_errors=True)
                log.warning("removed %s, a staging folder %.0f h old without an owner file", path, age_h)
                removed.append(path)
    return removed


def replace_folder(staging: Path, final: Path) -> None:
    """Swap ``staging`` into place of ``final`` with two renames; the old ``final`` is deleted after.

    A crash between the renames leaves the old folder as a hidden ``.<name>.old-*`` sibling,
    never a missing one.
    """
    old: Path | None = None
    if final.exists() or final.is_symlink():
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.old-", dir=final.parent))
        os.rmdir(old)
        os.replace(final, old)
    try:
        os.replace(staging, final)
    except BaseException:
        if old is not None:
            os.replace(old, final)
        raise
    _fsync_dir(final.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def file_sha256(path: Path | str) -> str:
    """SHA-256 (hex) of a file's bytes, streamed; a missing or unreadable file raises :class:`DataError` naming it."""
    try:
        with open(path, "rb") as handle:
            return hashlib.file_digest(handle, "sha256").hexdigest()
    except FileNotFoundError:
        raise DataError(f"{path}: file not found") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None


def atomic_write_bytes(path: Path | str, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda handle: handle.write(data))


def atomic_write_text(path: Path | str, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: Path | str, data: Any, indent: int | None = 2) -> Path:
    """Write ``data`` as JSON atomically; NaN/inf are refused (they are not JSON)."""
    text = json.dumps(data, indent=indent, allow_nan=False, default=_json_default)
    return atomic_write_text(path, text + "\n")


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


def read_json(path: Path | str) -> Any:
    """Read a JSON file through the one JSON reader (:mod:`brave6d.core.json_input`: size, depth and
    number limits); a missing, corrupt or over-limit file raises :class:`DataError` naming it."""
    return read_json_file(path)


def read_json_as(path: Path | str, parse: Callable[[Any], T]) -> T:
    """Read a JSON file and build an object from it with ``parse``; a :class:`DataError` that
    ``parse`` raises (naming the field) is raised again with the file's path in front."""
    data = read_json(path)
    try:
        return parse(data)
    except DataError as exc:
        raise DataError(f"{path}: {exc}") from None


def write_png(path: Path | str, image: NDArray[Any]) -> Path:
    """Write an 8-bit RGB (H, W, 3), 8-bit grey or 16-bit grey (H, W) image as PNG, atomically."""
    return atomic_write_bytes(path, png_bytes(image, str(path)))


def png_bytes(image: NDArray[Any], where: str = "image") -> bytes:
    """The PNG file :func:`write_png` writes for ``image`` (errors name ``where``)."""
    import cv2

    arr = np.ascontiguousarray(image)
    if arr.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{where}: PNG images must be uint8 or uint16, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = arr[:, :, ::-1]  # RGB -> BGR for OpenCV
    elif arr.ndim != 2:
        raise DataError(f"{where}: expected (H, W) or (H, W, 3) image, got shape {arr.shape}")
    ok, buf = cv2.imencode(".png", arr)
    if not ok:
        raise DataError(f"{where}: PNG encoding failed")
    return buf.tobytes()


def read_png(path: Path | str, expect: str = "any", size: tuple[int, int] | None = None,
             size_of: str = "the camera") -> NDArray[Any]:
    """Read a PNG as RGB uint8 (H, W, 3) or grey uint8/uint16 (H, W); errors name the file.

    ``expect`` is ``"rgb"``, ``"depth"`` (uint16 grey), or ``"any"``. ``size`` (width, height),
    when given, must match the image; ``size_of`` says where that size comes from in the message
    (e.g. ``"the camera in calibration/intrinsics.json"``).
    """
    import cv2

    p = Path(path)
    if not p.is_file():
        raise DataError(f"{p}: image not found")
    check_image_header(p)  # the pixel limit, before anything is decoded
    try:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise DataError(f"{p}: cannot decode image (corrupt or not a PNG)")
    if img.ndim == 3:
        img = img[:, :, 2::-1] if img.shape[2] == 4 else img[:, :, ::-1]
        img = np.ascontiguousarray(img)
    if expect == "rgb" and (img.ndim != 3 or img.dtype != np.uint8):
        raise DataError(f"{p}: expected an 8-bit RGB image, got {img.dtype} with shape {img.shape}")
    if expect == "depth" and (img.ndim != 2 or img.dtype != np.uint16):
        raise DataError(f"{p}: expected a uint16 depth image in mm, got {img.dtype} with shape {img.shape}")
    if size is not None and img.shape[:2] != (size[1], size[0]):
        raise DataError(f"{p}: image is {img.shape[1]}x{img.shape[0]}, {size_of} is {size[0]}x{size[1]}")
    return img


def depth_m_to_mm_u16(depth_m: NDArray[np.floating]) -> NDArray[np.uint16]:
    """Metric depth (NaN/inf/<=0 = no data) -> uint16 millimetres (0 = no data, saturates at 65535)."""
    d = np.asarray(depth_m, dtype=np.float64)
    mm = np.where(np.isfinite(d) & (d > 0), np.rint(d * 1000.0), 0.0)
    return np.clip(mm, 0, 65535).astype(np.uint16)


def depth_mm_u16_to_m(depth_mm: NDArray[np.uint16]) -> NDArray[np.float32]:
    """uint16 millimetres -> float32 metres (0 stays 0 = no data)."""
    return np.asarray(depth_mm, dtype=np.float32) / 1000.0

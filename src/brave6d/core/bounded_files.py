"""Opening a file that came from elsewhere: a regular file only, read within a size bound.

A path from someone else's dataset, release or capture may name a FIFO (``open`` waits for a
writer forever), a device (``/dev/zero`` never ends, ``/dev/tty`` waits for a key) or a file far
larger than the reader expects. :func:`open_regular` opens without waiting (``O_NONBLOCK``) and
refuses anything but a regular file; :func:`read_regular` also refuses a file over ``max_bytes``
from its length, and reads at most that many bytes even if it grows meanwhile. Every refusal is
one line naming the file (``error``, :class:`UnreadableFile`, a
:class:`~brave6d.core.errors.DataError`, by default).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from brave6d.core.errors import DataError

_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder"))


class UnreadableFile(DataError):
    """A file that is not read: ``problem`` says why (``file not found``, ``a FIFO ...``)."""

    def __init__(self, name: str, problem: str) -> None:
        super().__init__(f"{name}: {problem}")
        self.problem = problem


def _refuse(error: Callable[[str], Exception] | None, name: str, problem: str) -> Exception:
    return UnreadableFile(name, problem) if error is None else error(f"{name}: {problem}")


def _kind(mode: int) -> str:
    return next((words for test, words in _KINDS if test(mode)), "not a regular file")


def open_regular(path: Path | str, shown: str | None = None,
                 error: Callable[[str], Exception] | None = None) -> BinaryIO:
    """``path`` opened for reading in binary once it is a regular file (links followed); else
    ``error`` (default :class:`UnreadableFile`) naming it (``shown``, default the path): missing,
    unreadable, a FIFO, a device, a folder. Never waits: a FIFO is opened non-blocking and refused."""
    name = str(path) if shown is None else shown
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise _refuse(error, name, "file not found") from None
    except IsADirectoryError:
        raise _refuse(error, name, "a folder, not a file") from None
    except OSError as exc:
        raise _refuse(error, name, f"cannot read ({exc.strerror or exc})") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise _refuse(error, name, f"{_kind(mode)}, not a regular file; only regular files are read")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: Path | str, max_bytes: int, shown: str | None = None, what: str = "",
                 error: Callable[[str], Exception] | None = None) -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_regular`), refused with ``error`` when
    it holds more than ``max_bytes`` (``what`` names the kind of file in that message)."""
    name = str(path) if shown is None else shown
    data = b""
    with open_regular(path, shown, error) as handle:
        try:
            size = os.fstat(handle.fileno()).st_size
            if size <= max_bytes:
                data = handle.read(max_bytes + 1)
        except OSError as exc:
            raise _refuse(error, name, f"cannot read ({exc.strerror or exc})") from None
    if size > max_bytes or len(data) > max_bytes:
        raise _refuse(error, name, f"{max(size, len(data))} bytes{f' of {what}' if what else ''} "
                                   f"(at most {max_bytes} are read)")
    return data

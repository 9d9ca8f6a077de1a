"""Write a whole folder or nothing: build it in a hidden sibling, then swap it into place.

The importer and the BOP writer produce many files that only make sense together. They are
written into ``.<name>.tmp-<random>/`` next to the target; :func:`commit_folder` then moves the
old folder aside, renames the new one into place and deletes the old one. A failure before the
commit removes the staging folder and leaves the previous result untouched.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def staged_folder(target: Path | str) -> Iterator[Path]:
    """Yield an empty staging folder beside ``target``; on normal exit it replaces ``target``.

    On an exception the staging folder is deleted and ``target`` is left as it was.
    """
    final = Path(target)
    final.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=final.parent))
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    commit_folder(staging, final)


def commit_folder(staging: Path, final: Path) -> None:
    """Replace ``final`` by ``staging`` (two renames; the old folder is deleted afterwards)."""
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
        shutil.rmtree(staging, ignore_errors=True)
        raise
    _fsync_dir(final.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def link_or_copy(src: Path, dst: Path) -> str:
    """Hard-link ``src`` to ``dst`` (no extra disk, survives moving the folder); copy when linking
    is impossible (another file system). Returns ``"link"`` or ``"copy"``."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
        return "link"
    except OSError:
        shutil.copy2(src, dst)
        return "copy"


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

"""Files in a staged annotation folder: hard links to the capture's images where possible.

The folder itself is written whole or not at all by :func:`brave6d.core.atomic.staged_folder`.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path


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


"""Write zip archives by streaming files into them (never a whole file in memory), reproducibly.

Every member gets the same fixed time stamp and the files are added in the order given, so the
same inputs give the same bytes (and the same ``SHA256SUMS``). PNG images are stored (they are
compressed already); everything else is deflated. A progress bar with ETA counts the bytes.
"""

from __future__ import annotations

import shutil
import zipfile
from collections.abc import Sequence
from pathlib import Path

from brave6d.progress import progress_bar

_STAMP = (1980, 1, 1, 0, 0, 0)
_CHUNK = 1 << 20
_STORED = (".png", ".zip", ".jpg", ".jpeg")


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
                info.file_size = src.stat().st_size  # lets zipfile choose ZIP64 for files over 2 GiB
                with open(src, "rb") as source, zf.open(info, "w") as dest:
                    shutil.copyfileobj(source, dest, _CHUNK)
                bar.update(info.file_size)
    finally:
        bar.close()
    return path


def _info(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_STAMP)
    info.compress_type = zipfile.ZIP_STORED if name.lower().endswith(_STORED) else zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


def member_outside(names: Sequence[str], folder: str) -> str | None:
    """The first member name that does not lie inside ``folder/`` (or climbs out with ``..``), else None."""
    return next((m for m in names if not m.startswith(folder + "/") or ".." in Path(m).parts), None)

"""Check the images of a release: every PNG is complete and is what its folder says it is.

BOP's folders say the kind: ``rgb/`` 8-bit colour (3 channels), ``depth/`` 16-bit grey,
``mask/`` and ``mask_visib/`` 8-bit grey. The checks are :mod:`brave6d.core.png_check`'s (the one
PNG checker), at two of its levels, errors naming the image:

* :func:`check_png_file`, level ``header`` (signature, ``IHDR``, kind, size, the final ``IEND``:
  45 bytes read): a truncated or foreign file is caught (``release build`` checks the synthetic
  split this way);
* :func:`decode_png`, level ``decode`` (``release verify``): every chunk's CRC and a full decode,
  so damage inside the image data is caught too. The header is checked first, so a PNG that
  declares a huge size is refused before any memory is allocated for it.
"""

from __future__ import annotations

from pathlib import Path

from brave6d.core.png_check import folder_kind, png_problem, png_size
from brave6d.dataset.release.source import ReleaseError
from brave6d.dataset.release.zips import CheckedZip

#: The kind of a ``.png`` member from its folder (``rgb``, ``depth``, ``mask``, ``any``), None for no PNG.
image_kind = folder_kind


def check_png_file(path: Path, kind: str, size: tuple[int, int] | None = None) -> tuple[int, int]:
    """Header and tail check of a PNG file; returns its (width, height)."""
    problem = png_problem(path, kind, size, "header")
    if problem is not None:
        raise ReleaseError(f"{path}: {problem}")
    with open(path, "rb") as handle:
        return png_size(handle.read(24))


def decode_png(data: bytes, kind: str, where: str, size: tuple[int, int] | None = None) -> tuple[int, int]:
    """Check and decode a PNG held in memory; ``where`` names it (``zip:member``); returns (width, height)."""
    problem = png_problem(data, kind, size, "decode")
    if problem is not None:
        raise ReleaseError(f"{where}: {problem}")
    return png_size(data)


def decode_zip_images(zf: CheckedZip, folder: str, size: tuple[int, int] | None = None) -> int:
    """Decode every PNG member under ``folder/`` (kind by its folder: :func:`image_kind`), all of
    size ``size`` or, when None, of the first one's size; returns how many."""
    count = 0
    for member in zf.names:
        kind = image_kind(member)
        if kind is not None and member.startswith(folder + "/"):
            size = decode_png(zf.read(member), kind, f"{zf.shown}:{member}", size)
            count += 1
    return count

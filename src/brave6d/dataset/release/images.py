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

A synthetic split's ``rgb/`` may hold JPEG instead (BlenderProc writes it), checked at the same two
levels: :func:`check_jpeg_file` (its header's size, within the pixel limit, and the start and end
markers) and :func:`decode_zip_jpegs` (annotation's reader of a split's colour images, which checks
the header's pixel limit before it decodes, and the markers).
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

from brave6d.core.png_check import check_image_header, folder_kind, png_problem, png_size
from brave6d.dataset.release.source import ReleaseError
from brave6d.dataset.release.zips import CheckedZip

#: The kind of a ``.png`` member from its folder (``rgb``, ``depth``, ``mask``, ``any``), None for no PNG.
image_kind = folder_kind
#: A JPEG starts with SOI (and the next marker's 0xFF) and ends with EOI.
_JPEG_START, _JPEG_END = b"\xff\xd8\xff", b"\xff\xd9"


def is_rgb_jpeg(relative: str) -> bool:
    """Is the POSIX path ``relative`` a JPEG colour image of a BOP folder (``rgb/XXXXXX.jpg`` or ``.jpeg``)?"""
    path = PurePosixPath(relative)
    return path.parent.name == "rgb" and path.suffix.lower() in (".jpg", ".jpeg")


def _jpeg_problem(head: bytes, tail: bytes) -> str | None:
    if not head.startswith(_JPEG_START):
        return "not a JPEG (no start-of-image marker)"
    if not tail.endswith(_JPEG_END):
        return "JPEG cut short or damaged (no end-of-image marker)"
    return None


def _size_problem(got: tuple[int, int], size: tuple[int, int] | None) -> str | None:
    if size is not None and tuple(got) != tuple(size):
        return f"image is {got[0]}x{got[1]}, the folder's other images are {size[0]}x{size[1]}"
    return None


def check_jpeg_file(path: Path, size: tuple[int, int] | None = None) -> tuple[int, int]:
    """Header and end check of a JPEG colour image (a few bytes read, nothing decoded); returns its
    (width, height), which must be ``size`` when given."""
    from brave6d.core.errors import DataError

    try:
        got = check_image_header(path)  # the pixel limit, from the header alone
    except DataError as exc:
        raise ReleaseError(str(exc)) from None
    with open(path, "rb") as handle:
        head = handle.read(len(_JPEG_START))
        handle.seek(max(0, path.stat().st_size - len(_JPEG_END)))
        tail = handle.read()
    problem = _jpeg_problem(head, tail) or _size_problem(got, size)
    if problem is not None:
        raise ReleaseError(f"{path}: {problem}")
    return got


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


def decode_zip_jpegs(zf: CheckedZip, folder: str, tmp: Path, size: tuple[int, int] | None = None
                     ) -> tuple[int, tuple[int, int] | None]:
    """Decode every JPEG colour image under ``folder/`` (:func:`is_rgb_jpeg`) with annotation's reader
    of a split's colour images (8-bit colour, the pixel limit checked from the header first), all of
    size ``size`` or, when None, of the first one's; returns (how many, their size or ``size``)."""
    from brave6d.annotation import read_split_rgb

    def decode(path: Path) -> tuple[int, int]:
        data = path.read_bytes()  # already in memory, bounded by the zip's limits (run_reader)
        problem = _jpeg_problem(data[:len(_JPEG_START)], data[-len(_JPEG_END):])
        if problem is None:
            height, width = read_split_rgb(path).shape[:2]
            return width, height
        raise ReleaseError(f"{path}: {problem}")

    count = 0
    for member in zf.names:
        if member.startswith(folder + "/") and is_rgb_jpeg(member):
            got = zf.run_reader(decode, member, tmp)
            problem = _size_problem(got, size)
            if problem is not None:
                raise ReleaseError(f"{zf.shown}:{member}: {problem}")
            size, count = got, count + 1
    return count, size

"""Check the images of a release: every PNG is complete and is what its folder says it is.

BOP's folders say the kind: ``rgb/`` 8-bit colour (3 channels), ``depth/`` 16-bit grey,
``mask/`` and ``mask_visib/`` 8-bit grey. Two levels of checking, both naming the image:

* :func:`png_problem` reads only the header and the tail (signature, the ``IHDR`` chunk and its
  CRC, kind, size, the final ``IEND`` chunk): a truncated or foreign file is caught for the price
  of 45 bytes (``release build`` checks the synthetic split this way);
* :func:`decode_png` decodes the bytes (``release verify``): damage inside the image data is
  caught too. The header is checked first, so a PNG that declares a huge size is refused before
  any memory is allocated for it.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path, PurePosixPath

import numpy as np

from dataset.release.source import ReleaseError
from dataset.release.zips import CheckedZip

SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
#: The kind of image each BOP folder holds.
FOLDER_KINDS = {"rgb": "rgb", "depth": "depth", "mask": "mask", "mask_visib": "mask"}
#: (bit depth, PNG colour types) per kind; 2 is RGB, 3 palette (decodes to RGB), 0 grey.
_HEADER = {"rgb": (8, (2, 3)), "depth": (16, (0,)), "mask": (8, (0,))}
_DECODED = {"rgb": (np.uint8, 3, "8-bit with 3 channels"), "depth": (np.uint16, 1, "16-bit with 1 channel"),
            "mask": (np.uint8, 1, "8-bit with 1 channel")}
#: Larger images are refused before decoding (8192 x 8192).
MAX_PIXELS = 1 << 26


def image_kind(member: str) -> str | None:
    """The kind of a ``.png`` member from its folder (``rgb``, ``depth``, ``mask``), ``"any"`` for a
    PNG elsewhere, None for a file that is no PNG."""
    path = PurePosixPath(member)
    if path.suffix.lower() != ".png":
        return None
    return FOLDER_KINDS.get(path.parent.name, "any")


def png_problem(head: bytes, tail: bytes, kind: str, size: tuple[int, int] | None = None) -> str | None:
    """What is wrong with a PNG whose first 33 bytes are ``head`` and last 12 ``tail``, or None.
    ``size``: the expected (width, height)."""
    if head[:8] != SIGNATURE:
        return "not a PNG (no PNG signature)"
    if len(head) < 33 or head[12:16] != b"IHDR" or struct.unpack(">I", head[8:12])[0] != 13 \
            or zlib.crc32(head[12:29]) != struct.unpack(">I", head[29:33])[0]:
        return "not a complete PNG (its IHDR header is damaged or cut)"
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    if tail != _IEND:
        return "not a complete PNG (it does not end with IEND: truncated)"
    if not 0 < width * height <= MAX_PIXELS:
        return f"declares {width}x{height} pixels (at most {MAX_PIXELS} are read)"
    if size is not None and (width, height) != tuple(size):
        return f"the image is {width}x{height}, expected {size[0]}x{size[1]}"
    if kind in _HEADER and (depth != _HEADER[kind][0] or colour not in _HEADER[kind][1]):
        return f"a PNG of bit depth {depth} and colour type {colour}; a {kind} image must be {_DECODED[kind][2]}"
    return None


def check_png_file(path: Path, kind: str, size: tuple[int, int] | None = None) -> tuple[int, int]:
    """Header and tail check of a PNG file (:func:`png_problem`); returns its (width, height)."""
    with open(path, "rb") as handle:
        head = handle.read(33)
        handle.seek(max(0, path.stat().st_size - 12))
        tail = handle.read(12)
    problem = png_problem(head, tail, kind, size)
    if problem is not None:
        raise ReleaseError(f"{path}: {problem}")
    return struct.unpack(">II", head[16:24])


def decode_png(data: bytes, kind: str, where: str, size: tuple[int, int] | None = None) -> tuple[int, int]:
    """Check and decode a PNG held in memory; ``where`` names it (``zip:member``); returns (width, height)."""
    import cv2

    problem = png_problem(data[:33], data[-12:], kind, size)
    if problem is not None:
        raise ReleaseError(f"{where}: {problem}")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ReleaseError(f"{where}: the PNG does not decode (its image data are damaged)")
    if kind in _DECODED:
        dtype, channels, text = _DECODED[kind]
        got = 1 if image.ndim == 2 else image.shape[2]
        if image.dtype != dtype or got != channels:
            raise ReleaseError(f"{where}: decodes to {image.dtype} with {got} channel(s); a {kind} image must be "
                               f"{text}")
    return image.shape[1], image.shape[0]


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

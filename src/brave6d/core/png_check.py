"""Is a PNG whole, and the image it should be? The one checker of PNG files for every stage
(``brave6d synth``'s resume, ``release build``'s synthetic split, ``release verify``).

Three checks of rising cost (``CHECKS``), each also requiring the expected kind (bit depth and
colour type of ``rgb``, ``depth`` or ``mask``; ``any`` for any PNG) and, when given, the size; an
image that declares more than ``MAX_PIXELS`` pixels is refused before anything is decoded:

- ``header``: the signature, the IHDR chunk (and its CRC) and the file ending in the IEND chunk;
  reads 45 bytes. Finds a file cut short anywhere, one that is not a PNG, a wrong size or kind.
  Misses bytes changed inside the file (same length): bit rot, a block overwritten.
- ``crc``: every chunk walked and its CRC-32 checked, image data present, IEND last and nothing
  after it; reads the whole file. Also finds any changed byte. Misses only a file rewritten with
  valid CRCs: another valid PNG of the same size and kind, or a forged one.
- ``decode``: ``crc``, then a full decode (OpenCV). Also finds compressed data that does not
  inflate to the image, which only a forged file (with recomputed CRCs) has.

Every image that enters from elsewhere, in any format, is first held to ``MAX_PIXELS`` from its
header alone (:func:`image_header_problem`, :func:`check_image_header`): ``read_png``, the
importers (Pillow), ``calibrate folder``, ``estimate frame``, the BOP results reader. A header that
claims 100000 x 100000 pixels is one line naming the file, never an allocation or an OpenCV /
Pillow exception.

Cost per 640x480 image (rgb, depth and ~4 objects' masks: 9 PNGs, 0.65 MiB; one thread, files in
the page cache; ``benchmarks/synth.py --check-images 300`` on a busy 2-core machine): ``header``
0.45 .. 0.6 ms, ``crc`` 1.2 .. 2.1 ms, ``decode`` 19 .. 38 ms; rendering the image takes ~500 ms.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

from brave6d.core.bounded_files import UnreadableFile, open_regular

CHECKS = ("header", "crc", "decode")
DEFAULT_CHECK = "crc"

SIGNATURE = b"\x89PNG\r\n\x1a\n"
IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # length 0, type, CRC-32 of b"IEND"
_HEAD = len(SIGNATURE) + 8 + 13 + 4  # signature, IHDR length and type, its 13 bytes, its CRC

#: kind -> (bit depth, PNG colour types, words for messages); a palette image decodes to RGB.
KINDS: dict[str, tuple[int | None, tuple[int, ...], str]] = {
    "rgb": (8, (2, 3), "8-bit RGB"), "depth": (16, (0,), "16-bit grey"), "mask": (8, (0,), "8-bit grey"),
    "any": (None, (), "a PNG")}
#: The kind of image each BOP folder holds (``rgb/``, ``depth/``, ``mask/``, ``mask_visib/``).
FOLDER_KINDS = {"rgb": "rgb", "depth": "depth", "mask": "mask", "mask_visib": "mask"}
#: Larger images are refused before they are decoded (8192 x 8192).
MAX_PIXELS = 1 << 26
_COLOUR_WORDS = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}


def image_header_problem(source: bytes | Path, max_pixels: int = MAX_PIXELS) -> str | None:
    """Why the image ``source`` (its bytes, or a file) must not be decoded: no image header that
    Pillow or this module reads, or more than ``max_pixels`` pixels declared; None when it may be.

    A PNG's IHDR is read here (its CRC checked); other formats' headers by Pillow, which reads the
    header only (``Image.open`` is lazy) and whose own decompression-bomb limit is never reached
    first (its error is no ``OSError``)."""
    try:
        if isinstance(source, Path):
            with open_regular(source) as handle:  # a FIFO or a device is refused, never waited on
                head = handle.read(_HEAD)
        else:
            head = bytes(source[:_HEAD])
    except UnreadableFile as exc:
        return "missing" if exc.problem == "file not found" else exc.problem
    except OSError as exc:
        return f"cannot read ({exc.strerror or exc})"
    if head.startswith(SIGNATURE):  # the IHDR alone (the file's end is the decoder's business)
        return _header_problem(head, IEND, _HEAD + len(IEND), "any", None, max_pixels)
    size = _pillow_size(source, max_pixels)
    if isinstance(size, str):
        return size
    return _pixels_problem(*size, max_pixels)


def check_image_header(path: Path | str, max_pixels: int = MAX_PIXELS) -> tuple[int, int]:
    """(width, height) of the image file ``path`` from its header (:func:`image_header_problem`);
    ``DataError`` naming the file when it must not be decoded."""
    from brave6d.core.errors import DataError

    p = Path(path)
    problem = image_header_problem(p, max_pixels)
    if problem is not None:
        raise DataError(f"{p}: {'image not found' if problem == 'missing' else problem}")
    with open_regular(p) as handle:
        head = handle.read(24)
    if head.startswith(SIGNATURE):
        return png_size(head)
    size = _pillow_size(p)
    assert not isinstance(size, str)
    return size


def _pillow_size(source: bytes | Path, max_pixels: int = MAX_PIXELS) -> tuple[int, int] | str:
    """(width, height) from Pillow's reading of the header, or why it cannot be read."""
    import io
    import warnings

    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(source if isinstance(source, Path) else io.BytesIO(source)) as im:
                return int(im.size[0]), int(im.size[1])
    except Image.DecompressionBombError as exc:
        return f"declares too many pixels (at most {max_pixels} are read): {exc}"
    except (OSError, ValueError, SyntaxError, EOFError, struct.error) as exc:  # UnidentifiedImageError: an OSError
        return f"not an image this program reads ({exc})"


def _pixels_problem(width: int, height: int, max_pixels: int) -> str | None:
    if not 0 < width * height <= max_pixels:
        return f"declares {width}x{height} pixels (at most {max_pixels} are read)"
    return None


def folder_kind(relative: str) -> str | None:
    """The kind of a ``.png`` file from its BOP folder (``rgb``, ``depth``, ``mask``), ``"any"`` for a
    PNG elsewhere, None for a file that is no PNG (``relative``: a POSIX path)."""
    parts = relative.rsplit("/", 2)
    if not parts[-1].lower().endswith(".png"):
        return None
    return FOLDER_KINDS.get(parts[-2] if len(parts) > 1 else "", "any")


def png_size(head: bytes) -> tuple[int, int]:
    """(width, height) from the first 24 bytes of a PNG that :func:`png_problem` accepted."""
    return struct.unpack(">II", head[16:24])


def png_problem(source: bytes | Path, kind: str, size: tuple[int, int] | None = None,
                check: str = DEFAULT_CHECK) -> str | None:
    """Why the PNG ``source`` (its bytes, or a file) is not a whole ``kind`` image of ``size``
    (width, height; None: any) by ``check`` (module docstring); None when it is."""
    if check not in CHECKS:
        raise ValueError(f"unknown PNG check {check!r}; one of {', '.join(CHECKS)}")
    if kind not in KINDS:
        raise ValueError(f"unknown image kind {kind!r}; one of {', '.join(KINDS)}")
    try:
        if isinstance(source, Path) and check == "header":
            head, tail, length = _ends(source)
        else:
            if isinstance(source, Path):
                with open_regular(source) as handle:
                    data = handle.read()
            else:
                data = bytes(source)
            head, tail, length = data[:_HEAD], data[-len(IEND):], len(data)
    except UnreadableFile as exc:
        return "missing" if exc.problem == "file not found" else exc.problem
    except OSError as exc:
        return f"cannot read ({exc.strerror or exc})"
    problem = _header_problem(head, tail, length, kind, size)
    if problem is None and check != "header":
        problem = _chunk_problem(data)
    if problem is None and check == "decode":
        problem = _decode_problem(data, kind, size)
    return problem


def _ends(path: Path) -> tuple[bytes, bytes, int]:
    """The first ``_HEAD`` bytes, the last ``len(IEND)`` bytes and the length of ``path``."""
    with open_regular(path) as handle:
        head = handle.read(_HEAD)
        length = handle.seek(0, 2)
        handle.seek(max(length - len(IEND), 0))
        return head, handle.read(), length


def _header_problem(head: bytes, tail: bytes, length: int, kind: str, size: tuple[int, int] | None,
                    max_pixels: int = MAX_PIXELS) -> str | None:
    if not head:
        return "empty file"
    if not SIGNATURE.startswith(head[:len(SIGNATURE)]):
        return "not a PNG (no PNG signature)"
    if len(head) < _HEAD:
        return f"truncated ({length} bytes, the header needs {_HEAD})"
    n, ctype = struct.unpack(">I4s", head[8:16])
    if ctype != b"IHDR" or n != 13:
        return "not a PNG (no IHDR chunk first)"
    if zlib.crc32(head[12:29]) != struct.unpack(">I", head[29:33])[0]:
        return "damaged (IHDR CRC mismatch)"
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", head[16:29])
    too_many = _pixels_problem(width, height, max_pixels)
    if too_many is not None:
        return too_many
    if size is not None and (width, height) != tuple(size):
        return f"image is {width}x{height}, expected {size[0]}x{size[1]}"
    want_depth, want_colours, words = KINDS[kind]
    if want_depth is not None and (depth != want_depth or colour not in want_colours):
        return f"image is {depth}-bit {_COLOUR_WORDS.get(colour, f'colour type {colour}')}, expected {words}"
    if compression != 0 or filtering != 0 or interlace not in (0, 1):
        return "not a PNG (unknown compression, filter or interlace method)"
    if length < _HEAD + len(IEND) or tail != IEND:
        return f"truncated ({length} bytes, no IEND chunk at the end)"
    return None


def _chunk_problem(data: bytes) -> str | None:
    """Walk the chunks after the signature: each CRC right, IDAT present, IEND last, at the end."""
    view = memoryview(data)
    pos, seen_idat = len(SIGNATURE), False
    while pos < len(data):
        if pos + 12 > len(data):
            return f"truncated (chunk at byte {pos} cut short)"
        n, ctype = struct.unpack(">I4s", view[pos:pos + 8])
        end = pos + 12 + n
        if end > len(data):
            return f"truncated (chunk {ctype!r} at byte {pos} runs past the end)"
        if zlib.crc32(view[pos + 4:end - 4]) != struct.unpack(">I", view[end - 4:end])[0]:
            return f"damaged (chunk {ctype!r} at byte {pos}: CRC mismatch)"
        seen_idat = seen_idat or ctype == b"IDAT"
        if ctype == b"IEND":
            if end != len(data):
                return f"damaged ({len(data) - end} bytes after the IEND chunk)"
            return None if seen_idat else "damaged (no image data)"
        pos = end
    return "truncated (no IEND chunk)"


def _decode_problem(data: bytes, kind: str, size: tuple[int, int] | None) -> str | None:
    import cv2
    import numpy as np

    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    if image is None:
        return "does not decode"
    if kind == "any":
        return None
    width, height = size if size is not None else png_size(data)
    shape = (height, width, 3) if kind == "rgb" else (height, width)
    dtype = np.uint16 if kind == "depth" else np.uint8
    if image.shape != shape or image.dtype != dtype:
        return f"decodes to {image.dtype} {image.shape}, expected {np.dtype(dtype)} {shape}"
    return None

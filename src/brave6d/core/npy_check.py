"""The one reader of NumPy ``.npy`` files that come from elsewhere (``calibrate folder``'s pose files).

``np.load`` allocates the array its header declares before it reads the data, so a 256-byte file
whose header says shape (100000000, 4, 4) asks for 11.9 GiB (``_ArrayMemoryError``, or a
half-filled array where memory is overcommitted). :func:`read_npy` reads the header first
(``numpy.lib.format``) and refuses, in one line naming the file, a header that is not NumPy's, an
array of Python objects, one larger than ``max_bytes``, or one whose declared size is not the
data the file holds; only then is the array read.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from brave6d.core.bounded_files import open_regular
from brave6d.core.errors import DataError

#: Largest array read by default (a pose file of a million 4x4 float64 poses is 128 MB).
MAX_NPY_BYTES = 256 * 2**20


def npy_header(path: Path | str, max_bytes: int = MAX_NPY_BYTES) -> tuple[tuple[int, ...], np.dtype[Any]]:
    """(shape, dtype) from the header of the ``.npy`` file ``path``, checked as the module says;
    :class:`DataError` naming the file otherwise. Nothing is allocated for the data."""
    p = Path(path)
    try:
        with open_regular(p) as handle:  # a FIFO or a device is refused, never waited on
            length = handle.seek(0, 2)
            handle.seek(0)
            return _checked_header(handle, length, str(p), max_bytes)
    except OSError as exc:
        raise DataError(f"{p}: cannot read ({exc.strerror or exc})") from None


def _checked_header(handle: BinaryIO, length: int, where: str, max_bytes: int) -> tuple[tuple[int, ...], np.dtype[Any]]:
    """(shape, dtype) from the ``.npy`` header at the start of ``handle`` (``length`` bytes in all)."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(handle)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(handle)
        elif version == (2, 0):
            shape, _, dtype = fmt.read_array_header_2_0(handle)
        else:
            raise DataError(f"{where}: NumPy file format version {version[0]}.{version[1]} is not read (1.0 and 2.0 are)")
        data = length - handle.tell()
    except (ValueError, SyntaxError, TypeError) as exc:  # a header that is not NumPy's
        raise DataError(f"{where}: not a NumPy array file ({exc})") from None
    if dtype.hasobject:
        raise DataError(f"{where}: holds Python objects (dtype {dtype}), which are not read")
    declared = math.prod(shape) * dtype.itemsize
    described = f"an array of shape {tuple(shape)} {dtype} ({declared} bytes)"
    if declared > max_bytes:
        raise DataError(f"{where}: its header declares {described}, more than the {max_bytes} bytes read")
    if declared != data:
        raise DataError(f"{where}: its header declares {described} but the file holds {data} bytes of data")
    return tuple(shape), dtype


def read_npy(path: Path | str, max_bytes: int = MAX_NPY_BYTES) -> NDArray[Any]:
    """The array in the ``.npy`` file ``path``, its header checked first (:func:`npy_header`)."""
    npy_header(path, max_bytes)
    try:
        return np.load(Path(path), allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise DataError(f"{path}: not a NumPy array file ({exc})") from None


def npy_from_bytes(data: bytes, where: str, max_bytes: int = MAX_NPY_BYTES) -> NDArray[Any]:
    """The array in the ``.npy`` bytes ``data`` (a member of an ``.npz`` a server sent), its header
    checked as the module says first; :class:`DataError` naming ``where`` otherwise."""
    handle = io.BytesIO(data)
    shape, dtype = _checked_header(handle, len(data), where, max_bytes)
    try:
        handle.seek(0)
        return np.lib.format.read_array(handle, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise DataError(f"{where}: not a NumPy array file ({exc})") from None

"""Refuse a splat the render server cannot draw, with one line naming the file and what is wrong.

A diverged training can leave NaN or inf in any Gaussian parameter, and a splat can hold no
Gaussian at all, or only ones too transparent to ever reach a pixel. Such a splat used to pass
``brave6d export`` and then crash the server at warm-up (an empty tensor indexed). Export and
the renderer's loading both call :func:`check_splat`; :func:`ply_vertex_count` lets
:func:`brave6d.serve.bundle.load_bundle` refuse an empty splat from the PLY header alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError

if TYPE_CHECKING:
    from brave6d.training import SplatData

#: The rasterizer skips a Gaussian whose alpha at a pixel is below this (gsplat's 1/255).
MIN_ALPHA = 1.0 / 255.0

#: ``SplatData`` fields in the order of the Inria PLY's vertex properties.
FIELDS = ("means", "sh0", "shN", "opacities", "scales", "quats")

_HOW_TO_FIX = "the training diverged or the file was damaged: train the scene again (then export)"


def activated_opacity(splat: SplatData) -> NDArray[np.float64]:
    """``sigmoid`` of the stored opacity logits, in float64 (as the renderer uses them)."""
    return 1.0 / (1.0 + np.exp(-splat.opacities.astype(np.float64)))


def ply_property_names(splat: SplatData, field: str) -> list[str]:
    """The PLY property of each column of ``getattr(splat, field).reshape(N, -1)`` (memory order).

    ``shN`` is ``[N, K, 3]`` in memory but channel-major in the file (``f_rest_{c * K + k}``).
    """
    if field == "means":
        return ["x", "y", "z"]
    if field == "sh0":
        return ["f_dc_0", "f_dc_1", "f_dc_2"]
    if field == "shN":
        k = splat.shN.shape[1]
        return [f"f_rest_{c * k + j}" for j in range(k) for c in range(3)]
    if field == "opacities":
        return ["opacity"]
    if field == "scales":
        return ["scale_0", "scale_1", "scale_2"]
    if field == "quats":
        return ["rot_0", "rot_1", "rot_2", "rot_3"]
    raise ValueError(f"unknown splat field {field!r}")


def _non_finite_columns(splat: SplatData) -> list[tuple[str, NDArray[np.float32]]]:
    """``(PLY property, column)`` of every column holding a NaN or inf, in the file's order."""
    n = splat.num_gaussians
    found: list[tuple[str, NDArray[np.float32]]] = []
    for field in FIELDS:
        values = np.asarray(getattr(splat, field)).reshape(n, -1)
        if np.isfinite(values).all():
            continue
        names = ply_property_names(splat, field)
        bad = [(names[i], values[:, i]) for i in range(values.shape[1]) if not np.isfinite(values[:, i]).all()]
        if field == "shN":  # memory order -> file order (f_rest_0, f_rest_1, ...)
            bad.sort(key=lambda item: int(item[0].rsplit("_", 1)[1]))
        found += bad
    return found


def check_splat(splat: SplatData, path: Path | str) -> None:
    """Refuse (:class:`DataError` naming ``path``) a splat with no Gaussians, with a NaN or inf
    in any parameter, or whose every Gaussian is too transparent for the rasterizer to draw."""
    n = splat.num_gaussians
    if n == 0:
        raise DataError(f"{path}: the splat holds no Gaussians; {_HOW_TO_FIX}")
    bad = _non_finite_columns(splat)
    if bad:
        name, column = bad[0]
        nan, inf = int(np.isnan(column).sum()), int(np.isinf(column).sum())
        kind = "NaN and inf" if nan and inf else "NaN" if nan else "inf"
        count = nan + inf
        others = [prop for prop, _ in bad[1:]]
        listed = ", ".join(others[:4]) + (", ..." if len(others) > 4 else "")
        also = f" (NaN or inf also in {len(others)} more propert{'y' if len(others) == 1 else 'ies'}: {listed})" \
            if others else ""
        raise DataError(f"{path}: {count} Gaussian{'s have' if count > 1 else ' has'} {kind} in '{name}'{also}; "
                        f"{_HOW_TO_FIX}")
    if not (activated_opacity(splat) >= MIN_ALPHA).any():
        raise DataError(f"{path}: none of the {n} Gaussians is visible (every opacity is below "
                        f"1/255, so nothing can be drawn); {_HOW_TO_FIX}")


def ply_vertex_count(path: Path | str) -> int:
    """The number of ``vertex`` elements a PLY header declares (reads the header only)."""
    p = Path(path)
    with open(p, "rb") as handle:
        if handle.readline().strip() != b"ply":
            raise DataError(f"{p}: not a PLY file")
        for line in iter(handle.readline, b""):
            words = line.split()
            if words[:1] == [b"end_header"]:
                break
            if words[:2] == [b"element", b"vertex"] and len(words) == 3:
                try:
                    return int(words[2])
                except ValueError:
                    raise DataError(f"{p}: malformed PLY header line {line.strip()!r}") from None
    raise DataError(f"{p}: the PLY header declares no 'vertex' element")

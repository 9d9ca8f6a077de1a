"""Read and write Gaussian splats in the Inria 3DGS PLY layout (what 3DGS viewers read).

One ``vertex`` element of float32 properties, in this order::

    x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3

Opacity, scales and rotations are stored before activation (logit, log, raw w x y z);
``f_rest`` is channel-major (all red coefficients, then green, then blue). Models of SH degree
below 3 are written with zero-padded ``f_rest`` so that every viewer finds 45 of them.
The reader also accepts PLYs from other trainers: fewer ``f_rest`` (lower SH degree), extra
properties (ignored), missing normals, float64 properties.

A splat trained with Mip-Splatting's 3D filter has one more property after those, ``filter_3d``
(the filter's standard deviation in metres, :mod:`brave6d.training.filter3d`; Mip-Splatting's own
name); viewers that do not know it ignore it, and a PLY without it reads as no filter.

For those viewers :func:`write_viewer_ply` writes the *viewer PLY*: the filter baked into the
stored log-scales and logit-opacities (:func:`bake_filter_3d`, what the server draws), no extra
property, so SuperSplat, gsplat's viewer or SIBR draw the Gaussians the server draws. Only the
rasterizer's 2D mip filter (view-dependent) cannot be baked: a viewer in its antialiased mode
renders the file as served; a classic one differs where Gaussians are smaller than a pixel.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from plyfile import PlyData, PlyElement

from brave6d.core.atomic import atomic_write
from brave6d.core.errors import DataError
from brave6d.core.ply_check import check_ply_header

#: SH coefficient of degree 0 (rgb = 0.5 + SH_C0 * f_dc).
SH_C0 = 0.28209479177387814
#: Number of ``f_rest`` properties of a degree-3 model.
N_REST_DEGREE3 = 45


def inria_attribute_names(n_rest: int = N_REST_DEGREE3) -> list[str]:
    """The vertex property names, in the Inria order."""
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


@dataclass
class SplatData:
    """Gaussians as stored (pre-activation), float32 NumPy arrays.

    ``sh0``: [N, 1, 3] (f_dc); ``shN``: [N, K, 3] with K = (degree + 1)^2 - 1 (coefficient-major
    in memory, like gsplat and Inria's ``_features_rest``); ``opacities``: [N] logits;
    ``scales``: [N, 3] logs; ``quats``: [N, 4] (w, x, y, z), not necessarily normalised.
    """

    means: NDArray[np.float32]
    sh0: NDArray[np.float32]
    shN: NDArray[np.float32]
    opacities: NDArray[np.float32]
    scales: NDArray[np.float32]
    quats: NDArray[np.float32]
    filter_3d: NDArray[np.float32] | None = None  # [N] 3D filter std (m); None: trained without

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_for(self.shN.shape[1])

    def subset(self, keep: NDArray[np.integer] | NDArray[np.bool_]) -> SplatData:
        """The Gaussians ``keep`` selects (indices or a mask), every per-Gaussian field with them
        (``filter_3d`` included when present), so no field can be left behind."""
        return replace(self, **{f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[keep]
                                for f in fields(self)})


def sh_degree_for(n_rest_coeffs: int) -> int:
    """SH degree whose ``(d + 1)^2 - 1`` equals ``n_rest_coeffs`` (per channel)."""
    for d in range(5):
        if (d + 1) ** 2 - 1 == n_rest_coeffs:
            return d
    raise ValueError(f"{n_rest_coeffs} higher-order SH coefficients per channel match no SH degree")


def write_ply(path: Path | str, splat: SplatData, pad_to_degree3: bool = True) -> Path:
    """Write ``splat`` in the Inria layout, atomically (binary little-endian float32)."""
    n = splat.num_gaussians
    shN = np.asarray(splat.shN, dtype=np.float32).reshape(n, -1, 3)
    k = shN.shape[1]
    sh_degree_for(k)  # refuses impossible coefficient counts
    if pad_to_degree3 and k < N_REST_DEGREE3 // 3:
        shN = np.concatenate([shN, np.zeros((n, N_REST_DEGREE3 // 3 - k, 3), np.float32)], axis=1)
        k = shN.shape[1]
    names = inria_attribute_names(3 * k)
    if splat.filter_3d is not None:
        names.append(FILTER_3D)
    columns = [
        np.asarray(splat.means, np.float32).reshape(n, 3),
        np.zeros((n, 3), np.float32),
        np.asarray(splat.sh0, np.float32).reshape(n, 3),
        shN.transpose(0, 2, 1).reshape(n, 3 * k),  # channel-major
        np.asarray(splat.opacities, np.float32).reshape(n, 1),
        np.asarray(splat.scales, np.float32).reshape(n, 3),
        np.asarray(splat.quats, np.float32).reshape(n, 4),
    ]
    if splat.filter_3d is not None:
        columns.append(np.asarray(splat.filter_3d, np.float32).reshape(n, 1))
    flat = np.concatenate(columns, axis=1)
    vertex = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertex[name] = flat[:, i]
    ply = PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<")
    return atomic_write(path, ply.write)


_REST = re.compile(r"^f_rest_(\d+)$")
#: The vertex property of the 3D filter's standard deviation.
FILTER_3D = "filter_3d"


def read_ply(path: Path | str) -> SplatData:
    """Read a 3DGS PLY (this project's or another trainer's); errors name the file and field."""
    p = Path(path)
    check_ply_header(p)  # element counts against the file's size, before plyfile allocates anything
    try:
        ply = PlyData.read(str(p))
    except FileNotFoundError:
        raise DataError(f"{p}: file not found") from None
    except Exception as exc:  # noqa: BLE001 - plyfile raises several types for malformed headers / bodies
        raise DataError(f"{p}: not a readable PLY file ({exc})") from None
    if "vertex" not in ply:
        raise DataError(f"{p}: no 'vertex' element")
    v = ply["vertex"].data
    present = set(v.dtype.names or ())

    def cols(names: list[str]) -> NDArray[np.float32]:
        missing = [nm for nm in names if nm not in present]
        if missing:
            raise DataError(f"{p}: vertex property {missing[0]!r} is missing (not a 3DGS splat PLY?)")
        return np.stack([np.asarray(v[nm], dtype=np.float32) for nm in names], axis=1)

    n = len(v)
    means = cols(["x", "y", "z"])
    sh0 = cols(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3)
    rest_ids = sorted(int(m.group(1)) for nm in present if (m := _REST.match(nm)))
    if rest_ids != list(range(len(rest_ids))) or len(rest_ids) % 3:
        raise DataError(f"{p}: f_rest properties must be f_rest_0..f_rest_(3K-1), got {len(rest_ids)} of them")
    k = len(rest_ids) // 3
    try:
        sh_degree_for(k)
    except ValueError as exc:
        raise DataError(f"{p}: {exc}") from None
    if k:
        shN = cols([f"f_rest_{i}" for i in rest_ids]).reshape(n, 3, k).transpose(0, 2, 1)
    else:
        shN = np.zeros((n, 0, 3), np.float32)
    return SplatData(
        means=means,
        sh0=sh0,
        shN=np.ascontiguousarray(shN),
        opacities=cols(["opacity"]).reshape(n),
        scales=cols(["scale_0", "scale_1", "scale_2"]),
        quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]),
        filter_3d=_filter_3d(p, cols([FILTER_3D]).reshape(n)) if FILTER_3D in present else None,
    )


def _filter_3d(path: Path, values: NDArray[np.float32]) -> NDArray[np.float32]:
    if not bool(np.all(np.isfinite(values) & (values >= 0))):
        raise DataError(f"{path}: vertex property {FILTER_3D!r} must be finite and >= 0")
    return values


#: The lowest logit-opacity baking the filter writes (an opacity of about 1e-35, far below the
#: 1/255 any rasterizer draws), unless the stored one was already lower: finite in float32.
VIEWER_MIN_LOGIT = -80.0


def bake_filter_3d(splat: SplatData) -> SplatData:
    """``splat`` with its 3D filter folded into the stored scales and opacities, ``filter_3d`` None.

    :func:`brave6d.training.apply_filter_3d` (effective scale ``sqrt(s^2 + f^2)``, opacity times
    ``sqrt(det(S) / det(S + f^2 I))``) computed in log space in float64, so that any finite float32
    input gives finite values: log-scale ``0.5 * logaddexp(2 log s, 2 log f)`` and the logit of the
    reduced opacity through ``log(1 - a) = log(-expm1(log a))``, never below :data:`VIEWER_MIN_LOGIT`
    (or the stored logit when that is lower). A zero filter, or none, leaves the values unchanged.
    """
    if splat.filter_3d is None:
        return replace(splat)
    log_s = np.asarray(splat.scales, np.float64)
    with np.errstate(divide="ignore"):  # a zero filter: log 0 = -inf, and logaddexp(x, -inf) = x exactly
        log_f = np.log(np.asarray(splat.filter_3d, np.float64))[:, None]
    log_total = np.logaddexp(2.0 * log_s, 2.0 * log_f)
    log_factor = 0.5 * (2.0 * log_s - log_total).sum(axis=1)  # log sqrt(det ratio) <= 0
    logit = np.asarray(splat.opacities, np.float64)
    log_a = -np.logaddexp(0.0, -logit) + log_factor  # log(sigmoid(logit) * factor)
    with np.errstate(divide="ignore"):
        baked = log_a - np.log(-np.expm1(log_a))
    baked = np.where(log_factor == 0.0, logit, baked)  # unchanged where the filter changes nothing
    floor = np.minimum(logit, VIEWER_MIN_LOGIT)
    return replace(splat, scales=(0.5 * log_total).astype(np.float32),
                   opacities=np.maximum(baked, floor).astype(np.float32), filter_3d=None)


def write_viewer_ply(path: Path | str, splat: SplatData) -> Path:
    """Write the viewer PLY of ``splat`` (:func:`bake_filter_3d`; the Inria layout, nothing else),
    atomically. A splat with a NaN or inf parameter is refused with an error naming ``path``."""
    for name in ("means", "scales", "opacities", "quats", FILTER_3D):
        values = getattr(splat, name)
        if values is not None and not bool(np.all(np.isfinite(values))):
            raise DataError(f"{path}: cannot write the viewer PLY: the splat's {name} hold NaN or inf")
    if splat.filter_3d is not None and bool(np.any(splat.filter_3d < 0)):
        raise DataError(f"{path}: cannot write the viewer PLY: the splat's {FILTER_3D} holds negative values")
    return write_ply(path, bake_filter_3d(splat))


def trim_sh(splat: SplatData, degree: int) -> SplatData:
    """``splat`` with higher-order SH truncated (or zero-padded) to ``degree``."""
    k = (degree + 1) ** 2 - 1
    n = splat.num_gaussians
    shN = splat.shN[:, :k]
    if shN.shape[1] < k:
        shN = np.concatenate([shN, np.zeros((n, k - shN.shape[1], 3), np.float32)], axis=1)
    return replace(splat, shN=np.ascontiguousarray(shN))

"""Input checks and the documented neutralisation rules, shared by all backends.

Rules (applied identically before every backend, so all backends agree):

* Shapes, dtypes, devices and scalar arguments are checked; a violation raises
  :class:`RasterInputError` naming the argument.
* NaN or +-inf anywhere in ``means``, ``quats``, ``scales``, ``opacities``, ``colors``,
  ``viewmats``, ``Ks`` or ``backgrounds`` raises :class:`RasterInputError` naming the
  tensor and the number of bad values (silently rendering garbage hides training bugs).
* A quaternion whose squared norm is below ``QUAT_MIN_SQNORM`` (zero or denormal) is
  replaced by the identity rotation; its gradient is zero.
* Scales are clamped to ``[SCALE_MIN, SCALE_MAX]``; the gradient is zero where clamped.
* Gaussians with camera depth outside ``[near_plane, far_plane]`` are culled by the
  backends (radius 0, zero gradient), as are Gaussians whose projection is degenerate.
* Opacities are used as given (already activated, like gsplat): alpha is capped at
  ``ALPHA_MAX`` and skipped below ``ALPHA_THRESHOLD``.
* ``Ks`` arrive in the project's OpenCV convention (pixel centres at integer coordinates) and
  leave in gsplat's (centres at +0.5): the principal point moves by +0.5 px here, once, for
  every backend (see ``_pixels``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from brave6d.core.errors import BraveError

from .constants import QUAT_MIN_SQNORM, SCALE_MAX, SCALE_MIN
from ._pixels import gsplat_intrinsics

MAX_SH_DEGREE = 3


class RasterInputError(BraveError, ValueError):
    """The rasterizer was given inputs it cannot render (bad shape, NaN/inf, bad camera)."""


class RasterBackendError(BraveError, RuntimeError):
    """The requested rasterizer backend cannot run here (e.g. 'cuda' without a GPU)."""


@dataclass(frozen=True)
class RasterInputs:
    """Checked and neutralised rasterizer inputs (still attached to the caller's graph)."""

    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4], safe to normalise
    scales: Tensor  # [N, 3], clamped
    opacities: Tensor  # [N]
    colors: Tensor  # [N, 3], [C, N, 3], [N, K, 3] or [C, N, K, 3]
    viewmats: Tensor  # [C, 4, 4]
    Ks: Tensor  # [C, 3, 3], gsplat's pixel convention (the caller's OpenCV K, cx and cy + 0.5)
    backgrounds: Tensor | None  # [C, 3] or None
    width: int
    height: int
    sh_degree: int | None
    near_plane: float
    far_plane: float
    eps2d: float
    antialiased: bool = False  # 2D mip filter: opacity times det(cov2d) / det(cov2d + eps2d I), sqrt

    @property
    def n_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def n_cameras(self) -> int:
        return int(self.viewmats.shape[0])

    @property
    def per_camera_colors(self) -> bool:
        """True when colours (or SH coefficients) are given per camera."""
        base = 2 if self.sh_degree is None else 3
        return self.colors.dim() == base + 1


def _require_shape(name: str, t: Tensor, shape: tuple) -> None:
    ok = t.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, t.shape))
    if not ok:
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise RasterInputError(f"rasterize: `{name}` must have shape {want}, got {list(t.shape)}")


def _host_array(t: Tensor) -> np.ndarray | None:
    """A NumPy view (no copy) of a CPU tensor, None for other devices.

    The checks below run on it with NumPy: on a CPU, each small torch operation may wake the
    intra-op thread pool (tens of microseconds with OMP_WAIT_POLICY=PASSIVE), and the checks
    are a dozen such operations per render."""
    return t.detach().numpy() if t.device.type == "cpu" else None


def _require_finite(name: str, t: Tensor) -> None:
    if t.numel() == 0:
        return
    # One reduction first: a NaN or inf anywhere makes the sum non-finite, so a finite sum
    # proves the tensor finite; only a non-finite sum (or a float overflow) needs the full test.
    host = _host_array(t)
    if host is not None:
        with np.errstate(over="ignore", invalid="ignore"):
            if np.isfinite(host.sum()):
                return
        n_bad = int(host.size - np.count_nonzero(np.isfinite(host)))
    elif bool(torch.isfinite(t.detach().sum())):
        return
    else:
        n_bad = int((~torch.isfinite(t.detach())).sum())
    if n_bad:
        raise RasterInputError(
            f"rasterize: `{name}` contains {n_bad} NaN/inf value(s) out of {t.numel()}"
        )


def _require_float(name: str, t: Tensor) -> None:
    if not isinstance(t, Tensor):
        raise RasterInputError(f"rasterize: `{name}` must be a torch.Tensor, got {type(t).__name__}")
    if t.dtype not in (torch.float32, torch.float64):
        raise RasterInputError(
            f"rasterize: `{name}` must be float32 (or float64), got {t.dtype}; "
            "half precision is not supported"
        )


def _check_colors(colors: Tensor, n: int, c: int, sh_degree: int | None) -> None:
    if sh_degree is None:
        if colors.dim() == 2 and tuple(colors.shape) == (n, 3):
            return
        if colors.dim() == 3 and tuple(colors.shape) == (c, n, 3):
            return
        raise RasterInputError(
            f"rasterize: `colors` must be [N, 3] or [C, N, 3] RGB (N={n}, C={c}) when "
            f"sh_degree is None, got {list(colors.shape)}"
        )
    k_needed = (sh_degree + 1) ** 2
    lead = tuple(colors.shape[:-2])
    if colors.dim() >= 3 and colors.shape[-1] == 3 and lead in ((n,), (c, n)):
        if colors.shape[-2] < k_needed:
            raise RasterInputError(
                f"rasterize: sh_degree={sh_degree} needs at least {k_needed} SH coefficients "
                f"per Gaussian, `colors` has {colors.shape[-2]}"
            )
        return
    raise RasterInputError(
        f"rasterize: `colors` must be [N, K, 3] or [C, N, K, 3] SH coefficients (N={n}, C={c}) "
        f"when sh_degree is set, got {list(colors.shape)}"
    )


def check_values(named: dict[str, Tensor]) -> None:
    """NaN/inf in any named tensor and non-positive focal lengths in ``Ks`` (RasterInputError)."""
    for name, t in named.items():
        _require_finite(name, t)
    fxfy = named["Ks"].detach()[:, [0, 1], [0, 1]]
    if bool((fxfy <= 0).any()):
        raise RasterInputError("rasterize: focal lengths Ks[:, 0, 0] and Ks[:, 1, 1] must be > 0")


def sanitize_quats(quats: Tensor) -> Tensor:
    """Replace zero / denormal quaternions by the identity (zero gradient there)."""
    if quats.numel() == 0:
        return quats
    host = _host_array(quats)
    if host is not None:
        # a matrix product sums the 4 squares 4x faster than a reduction over the short axis
        bad_host = np.square(host, dtype=np.float64) @ np.ones(4) < QUAT_MIN_SQNORM
        if not bad_host.any():
            return quats
        bad = torch.from_numpy(bad_host)
    else:  # on a GPU: no host sync, the same values (where() keeps the good rows as they are)
        bad = (quats.detach().double() ** 2).sum(-1) < QUAT_MIN_SQNORM
    identity = torch.zeros_like(quats)
    identity[:, 0] = 1.0
    return torch.where(bad[:, None], identity, quats)


def sanitize_scales(scales: Tensor) -> Tensor:
    """Clamp activated scales to the documented range (zero gradient where clamped)."""
    host = _host_array(scales)
    if host is not None and (host.size == 0 or (host.min() >= SCALE_MIN and host.max() <= SCALE_MAX)):
        return scales  # the clamp would be the identity, gradient included
    return scales.clamp(min=SCALE_MIN, max=SCALE_MAX)


def prepare_inputs(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int | None,
    near_plane: float,
    far_plane: float,
    backgrounds: Tensor | None,
    eps2d: float,
    antialiased: bool = False,
    validate: bool = True,
) -> RasterInputs:
    """Check every rasterizer argument and apply the neutralisation rules above.

    ``validate=False`` leaves out the value checks (NaN/inf, focal lengths > 0), which on a GPU
    each wait for the device: for callers that checked their cameras once and watch their
    parameters themselves (the trainer's lean GPU step). Types, devices and shapes are always
    checked (on the host, free)."""
    named = {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "colors": colors,
        "viewmats": viewmats,
        "Ks": Ks,
    }
    if backgrounds is not None:
        named["backgrounds"] = backgrounds
    for name, t in named.items():
        _require_float(name, t)
    device = means.device
    for name, t in named.items():
        if t.device != device:
            raise RasterInputError(
                f"rasterize: `{name}` is on {t.device} but `means` is on {device}"
            )

    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise RasterInputError(f"rasterize: `{name}` must be a positive int, got {value!r}")
    if sh_degree is not None and (
        isinstance(sh_degree, bool) or not isinstance(sh_degree, int)
        or not 0 <= sh_degree <= MAX_SH_DEGREE
    ):
        raise RasterInputError(
            f"rasterize: `sh_degree` must be None or an int in [0, {MAX_SH_DEGREE}], "
            f"got {sh_degree!r}"
        )
    for name, value in (("near_plane", near_plane), ("far_plane", far_plane), ("eps2d", eps2d)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise RasterInputError(f"rasterize: `{name}` must be a finite number, got {value!r}")
    if near_plane < 0.0 or far_plane <= near_plane:
        raise RasterInputError(
            f"rasterize: need 0 <= near_plane < far_plane, got near={near_plane}, far={far_plane}"
        )
    if eps2d < 0.0:
        raise RasterInputError(f"rasterize: `eps2d` must be >= 0, got {eps2d}")
    if not isinstance(antialiased, bool):
        raise RasterInputError(f"rasterize: `antialiased` must be a bool, got {antialiased!r}")

    _require_shape("means", means, (None, 3))
    n = int(means.shape[0])
    _require_shape("quats", quats, (n, 4))
    _require_shape("scales", scales, (n, 3))
    _require_shape("opacities", opacities, (n,))
    _require_shape("viewmats", viewmats, (None, 4, 4))
    c = int(viewmats.shape[0])
    if c < 1:
        raise RasterInputError("rasterize: need at least one camera (`viewmats` is [0, 4, 4])")
    _require_shape("Ks", Ks, (c, 3, 3))
    _check_colors(colors, n, c, sh_degree)
    if backgrounds is not None:
        if backgrounds.dim() == 1:
            _require_shape("backgrounds", backgrounds, (3,))
            backgrounds = backgrounds[None].expand(c, 3)
        else:
            _require_shape("backgrounds", backgrounds, (c, 3))

    if validate:
        check_values(named)

    return RasterInputs(
        means=means,
        quats=sanitize_quats(quats),
        scales=sanitize_scales(scales),
        opacities=opacities,
        colors=colors,
        viewmats=viewmats,
        Ks=gsplat_intrinsics(Ks),
        backgrounds=backgrounds,
        width=int(width),
        height=int(height),
        sh_degree=sh_degree,
        near_plane=float(near_plane),
        far_plane=float(far_plane),
        eps2d=float(eps2d),
        antialiased=antialiased,
    )

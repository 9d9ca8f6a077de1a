"""The Gaussian model: trainable parameters (gsplat names), initialisation and activations.

Parameters, stored before activation like Inria and gsplat's ``simple_trainer``:
``means`` [N, 3], ``quats`` [N, 4] (w, x, y, z), ``scales`` [N, 3] (log), ``opacities`` [N]
(logit), ``sh0`` [N, 1, 3] and ``shN`` [N, K, 3] with K = (sh_degree + 1)^2 - 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree
from torch import Tensor

from brave6d.training.ply import SH_C0, SplatData, read_ply, write_ply
from brave6d.training.scene_frame import MIN_INIT_DISTANCE, SceneFrame

PARAM_NAMES = ("means", "quats", "scales", "opacities", "sh0", "shN")

def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """Degree-0 SH coefficient of a colour in [0, 1]."""
    return (rgb - 0.5) / SH_C0


#: A lone point's initial scale, in scene extents (it has no neighbours to measure).
LONE_POINT_SCALE = 1e-3


def initial_log_scales(points: np.ndarray, extent: float = 1.0) -> np.ndarray:
    """Log of the RMS distance to the 3 nearest neighbours, per point (Inria's init).

    ``extent``: the scene's extent in the points' units (1 in a training frame,
    :mod:`brave6d.training.scene_frame`). Coincident points get the floor ``MIN_INIT_DISTANCE``
    extents (Inria's ``sqrt(1e-7)`` on the demo's scene); a lone point gets ``LONE_POINT_SCALE`` extents.
    """
    if not (math.isfinite(extent) and extent > 0.0):
        raise ValueError(f"initial_log_scales: the extent must be a positive number, got {extent}")
    n = len(points)
    if n == 0:
        return np.zeros((0, 3), np.float32)
    fallback = LONE_POINT_SCALE * extent
    if n == 1:
        return np.full((1, 3), math.log(fallback), np.float32)
    floor2 = (MIN_INIT_DISTANCE * extent) ** 2
    k = min(4, n)
    dist, _ = cKDTree(points).query(points, k=k)
    d2 = np.mean(dist[:, 1:] ** 2, axis=1)
    d2 = np.maximum(np.nan_to_num(d2, nan=floor2, posinf=fallback**2), floor2)
    return np.repeat(np.log(np.sqrt(d2))[:, None], 3, axis=1).astype(np.float32)


@dataclass
class GaussianModel:
    """Trainable Gaussians (``params``: a ParameterDict with the gsplat names) of max SH degree."""

    params: torch.nn.ParameterDict
    sh_degree: int
    #: Mip-Splatting's 3D filter [N] (std, metres; :mod:`brave6d.training.filter3d`), not trained:
    #: computed from the training cameras; None: no filter
    filter_3d: Tensor | None = None

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_points(
        cls,
        points: ArrayLike,
        colors: ArrayLike | None = None,
        sh_degree: int = 3,
        init_opacity: float = 0.1,
        init_scale: float = 1.0,
        device: torch.device | str = "cpu",
        extent: float = 1.0,
    ) -> GaussianModel:
        """Isotropic Gaussians at ``points`` (N, 3) with ``colors`` (N, 3) in [0, 1] (grey if None).

        ``extent``: the scene's extent in the points' units (1: points in a training frame, as
        :func:`brave6d.training.train` gives; a caller in world units passes ``data.scene_extent()``)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(pts).all():
            raise ValueError("GaussianModel.from_points: points contain NaN or inf")
        n = len(pts)
        rgb = np.full((n, 3), 0.5) if colors is None else np.asarray(colors, dtype=np.float64).reshape(n, 3)
        log_scales = initial_log_scales(pts, extent) + np.float32(math.log(init_scale))
        quats = np.zeros((n, 4), np.float32)
        quats[:, 0] = 1.0
        opacity = min(max(init_opacity, 1e-6), 1.0 - 1e-6)
        k = (sh_degree + 1) ** 2 - 1
        tensors = {
            "means": torch.from_numpy(pts.astype(np.float32)),
            "quats": torch.from_numpy(quats),
            "scales": torch.from_numpy(log_scales),
            "opacities": torch.full((n,), math.log(opacity / (1.0 - opacity)), dtype=torch.float32),
            "sh0": rgb_to_sh0(torch.from_numpy(np.clip(rgb, 0.0, 1.0).astype(np.float32)))[:, None, :],
            "shN": torch.zeros((n, k, 3), dtype=torch.float32),
        }
        return cls.from_tensors(tensors, sh_degree, device)

    @classmethod
    def from_tensors(cls, tensors: dict[str, Tensor], sh_degree: int, device: torch.device | str = "cpu") -> GaussianModel:
        """Wrap pre-activation tensors (the :data:`PARAM_NAMES`) as trainable parameters."""
        params = torch.nn.ParameterDict(
            {name: torch.nn.Parameter(tensors[name].to(device=device, dtype=torch.float32).contiguous())
             for name in PARAM_NAMES})
        return cls(params, sh_degree)

    @classmethod
    def from_splat(cls, splat: SplatData, device: torch.device | str = "cpu") -> GaussianModel:
        """A model from PLY data (see :func:`brave6d.training.ply.read_ply`)."""
        tensors = {name: torch.from_numpy(np.ascontiguousarray(getattr(splat, name))) for name in PARAM_NAMES}
        model = cls.from_tensors(tensors, splat.sh_degree, device)
        if splat.filter_3d is not None:
            model.filter_3d = torch.as_tensor(np.asarray(splat.filter_3d, np.float32), device=device)
        return model

    @classmethod
    def from_ply(cls, path: str | Path, device: torch.device | str = "cpu") -> GaussianModel:
        """Load a 3DGS PLY (this project's or another trainer's)."""
        return cls.from_splat(read_ply(path), device)

    def in_world(self, frame: SceneFrame) -> GaussianModel:
        """This model, trained in ``frame`` (:mod:`brave6d.training.scene_frame`), in the world: centres
        moved back, scales and the 3D filter times ``frame.unit`` (log scales plus ``log(unit)``);
        rotations, opacities and colours unchanged."""
        p = {k: v.detach() for k, v in self.params.items()}
        means = frame.world_points(p["means"].cpu().double().numpy())
        tensors = {**p, "means": torch.from_numpy(means), "scales": p["scales"].double() + math.log(frame.unit)}
        out = GaussianModel.from_tensors(tensors, self.sh_degree, self.device)
        if self.filter_3d is not None:
            out.filter_3d = (self.filter_3d.double() * frame.unit).to(self.filter_3d.dtype)
        return out

    def save_ply(self, path: str | Path) -> Path:
        """Export in the Inria layout (see :mod:`brave6d.training.ply`)."""
        return write_ply(path, self.to_splat())

    def to_splat(self) -> SplatData:
        """The parameters as float32 NumPy arrays (for :func:`brave6d.training.ply.write_ply`)."""
        arrays = {name: self.params[name].detach().cpu().numpy().astype(np.float32, copy=False) for name in PARAM_NAMES}
        f3d = None if self.filter_3d is None else self.filter_3d.detach().cpu().numpy().astype(np.float32)
        return SplatData(**arrays, filter_3d=f3d)

    @property
    def antialiased(self) -> bool:
        """Rendered with Mip-Splatting's filters (a model trained with them carries the 3D filter):
        the rasterizer's ``antialiased`` mode besides :meth:`render_scales_opacities`."""
        return self.filter_3d is not None

    def render_scales_opacities(self) -> tuple[Tensor, Tensor]:
        """Activated scales and opacities as the rasterizer draws them: through the 3D filter when
        the model has one (:func:`brave6d.training.filter3d.apply_filter_3d`)."""
        from brave6d.training.filter3d import apply_filter_3d

        return apply_filter_3d(self.scales(), self.opacities(), self.filter_3d)

    # ------------------------------------------------------------------ activations
    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @property
    def means(self) -> Tensor:
        return self.params["means"]

    @property
    def quats(self) -> Tensor:
        return self.params["quats"]

    def scales(self) -> Tensor:
        """Activated scales (exp)."""
        return torch.exp(self.params["scales"])

    def opacities(self) -> Tensor:
        """Activated opacities (sigmoid)."""
        return torch.sigmoid(self.params["opacities"])

    def sh_coeffs(self, degree: int | None = None) -> Tensor:
        """The SH coefficients up to ``degree`` (default: the model's), [N, (degree + 1)^2, 3].

        Only the coefficients the degree uses are copied (degree 0 is ``sh0`` itself), which
        matters on the CPU, where this concatenation and its backward are a per-step cost."""
        d = self.sh_degree if degree is None else degree
        if not 0 <= d <= self.sh_degree:
            raise ValueError(f"sh_coeffs: degree must be in 0..{self.sh_degree}, got {d}")
        if d == 0:
            return self.params["sh0"]
        return torch.cat([self.params["sh0"], self.params["shN"][:, : (d + 1) ** 2 - 1]], dim=1)

    def non_finite(self) -> list[str]:
        """Names of parameters that hold NaN or inf (empty when all are finite)."""
        return [name for name in PARAM_NAMES if not bool(torch.isfinite(self.params[name].detach()).all())]

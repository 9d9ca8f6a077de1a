"""Holdout evaluation, ``splat/metrics.json`` and the training-curve plot.

PSNR and SSIM (Inria's definitions, see :mod:`brave6d.training.losses`) are computed per held-out view
at the training resolution and averaged overall and per distance level. A side-by-side PNG
(render | ground truth) is written per held-out view.
"""

from __future__ import annotations

import logging
import resource
import sys
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from brave6d.core.atomic import atomic_write, atomic_write_json, write_png
from brave6d.training.views import TrainingData, View, image_tensor
from brave6d.training.losses import fill_invalid, psnr, ssim
from brave6d.training.model import GaussianModel

log = logging.getLogger(__name__)


@dataclass
class ViewScore:
    index: int
    view_id: str
    distance_level: int
    distance_m: float
    psnr: float
    ssim: float


@dataclass
class HoldoutMetrics:
    """Mean PSNR/SSIM over the held-out views, overall and per distance level."""

    psnr: float
    ssim: float
    n_views: int
    per_level: dict[int, dict[str, float]] = field(default_factory=dict)
    per_view: list[ViewScore] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"psnr": self.psnr, "ssim": self.ssim, "n_views": self.n_views,
                "per_level": {str(k): v for k, v in sorted(self.per_level.items())},
                "per_view": [asdict(s) for s in self.per_view]}


@torch.no_grad()
def render_view(model: GaussianModel, view: View, data: TrainingData, sh_degree: int | None = None) -> torch.Tensor:
    """Render ``model`` into ``view``'s camera: float [H, W, 3] in [0, 1] (``model`` and ``data`` in
    the same frame: the world's, or both in a training frame)."""
    from brave6d.training.rasterizer import rasterize

    from brave6d.training.scene_frame import near_far

    d = model.sh_degree if sh_degree is None else sh_degree
    device = model.device
    viewmat = torch.from_numpy(view.viewmat).float().to(device)[None]
    K = torch.from_numpy(data.camera.K).float().to(device)[None]
    scales, opacities = model.render_scales_opacities()
    near, far = near_far(data.scene_extent())  # the trainer's planes: relative to the scene
    colors, _, _, _ = rasterize(model.means, model.quats, scales, opacities,
                                model.sh_coeffs(d), viewmat, K, data.camera.width,
                                data.camera.height, sh_degree=d, near_plane=near, far_plane=far,
                                antialiased=model.antialiased)
    return colors[0].clamp(0.0, 1.0)


def evaluate_holdout(model: GaussianModel, data: TrainingData, image_dir: Path | None = None) -> HoldoutMetrics:
    """Score ``model`` on ``data.test``; with ``image_dir``, write ``<view_id>.png`` (render | GT)."""
    scores: list[ViewScore] = []
    valid = data.valid_tensor(model.device)
    for view in data.test:
        render = render_view(model, view, data)
        gt = image_tensor(view, model.device)
        scored = fill_invalid(gt, render, valid)  # border pixels without raw data do not score
        scores.append(ViewScore(view.index, view.view_id, view.distance_level, view.distance_m,
                                psnr(render, gt, valid), float(ssim(render, scored))))
        if image_dir is not None:
            side = torch.cat([render, gt], dim=1)
            write_png(image_dir / f"{view.view_id}.png",
                      (side.cpu().numpy() * 255.0 + 0.5).clip(0, 255).astype(np.uint8))
    by_level: dict[int, list[ViewScore]] = defaultdict(list)
    for s in scores:
        by_level[s.distance_level].append(s)
    per_level = {lvl: {"distance_m": ss[0].distance_m, "psnr": _mean([s.psnr for s in ss]),
                       "ssim": _mean([s.ssim for s in ss]), "n_views": len(ss)}
                 for lvl, ss in sorted(by_level.items())}
    return HoldoutMetrics(_mean([s.psnr for s in scores]), _mean([s.ssim for s in scores]), len(scores),
                          per_level, scores)


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def peak_memory_mb(device: torch.device) -> dict[str, float]:
    """Peak resident memory of this process (and peak CUDA allocation on a GPU), MiB."""
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rss_mb = rss_kb / (1024.0 * 1024.0) if sys.platform == "darwin" else rss_kb / 1024.0
    out = {"peak_rss_mb": rss_mb}
    if device.type == "cuda" and torch.cuda.is_available():
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    return out


def json_safe(obj: Any) -> Any:
    """Replace NaN/inf floats with None, recursively (JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def write_metrics(path: Path, metrics: dict[str, Any]) -> Path:
    """Write ``metrics.json`` atomically."""
    return atomic_write_json(path, json_safe(metrics))


def plot_curves(path: Path, curve: list[dict[str, float]], title: str = "training") -> Path:
    """PSNR (train EMA and holdout points) and #Gaussians against training time, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([c["time_s"] for c in curve])
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    ax1.plot(t, [c.get("train_psnr", np.nan) for c in curve], label="train (EMA)")
    held = [(c["time_s"], c["holdout_psnr"]) for c in curve if c.get("holdout_psnr") is not None]
    if held:
        ax1.plot(*zip(*held), "o-", label="holdout")
    ax1.set_xlabel("training time [s]")
    ax1.set_ylabel("PSNR [dB]")
    ax1.grid(alpha=0.3)
    ax1.legend()
    ax2.plot(t, [c["num_gaussians"] for c in curve], color="tab:green")
    ax2.set_xlabel("training time [s]")
    ax2.set_ylabel("# Gaussians")
    ax2.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    atomic_write(path, lambda handle: fig.savefig(handle, format="png", dpi=110))
    plt.close(fig)
    return path

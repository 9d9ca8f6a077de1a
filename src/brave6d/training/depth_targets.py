"""Sensor depth as a training target: resampled to the training resolution, with a validity mask.

A depth sensor gives no value where it sees nothing (0 in the project's depth images) and a value of
one surface or the other at a depth edge, never a blend; a splat's rendered expected depth blends at
edges. So a target pixel is used only where the sensor is trustworthy and the render can agree:

* it has data (``> 0``), and every capture pixel it averages has data (a block with a hole is left out);
* it lies on no depth edge: the depths it averages, and its 3x3 neighbours at training resolution,
  span at most ``edge_ratio`` times its depth (a step bigger than that is an occlusion boundary).

The target is the mean of the block (the sensor's noise averages down with it). A frame without a
depth file, or whose every pixel is left out, has no target (``None``) and trains on colour alone.
:func:`load_depth_targets` makes every training view's target once (the trainer's, and the coarse
level's halves of them).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from brave6d.core.errors import DataError
from brave6d.training.views import TrainingData, load_depth_m

log = logging.getLogger(__name__)

#: Default relative depth step (of the pixel's depth) above which a pixel counts as a depth edge.
EDGE_RATIO = 0.02


@dataclass(frozen=True)
class DepthTarget:
    """One view's target depth (float32 [H, W], 0 where ``valid`` is False; in the poses' units: metres
    in the world, extents in a training frame) and its mask."""

    depth: Tensor
    valid: Tensor  # bool [H, W]

    @property
    def count(self) -> int:
        return int(self.valid.sum())

    def to(self, device: torch.device | str) -> DepthTarget:
        return DepthTarget(self.depth.to(device), self.valid.to(device))

    def halved(self, edge_ratio: float = EDGE_RATIO) -> DepthTarget:
        """The target at half width and height (2x2 blocks, the coarse training level)."""
        depth, valid = block_average(self.depth.cpu().numpy(), 2, self.valid.cpu().numpy(), edge_ratio)
        return DepthTarget(torch.from_numpy(depth), torch.from_numpy(valid)).to(self.depth.device)


def block_average(depth: NDArray[np.floating], factor: int, valid: NDArray[np.bool_] | None = None,
                  edge_ratio: float = EDGE_RATIO) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Average ``factor`` x ``factor`` blocks of ``depth`` (metres; 0 or non-finite: no data).

    A block is valid when all its pixels are (``valid`` and data) and its depths span at most
    ``edge_ratio`` times their mean. The last rows/columns that do not fill a block are dropped.
    """
    if factor < 1:
        raise DataError(f"depth target: the resampling factor must be >= 1, got {factor}")
    d = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0)
    if valid is not None:
        ok &= valid
    d = np.where(ok, d, 0.0)
    h, w = d.shape[0] // factor * factor, d.shape[1] // factor * factor
    if h == 0 or w == 0:
        raise DataError(f"depth target: a {d.shape[1]}x{d.shape[0]} depth image is smaller than one "
                        f"{factor}x{factor} block")
    blocks = d[:h, :w].reshape(h // factor, factor, w // factor, factor)
    ok_blocks = ok[:h, :w].reshape(h // factor, factor, w // factor, factor).all(axis=(1, 3))
    mean = blocks.mean(axis=(1, 3))
    with np.errstate(invalid="ignore"):
        span = blocks.max(axis=(1, 3)) - np.where(ok[:h, :w], d[:h, :w], np.inf).reshape(blocks.shape).min(axis=(1, 3))
    keep = ok_blocks & (span <= edge_ratio * mean)
    return np.where(keep, mean, 0.0).astype(np.float32), keep


def drop_edges(depth: NDArray[np.float32], valid: NDArray[np.bool_], edge_ratio: float = EDGE_RATIO
               ) -> NDArray[np.bool_]:
    """``valid`` without the pixels whose valid 3x3 neighbours differ from them by more than
    ``edge_ratio`` times their depth, and without those next to a pixel without data."""
    h, w = depth.shape
    padded = np.pad(np.where(valid, depth, np.nan), 1, mode="edge")  # the image border is no hole
    keep = valid.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            other = padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
            with np.errstate(invalid="ignore"):
                keep &= np.isfinite(other) & (np.abs(other - depth) <= edge_ratio * depth)
    return keep


def depth_target(depth_m: NDArray[np.floating] | None, width: int, height: int,
                 edge_ratio: float = EDGE_RATIO) -> DepthTarget | None:
    """A view's target at ``width`` x ``height`` from its depth image at capture resolution.

    The capture size must be an integer multiple of the training size (the presets' ``downscale``).
    None when there is no depth image or no pixel is usable.
    """
    if depth_m is None:
        return None
    dh, dw = depth_m.shape[:2]
    factor = dw // width if width else 0
    if factor < 1 or dw != factor * width or dh != factor * height:
        raise DataError(f"depth target: a {dw}x{dh} depth image does not shrink to {width}x{height} "
                        "by an integer factor")
    depth, valid = block_average(depth_m, factor, None, edge_ratio)
    valid = drop_edges(depth, valid, edge_ratio)
    if not valid.any():
        return None
    return DepthTarget(torch.from_numpy(np.where(valid, depth, 0.0).astype(np.float32)), torch.from_numpy(valid))


def load_depth_targets(data: TrainingData, edge_ratio: float, device: torch.device | str = "cpu"
                       ) -> list[DepthTarget | None]:
    """The depth target of every training view at the training resolution (None: no usable depth), in
    the units of ``data``'s poses (metres divided by :attr:`TrainingData.length_unit`).

    Training views without depth train on colour alone; when no view has any, the run says so once.
    """
    cam = data.camera
    unit = data.length_unit  # metres per unit of the poses (a training frame's extent; 1 in the world)
    targets: list[DepthTarget | None] = []
    for view in data.train:
        depth_m = load_depth_m(view, data.depth_camera)
        depth = depth_m if depth_m is None or unit == 1.0 else (depth_m.astype(np.float64) / unit).astype(np.float32)
        target = depth_target(depth, cam.width, cam.height, edge_ratio)
        targets.append(None if target is None else target.to(device))
    used = sum(t is not None for t in targets)
    if used == 0:
        log.warning("depth loss asked for, but none of the %d training views has usable depth; training on "
                    "colour alone", len(targets))
    elif used < len(targets):
        log.info("depth loss on %d of %d training views (the others have no usable depth)", used, len(targets))
    return targets


def depth_loss(render_depth: Tensor, render_alpha: Tensor, target: DepthTarget, min_alpha: float = 0.5,
               masked_sums: bool = False) -> Tensor:
    """Mean relative L1 ``|d - d*| / d*`` of the rendered expected depth over the target's valid pixels
    where the render is opaque (alpha >= ``min_alpha``: elsewhere its expected depth is ill-defined;
    the colour loss fills holes). Relative, so that a millimetre counts the same at every ring.
    Zero (with a gradient graph) when no pixel qualifies.

    ``masked_sums``: the same loss as sums over a mask, without the pixel count on the host nor
    boolean gathers (each waits for a GPU): the lean GPU step's form; equal up to the order of the
    float sums."""
    d = render_depth.reshape(target.depth.shape)
    use = target.valid & (render_alpha.detach().reshape(target.depth.shape) >= min_alpha)
    if masked_sums:
        # unused pixels take the target's (or 1) on both sides: zero, with a finite zero gradient
        ref = torch.where(use, target.depth, torch.ones_like(target.depth))
        rel = (torch.where(use, d, ref) - ref).abs() / ref
        return rel.sum() / use.sum().clamp(min=1)
    count = int(use.sum())
    if count == 0:
        return d.sum() * 0.0
    rel = (d[use] - target.depth[use]).abs() / target.depth[use]
    return rel.sum() / count

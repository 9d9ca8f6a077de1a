"""The training losses: CenterNet's penalty-reduced focal loss with L1 box terms, and the
coordinate net's masked L1 with a mask cross-entropy (GDR-Net's geometric losses)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F


def detector_loss(heat_logits: Tensor, size: Tensor, offset: Tensor, target: dict[str, Tensor]) -> Tensor:
    """Focal loss on the heatmaps (alpha 2, beta 4) + L1 on log box size and centre offset at the
    object centres, each normalised by the number of objects."""
    heat = target["heat"]
    pos = (heat >= 1.0).to(heat_logits.dtype)
    log_p, log_not_p = F.logsigmoid(heat_logits), F.logsigmoid(-heat_logits)
    p = log_p.exp()
    focal = -(pos * (1 - p) ** 2 * log_p + (1 - pos) * (1 - heat) ** 4 * p ** 2 * log_not_p).sum()
    weight = target["weight"]
    n = weight.sum().clamp(min=1.0)
    box = (weight * ((size - target["size"]).abs() + (offset - target["offset"]).abs())).sum()
    return (focal + box) / n


def pose_loss(coords: Tensor, mask_logits: Tensor, target: dict[str, Tensor]) -> Tensor:
    """L1 between predicted and true coordinates on the visible pixels + binary cross-entropy of the mask."""
    mask = target["masks"]
    l1 = (mask * (coords - target["coords"]).abs()).sum() / (3.0 * mask.sum()).clamp(min=1.0)
    return l1 + F.binary_cross_entropy_with_logits(mask_logits, mask)

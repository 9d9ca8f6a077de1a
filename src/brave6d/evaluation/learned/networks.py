"""The two networks of the learned estimator, small enough to train on a 2-core CPU.

- :class:`Detector`: CenterNet-style ("objects as points"): one heatmap per object class at a
  quarter of the image's resolution, plus the box size and the sub-cell offset of each centre. No
  anchors and no NMS operator (a 3x3 max-pool keeps the peaks), so it needs nothing beyond torch.
- :class:`CoordinateNet`: GDR-Net's geometric half on a zoomed-in crop: per pixel, the object's
  (normalised) model coordinates and a visible-mask logit, one head per class; a robust PnP turns
  them into a pose (:mod:`brave6d.evaluation.learned.inference`).

torchvision's detection models were the other candidate; on PyPI its wheel is built against
CUDA's torch (it imports ``libc10_cuda``) and does not load beside the CPU wheel this project
installs, and a ResNet-FPN detector trains at seconds per step on two cores (docs/GUIDE.md).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

#: Output stride of the detector's maps (pixels of the input image per cell).
DETECTOR_STRIDE = 4
#: Output stride of the coordinate net (crop pixels per output pixel).
COORD_STRIDE = 4


def _block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True),
                         nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class _Encoder(nn.Module):
    """Four stages, each halving the resolution: features at strides 2, 4, 8, 16."""

    def __init__(self, width: int) -> None:
        super().__init__()
        chans = (width, 2 * width, 3 * width, 4 * width)
        self.stages = nn.ModuleList([_block(3, chans[0], 2), _block(chans[0], chans[1], 2),
                                     _block(chans[1], chans[2], 2), _block(chans[2], chans[3], 2)])
        self.channels = chans

    def forward(self, x: Tensor) -> list[Tensor]:
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        return feats


class _Decoder(nn.Module):
    """Upsample from stride 16 back to ``out_level`` (0: stride 2, 1: stride 4), adding skips."""

    def __init__(self, chans: tuple[int, ...], out_level: int) -> None:
        super().__init__()
        self.out_level = out_level
        self.lateral = nn.ModuleList([nn.Conv2d(c, chans[out_level + 1], 1) for c in chans[out_level:]])
        self.smooth = nn.ModuleList([_block(chans[out_level + 1], chans[out_level + 1]) for _ in chans[out_level:-1]])
        self.channels = chans[out_level + 1]

    def forward(self, feats: list[Tensor]) -> Tensor:
        feats = feats[self.out_level:]
        x = self.lateral[-1](feats[-1])
        for i in range(len(feats) - 2, -1, -1):
            x = F.interpolate(x, size=feats[i].shape[-2:], mode="bilinear", align_corners=False)
            x = self.smooth[i](x + self.lateral[i](feats[i]))
        return x


class Detector(nn.Module):
    """CenterNet-style detector: ``forward(images)`` -> heatmap logits (B, C, H/4, W/4), box size
    (B, 2, ...) in input pixels (log-space), centre offset (B, 2, ...) in cells."""

    def __init__(self, classes: int, width: int = 16) -> None:
        super().__init__()
        self.encoder = _Encoder(width)
        self.decoder = _Decoder(self.encoder.channels, 1)
        c = self.decoder.channels
        self.heads = nn.Conv2d(c, classes + 4, 1)  # heatmap logits, log box size (2), centre offset (2)
        self.classes = classes
        with torch.no_grad():
            self.heads.bias[:classes].fill_(-4.6)  # CenterNet's prior: sigmoid(-4.6) = 0.01

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        out = self.heads(self.decoder(self.encoder(images)))
        c = self.classes
        return out[:, :c], out[:, c:c + 2], out[:, c + 2:]


class CoordinateNet(nn.Module):
    """Per-pixel model coordinates and visible mask on a crop: ``forward(crops, class_index)`` ->
    (B, 3, S, S) coordinates in [-1, 1] (tanh; the model's centre and radius normalise them) and
    (B, 1, S, S) mask logits, at a quarter of the crop's resolution, of the class asked for."""

    def __init__(self, classes: int, width: int = 24) -> None:
        super().__init__()
        self.classes = classes
        self.encoder = _Encoder(width)
        self.decoder = _Decoder(self.encoder.channels, 1)
        c = self.decoder.channels
        self.head = nn.Sequential(nn.Conv2d(c, c, 3, 1, 1), nn.ReLU(inplace=True), nn.Conv2d(c, 4 * classes, 1))

    def forward(self, crops: Tensor, class_index: Tensor) -> tuple[Tensor, Tensor]:
        out = self.head(self.decoder(self.encoder(crops)))
        b, _, h, w = out.shape
        out = out.view(b, self.classes, 4, h, w)[torch.arange(b), class_index]
        return torch.tanh(out[:, :3]), out[:, 3:]

"""``resolve_device``: the one place that turns ``auto``/``cpu``/``cuda`` into a torch device.

Training, the render server and the report all choose their device through it, so ``auto``
means the same everywhere and ``cuda`` without a GPU fails with the same message.
"""

from __future__ import annotations

import torch

from brave6d.core.errors import BraveError


def resolve_device(device: str | torch.device) -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is an error.

    A ``torch.device`` is returned as it is (a caller that resolved once passes the result on).
    """
    if isinstance(device, torch.device):
        return device
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise BraveError("--device cuda: no CUDA GPU is available here (use --device cpu or auto)")
    if device not in ("cpu", "cuda"):
        raise BraveError(f"--device must be auto, cpu or cuda, got {device!r}")
    return torch.device(device)

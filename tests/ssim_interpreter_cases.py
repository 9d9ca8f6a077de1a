"""Run the device SSIM's Triton kernels through Triton's interpreter against the reference SSIM.

Not a test module: ``tests/test_ssim_device.py`` runs it in a subprocess (the interpreter is chosen
when triton is first imported, ``TRITON_INTERPRET=1``).

    TRITON_INTERPRET=1 python tests/ssim_interpreter_cases.py OUT.json

Per case: both SSIM values, the largest gradient difference and the largest gradient, and whether
everything was finite; named hard cases first, then hypothesis-drawn image pairs.
"""

from __future__ import annotations

import sys
from typing import Any

import torch
from hypothesis import given
from hypothesis import strategies as st
from interpreter_common import FEW_DRAWS, write_report

from brave6d.training.losses import ssim
from brave6d.training.ssim_device import device_ssim


def compare(render: torch.Tensor, target: torch.Tensor) -> dict[str, Any]:
    out = {}
    for name, fn in (("device", device_ssim), ("reference", ssim)):
        x = render.clone().requires_grad_(True)
        value = fn(x, target)
        value.backward()
        out[name] = (float(value.detach()), x.grad)
    (v_dev, g_dev), (v_ref, g_ref) = out["device"], out["reference"]
    return {"shape": list(render.shape), "device": v_dev, "reference": v_ref,
            "grad_max_diff": float((g_dev - g_ref).abs().max()), "grad_max": float(g_ref.abs().max()),
            "finite": bool(torch.isfinite(g_dev).all()) and v_dev == v_dev}


def named() -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    rand = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    return {
        "random-3ch": (rand(21, 37, 3), rand(21, 37, 3)),
        "one-channel": (rand(18, 9, 1), rand(18, 9, 1)),
        "both-constant": (torch.full((12, 14, 3), 0.5), torch.full((12, 14, 3), 0.5)),
        "black-vs-white": (torch.zeros(10, 10, 3), torch.ones(10, 10, 3)),
        "constant-target": (rand(9, 13, 3), torch.full((9, 13, 3), 0.25)),
        "one-pixel": (rand(1, 1, 3), rand(1, 1, 3)),
        "below-the-window": (rand(4, 6, 3), rand(4, 6, 3)),
        "out-of-range-render": (rand(16, 20, 3) * 2 - 0.5, rand(16, 20, 3)),
        "non-contiguous": (rand(3, 15, 11).permute(1, 2, 0), rand(15, 11, 3)),
    }


def main(out_path: str) -> int:
    results: dict[str, Any] = {name: compare(a, b) for name, (a, b) in named().items()}
    drawn: list[dict[str, Any]] = []

    @FEW_DRAWS
    @given(seed=st.integers(0, 2**20), h=st.integers(1, 24), w=st.integers(1, 24), c=st.sampled_from([1, 3]),
           same=st.booleans())
    def pair(seed: int, h: int, w: int, c: int, same: bool) -> None:
        g = torch.Generator().manual_seed(seed)
        a = torch.rand(h, w, c, generator=g)
        b = a.clone() if same else torch.rand(h, w, c, generator=g)
        drawn.append({"seed": seed, **compare(a, b)})

    return write_report(out_path, results, pair, drawn)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))

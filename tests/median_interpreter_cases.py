"""Run the median-depth Triton kernel through Triton's interpreter against the CPU rasterizer.

Not a test module: ``tests/test_median_depth_gpu.py`` runs it in a subprocess, since Triton's
interpreter mode is fixed when triton is first imported (``TRITON_INTERPRET=1``) and must not leak
into the test process (on a GPU machine that process compiles the same kernel for the device).

    TRITON_INTERPRET=1 python tests/median_interpreter_cases.py OUT.json

For each case (named hard cases, then hypothesis-drawn scenes) it renders with the CPU backend
(``median_depth=True``), builds gsplat's tile lists from the CPU projections
(:func:`tile_intersections`), runs the kernel, and writes per case: pixels, pixels with a median,
mismatches, and how many of those are ambiguous (the float64 walk of that pixel puts a decision
within 1e-5 of a threshold: transmittance 0.5, alpha 1/255, sigma 0).
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from interpreter_common import FEW_DRAWS, write_report

from brave6d.training.rasterizer import rasterize
from brave6d.training.rasterizer.constants import ALPHA_MAX, ALPHA_THRESHOLD, TILE_SIZE
from brave6d.training.rasterizer.median_depth import median_depth, tile_intersections

AMBIGUITY = 1e-5


def scene(seed: int, n: int, n_cams: int, width: int, height: int, opacity: tuple[float, float],
          scale_px: tuple[float, float], spread: float = 1.0, z: tuple[float, float] = (2.0, 5.0)
          ) -> dict[str, Any]:
    """Gaussians in front of ``n_cams`` cameras side by side, screen sigmas in ``scale_px``."""
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    depth = z[0] + (z[1] - z[0]) * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) - 0.5) * spread * width / f * depth
    y = (torch.rand(n, generator=g) - 0.5) * spread * height / f * depth
    sig = scale_px[0] * (scale_px[1] / scale_px[0]) ** torch.rand(n, 3, generator=g)
    viewmats = torch.eye(4).repeat(n_cams, 1, 1)
    viewmats[:, 0, 3] = torch.linspace(-0.1, 0.1, n_cams)
    k = torch.tensor([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return {
        "means": torch.stack([x, y, depth], -1), "quats": torch.randn(n, 4, generator=g),
        "scales": sig * depth[:, None] / f,
        "opacities": opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g),
        "colors": torch.rand(n, 3, generator=g), "viewmats": viewmats,
        "Ks": k.repeat(n_cams, 1, 1), "width": width, "height": height,
    }


def _ambiguous(info: dict[str, Any], offsets: np.ndarray, ids: np.ndarray, cam: int, y: int, x: int,
               tiles_w: int) -> bool:
    """Walk one pixel in float64: is any decision up to its 0.5 crossing within AMBIGUITY?"""
    m2 = info["means2d"].detach().double().reshape(-1, 2).numpy()
    con = info["conics"].detach().double().reshape(-1, 3).numpy()
    opa = info["opacities"].detach().double().reshape(-1).numpy()
    tile = (cam * offsets.shape[1] + y // TILE_SIZE) * tiles_w + x // TILE_SIZE
    flat = offsets.reshape(-1)
    end = flat[tile + 1] if tile + 1 < flat.size else ids.size
    trans = 1.0
    for g in ids[flat[tile]:end]:
        dx, dy = m2[g, 0] - (x + 0.5), m2[g, 1] - (y + 0.5)
        sigma = 0.5 * (con[g, 0] * dx * dx + con[g, 2] * dy * dy) + con[g, 1] * dx * dy
        alpha = min(ALPHA_MAX, opa[g] * math.exp(-sigma))
        if abs(sigma) < AMBIGUITY or abs(alpha - ALPHA_THRESHOLD) < AMBIGUITY:
            return True
        if sigma < 0 or alpha < ALPHA_THRESHOLD:
            continue
        trans *= 1.0 - alpha
        if abs(trans - 0.5) < AMBIGUITY:
            return True
        if trans <= 0.5:
            return False
    return False


def compare(case: dict[str, Any], antialiased: bool = False) -> dict[str, Any]:
    """CPU rasterizer's median vs the Triton kernel's on the same projections."""
    w, h = case["width"], case["height"]
    _, _, _, info = rasterize(case["means"], case["quats"], case["scales"], case["opacities"],
                              case["colors"], case["viewmats"], case["Ks"], w, h, backend="cpu",
                              median_depth=True, antialiased=antialiased)
    offsets, ids = tile_intersections(info["means2d"], info["radii"], info["depths"], w, h)
    ours = median_depth(info["means2d"], info["conics"], info["opacities"], info["depths"],
                        offsets, ids, w, h)
    ref = info["median_depth"]
    assert ours.shape == ref.shape, (ours.shape, ref.shape)
    finite = bool(torch.isfinite(ours).all())
    bad = ((ours - ref).abs() > 1e-5 * ref.abs().clamp(min=1e-6))[..., 0].nonzero().tolist()
    n_amb = sum(_ambiguous(info, offsets.numpy(), ids.numpy(), c, y, x, offsets.shape[2])
                for c, y, x in bad)
    return {"pixels": ref.numel(), "with_median": int((ref > 0).sum()), "finite": finite,
            "mismatches": len(bad), "ambiguous_mismatches": n_amb, "isects": int(ids.numel()),
            "median_values": sorted({round(float(v), 6) for v in ours.unique()})[:4]}


NAMED = {
    "random-classic": (dict(seed=0, n=150, n_cams=2, width=64, height=48, opacity=(0.1, 0.9),
                            scale_px=(0.7, 6.0)), False),
    "random-antialiased": (dict(seed=1, n=150, n_cams=2, width=64, height=48, opacity=(0.1, 0.9),
                                scale_px=(0.3, 6.0)), True),
    "odd-size-off-screen": (dict(seed=2, n=120, n_cams=1, width=37, height=29, opacity=(0.2, 0.9),
                                 scale_px=(0.7, 5.0), spread=3.0), False),
    "opaque-dense": (dict(seed=3, n=300, n_cams=1, width=48, height=32, opacity=(0.8, 1.0),
                          scale_px=(2.0, 8.0)), False),
    "many-cameras": (dict(seed=4, n=60, n_cams=5, width=32, height=32, opacity=(0.3, 0.9),
                          scale_px=(1.0, 6.0)), False),
    # every Gaussian behind the cameras: no Gaussian in the view, no tile list
    "empty-view": (dict(seed=5, n=40, n_cams=2, width=32, height=24, opacity=(0.5, 0.9),
                        scale_px=(1.0, 4.0), z=(-5.0, -2.0)), False),
    # faint Gaussians: most pixels never reach T <= 0.5 (median 0 there)
    "never-half": (dict(seed=6, n=20, n_cams=1, width=48, height=32, opacity=(0.02, 0.08),
                        scale_px=(2.0, 6.0)), False),
    # N = 1, one Gaussian covering the whole image with opacity 0.95: its depth everywhere
    "one-covering": (dict(seed=7, n=1, n_cams=1, width=40, height=30, opacity=(0.95, 0.95),
                          scale_px=(400.0, 400.0), spread=0.0), False),
    # N = 1 far below a pixel (sigma 1e-3 px)
    "one-tiny": (dict(seed=8, n=1, n_cams=1, width=16, height=16, opacity=(0.99, 0.99),
                      scale_px=(1e-3, 1e-3), spread=0.0), True),
}


def main(out_path: str) -> int:
    results: dict[str, Any] = {}
    for name, (kwargs, aa) in NAMED.items():
        results[name] = compare(scene(**kwargs), antialiased=aa)

    drawn: list[dict[str, Any]] = []

    @settings(FEW_DRAWS, max_examples=8)
    @given(seed=st.integers(0, 2**20), n=st.integers(1, 80), width=st.integers(1, 40),
           height=st.integers(1, 40), lo=st.floats(0.01, 1.0), scale=st.floats(0.05, 30.0),
           aa=st.booleans())
    def drawn_scene(seed: int, n: int, width: int, height: int, lo: float, scale: float, aa: bool
                    ) -> None:
        case = scene(seed, n, 1, width, height, (lo, min(1.0, lo + 0.5)), (scale, scale * 3))
        drawn.append({"seed": seed, "n": n, "size": [width, height], **compare(case, aa)})

    return write_report(out_path, results, drawn_scene, drawn)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))

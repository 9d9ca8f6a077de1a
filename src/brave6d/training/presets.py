"""Training presets: the hyperparameters of one training run, as a typed, frozen dataclass.

``default`` follows the Inria reference (30k steps, learning rates, densification schedule;
see docs/ARCHITECTURE.md). ``quality`` trains longer (50k steps, densifying until 25k). ``fast`` is
tuned for the CPU demo (2 cores, no GPU) to reach a given holdout PSNR in the least time: half-resolution
images (320x200 for the demo), 2000 steps of which the first 600 on 2x2-averaged images
(coarse-to-fine), densification from step 100 to 1200 every 50 steps without opacity reset, at most
100k Gaussians, SH degree 2, learning rates raised for the short run and, from step 600, annealed to a
tenth (all but the positions, which decay as Inria's), and a 14-minute budget.
``benchmarks/time_to_quality.py`` compares it with any other configuration, interleaved on one machine.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

from brave6d.core.errors import BraveError


@dataclass(frozen=True)
class Preset:
    """Everything that shapes a training run (all steps count optimiser iterations)."""

    name: str
    steps: int = 30_000
    downscale: int = 1  # images are resampled to 1/downscale of the undistorted resolution
    time_budget_s: float | None = None  # stop (and evaluate) when training has run this long
    seed: int = 0
    # loss
    ssim_lambda: float = 0.2
    # spherical harmonics: degree +1 every `sh_degree_interval` steps up to `sh_degree`
    sh_degree: int = 3
    sh_degree_interval: int = 1000
    # Adam learning rates (Inria); means: times the scene extent, exponential decay init -> final
    means_lr_init: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20.0
    opacities_lr: float = 5e-2
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    adam_eps: float = 1e-15
    # initialisation
    init_opacity: float = 0.1
    init_scale: float = 1.0  # multiplies the mean 3-nearest-neighbour distance
    max_init_points: int = 300_000
    # densification (gsplat DefaultStrategy names; Inria values)
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    grow_grad2d: float = 2e-4
    grow_scale3d: float = 0.01
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1
    max_gaussians: int | None = None  # growth is limited to the highest gradients beyond this
    # coarse-to-fine: the first `coarse_steps` steps train on 2x2-averaged images (half width and
    # height, a quarter of the pixels per step); 0: every step at the training resolution
    coarse_steps: int = 0
    # annealing: the learning rates of quats, scales, opacities and SH fall log-linearly from their
    # value at `lr_decay_start` to `lr_decay_final` times it at the last step (1.0, or a start at or
    # after the last step: constant, as Inria)
    lr_decay_final: float = 1.0
    lr_decay_start: int = 0
    # bookkeeping
    checkpoint_every: int = 5000
    keep_checkpoints: int = 2
    curve_every: int = 100  # record (time, train PSNR, #Gaussians) for the training curves
    eval_every: int = 0  # holdout evaluation during training (0: only at the end)

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise BraveError(f"preset {self.name}: steps must be >= 1, got {self.steps}")
        if self.downscale < 1:
            raise BraveError(f"preset {self.name}: downscale must be >= 1, got {self.downscale}")
        if not 0 <= self.sh_degree <= 3:
            raise BraveError(f"preset {self.name}: sh_degree must be in 0..3, got {self.sh_degree}")
        if not 0.0 <= self.ssim_lambda <= 1.0:
            raise BraveError(f"preset {self.name}: ssim_lambda must be in [0, 1], got {self.ssim_lambda}")
        if not 0 <= self.coarse_steps <= self.steps:
            raise BraveError(f"preset {self.name}: coarse_steps must be in 0..steps ({self.steps}), got {self.coarse_steps}")
        if not (math.isfinite(self.lr_decay_final) and 0.0 < self.lr_decay_final <= 1.0):
            raise BraveError(f"preset {self.name}: lr_decay_final must be in (0, 1], got {self.lr_decay_final}")
        if self.lr_decay_start < 0:  # at or after the last step: no annealing
            raise BraveError(f"preset {self.name}: lr_decay_start must be >= 0, got {self.lr_decay_start}")
        if self.checkpoint_every < 1 or self.keep_checkpoints < 1:
            raise BraveError(f"preset {self.name}: checkpoint_every and keep_checkpoints must be >= 1")

    def with_overrides(self, **changes: Any) -> Preset:
        """A copy with some fields replaced (``None`` values are ignored)."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})

    def with_steps(self, steps: int) -> Preset:
        """A copy for a run of ``steps`` steps: every step-based schedule scales with it."""
        if steps == self.steps:
            return self
        f = steps / self.steps

        def sc(v: int) -> int:
            return max(1, round(v * f))

        return replace(
            self, steps=steps, sh_degree_interval=sc(self.sh_degree_interval),
            refine_start=sc(self.refine_start), refine_stop=sc(self.refine_stop),
            refine_every=sc(self.refine_every), reset_every=sc(self.reset_every),
            checkpoint_every=sc(self.checkpoint_every), curve_every=sc(self.curve_every),
            eval_every=sc(self.eval_every) if self.eval_every else 0,
            coarse_steps=min(steps, round(self.coarse_steps * f)),
            lr_decay_start=min(steps, round(self.lr_decay_start * f)),
        )

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


DEFAULT = Preset(name="default")

QUALITY = Preset(
    name="quality", steps=50_000, refine_stop=25_000, checkpoint_every=5000,
)

FAST = Preset(
    name="fast",
    steps=2000,
    downscale=2,
    time_budget_s=14 * 60.0,
    sh_degree=2,
    sh_degree_interval=400,
    # learning rates for a short run (tuned on the demo capture, issue 22): colours 5x, scales 3x,
    # positions 3x Inria's, the positions decaying to 5e-6 (x extent) instead of 1.6e-6
    sh0_lr=0.012,
    shN_lr=0.0006,
    scales_lr=0.015,
    means_lr_init=5e-4,
    means_lr_final=5e-6,
    coarse_steps=600,  # the first 600 steps on 2x2-averaged images
    lr_decay_final=0.1,  # from the first full-resolution step, all but the positions' rates fall to 1/10
    lr_decay_start=600,
    refine_start=100,
    refine_stop=1200,
    refine_every=50,
    reset_every=1_000_000,  # no opacity reset: too few steps remain to recover from one
    grow_grad2d=2e-4,
    max_gaussians=100_000,
    max_init_points=60_000,
    checkpoint_every=500,
    curve_every=20,
)

PRESETS: dict[str, Preset] = {p.name: p for p in (FAST, DEFAULT, QUALITY)}

#: ``fast`` before issue 22 (3000 steps at full resolution, Inria's learning rates, 150k Gaussians),
#: kept for ``benchmarks/time_to_quality.py`` (``--a old=fast-3000``) and for reproducing older runs.
FAST_3000 = Preset(
    name="fast-3000",
    steps=3000,
    downscale=2,
    time_budget_s=14 * 60.0,
    sh_degree=2,
    sh_degree_interval=600,
    refine_start=300,
    refine_stop=1800,
    refine_every=150,
    reset_every=1_000_000,
    grow_grad2d=2e-4,
    max_gaussians=150_000,
    max_init_points=60_000,
    checkpoint_every=750,
    curve_every=30,
)
#: ``fast`` before the learning-rate annealing (the same schedule with constant rates but the positions'),
#: for ``--a old=fast-2000``.
FAST_2000 = replace(FAST, name="fast-2000", lr_decay_final=1.0, lr_decay_start=0)
BENCHMARK_PRESETS: dict[str, Preset] = {**PRESETS, FAST_3000.name: FAST_3000, FAST_2000.name: FAST_2000}


def get_preset(name: str, known: dict[str, Preset] = PRESETS) -> Preset:
    """The preset called ``name`` (``fast``, ``default`` or ``quality``; benchmarks also pass
    :data:`BENCHMARK_PRESETS`, which adds ``fast-3000`` and ``fast-2000``)."""
    try:
        return known[name]
    except KeyError:
        raise BraveError(f"unknown preset {name!r}; choose one of {sorted(known)}") from None

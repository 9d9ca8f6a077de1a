"""Densification (clone, split, prune, opacity reset): gsplat's ``DefaultStrategy``, fixed.

gsplat 1.5.3's ``DefaultStrategy.step_post_backward`` guards the opacity reset with
``step % reset_every == 0 & step > 0``; Python parses that as the chained comparison
``(step % reset_every == 0) and (0 > 0)`` (``&`` binds tighter than ``==``), so opacities are
never reset. :class:`DensifyStrategy` performs the reset itself at the Inria steps (every
``reset_every`` steps while refining), which is idempotent, so it stays correct with a fixed
gsplat as well. It also adds an optional cap on the number of Gaussians (CPU presets): when a
refinement would grow past ``max_gaussians``, only the Gaussians with the highest image-plane
gradients grow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import reset_opa

from training.presets import Preset


@dataclass
class DensifyStrategy(DefaultStrategy):
    """``DefaultStrategy`` with a working opacity reset and an optional growth cap."""

    max_gaussians: int | None = None

    def step_post_backward(self, params: Any, optimizers: dict[str, torch.optim.Optimizer], state: dict[str, Any],
                           step: int, info: dict[str, Any], packed: bool = False) -> None:
        super().step_post_backward(params, optimizers, state, step, info, packed=packed)
        if self.should_reset_opacity(step):
            reset_opa(params=params, optimizers=optimizers, state=state, value=self.prune_opa * 2.0)

    def should_reset_opacity(self, step: int) -> bool:
        """Inria: every ``reset_every`` steps after the first, while densifying."""
        return 0 < step < self.refine_stop_iter and step % self.reset_every == 0

    @torch.no_grad()
    def _grow_gs(self, params: Any, optimizers: dict[str, torch.optim.Optimizer], state: dict[str, Any],
                 step: int) -> tuple[int, int]:
        if self.max_gaussians is None:
            return super()._grow_gs(params, optimizers, state, step)
        room = self.max_gaussians - len(params["means"])
        grads = state["grad2d"] / state["count"].clamp_min(1)
        candidates = grads > self.grow_grad2d
        threshold = self.grow_grad2d
        if room <= 0:
            return 0, 0
        if int(candidates.sum()) > room:
            # each duplicate or split adds one Gaussian: keep the `room` highest gradients
            threshold = float(torch.topk(grads[candidates], room + 1).values[-1])
        saved = self.grow_grad2d
        self.grow_grad2d = threshold
        try:
            return super()._grow_gs(params, optimizers, state, step)
        finally:
            self.grow_grad2d = saved


def make_strategy(preset: Preset) -> DensifyStrategy:
    """The densification strategy of a preset (gsplat parameter names)."""
    return DensifyStrategy(
        prune_opa=preset.prune_opa,
        grow_grad2d=preset.grow_grad2d,
        grow_scale3d=preset.grow_scale3d,
        prune_scale3d=preset.prune_scale3d,
        refine_start_iter=preset.refine_start,
        refine_stop_iter=preset.refine_stop,
        reset_every=preset.reset_every,
        refine_every=preset.refine_every,
        max_gaussians=preset.max_gaussians,
    )

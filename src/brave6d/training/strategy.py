"""Densification (clone, split, prune, opacity reset) of the Gaussian model, in plain torch.

The rules are gsplat 1.5.3's ``DefaultStrategy`` (Apache-2.0) with the options the presets use
(no AbsGS, no screen-size refinement, no pause after a reset), written out here so that training
needs gsplat only for the CUDA rasterizer: a CPU-only install trains with the same numbers.
Two differences from gsplat 1.5.3, both on purpose:

* the opacity reset happens (gsplat's guard ``step % reset_every == 0 & step > 0`` parses as
  ``(step % reset_every == 0) and (0 > 0)``, so it never fires): every ``reset_every`` steps
  while refining, as Inria does;
* an optional cap on the number of Gaussians (CPU presets): when a refinement would grow past
  ``max_gaussians``, only the Gaussians with the highest image-plane gradients grow.

The options are the preset's :class:`~brave6d.training.presets.Densification` (gsplat's names, but
``refine_start`` / ``refine_stop`` for gsplat's ``refine_start_iter`` / ``refine_stop_iter``).
Parameters and optimiser state are edited in place through ``params`` (a ParameterDict with
the gsplat names) and one single-group optimiser per parameter; ``state`` holds the running
gradient statistics (``grad2d``, ``count``) and ``scene_scale``.
"""

from __future__ import annotations

from collections.abc import Callable, MutableMapping
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from brave6d.training.presets import Densification

Params = MutableMapping[str, torch.nn.Parameter]
Optimizers = dict[str, torch.optim.Optimizer]
REQUIRED_PARAMS = ("means", "scales", "quats", "opacities")


@dataclass
class DensifyStrategy:
    """Inria's adaptive density control (gsplat's rules), with a working opacity reset; ``options`` is
    the preset's own :class:`~brave6d.training.presets.Densification` (``preset.densification``)."""

    options: Densification = field(default_factory=Densification)

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """Running statistics, allocated on the first step (on the gradients' device)."""
        return {"grad2d": None, "count": None, "scene_scale": scene_scale}

    def check_sanity(self, params: Params, optimizers: Optimizers) -> None:
        """Refuse parameter/optimiser layouts the in-place edits below would corrupt."""
        trainable = {name for name, p in params.items() if p.requires_grad}
        if trainable != set(optimizers):
            raise ValueError(f"trainable parameters {sorted(trainable)} and optimizers {sorted(optimizers)} "
                             "must have the same keys")
        for name, opt in optimizers.items():
            if len(opt.param_groups) != 1:
                raise ValueError(f"optimizer {name!r} must have exactly one param_group, "
                                 f"got {len(opt.param_groups)}")
        missing = [k for k in REQUIRED_PARAMS if k not in params]
        if missing:
            raise ValueError(f"densification needs the parameters {missing}")

    def step_pre_backward(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int,
                          info: dict[str, Any]) -> None:
        """Before ``loss.backward()``: keep the gradient of the 2D means (the growth criterion)."""
        info["means2d"].retain_grad()

    def step_post_backward(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int,
                           info: dict[str, Any], packed: bool = False) -> None:
        """After the optimiser step: accumulate gradients; grow, prune and reset on schedule."""
        if packed:
            raise ValueError("DensifyStrategy needs the rasterizer's non-packed info (packed=False)")
        if step >= self.options.refine_stop:
            return
        self._update_state(params, state, info)
        if step > self.options.refine_start and step % self.options.refine_every == 0:
            self._grow_gs(params, optimizers, state)
            self._prune_gs(params, optimizers, state, step)
            state["grad2d"].zero_()
            state["count"].zero_()
            torch.cuda.empty_cache()
        if self.should_reset_opacity(step):
            reset_opacities(params, optimizers, value=self.options.prune_opa * 2.0)

    def should_reset_opacity(self, step: int) -> bool:
        """Inria: every ``reset_every`` steps after the first, while densifying."""
        return 0 < step < self.options.refine_stop and step % self.options.reset_every == 0

    def _update_state(self, params: Params, state: dict[str, Any], info: dict[str, Any]) -> None:
        # gradients of the 2D means in [-1, 1] screen units, summed over the cameras that see each Gaussian
        grads = info["means2d"].grad.clone()
        grads[..., 0] *= info["width"] / 2.0 * info["n_cameras"]
        grads[..., 1] *= info["height"] / 2.0 * info["n_cameras"]
        n_gaussians = len(next(iter(params.values())))
        if state["grad2d"] is None:
            state["grad2d"] = torch.zeros(n_gaussians, device=grads.device)
        if state["count"] is None:
            state["count"] = torch.zeros(n_gaussians, device=grads.device)
        seen = (info["radii"] > 0.0).all(dim=-1)  # [C, N]
        if grads.device.type != "cpu":  # masked sums: no nonzero() and boolean gather waiting for the GPU
            state["grad2d"] += torch.where(seen, grads.norm(dim=-1), 0.0).sum(dim=0)
            state["count"] += seen.sum(dim=0, dtype=torch.float32)
            return
        ids = torch.where(seen)[1]
        state["grad2d"].index_add_(0, ids, grads[seen].norm(dim=-1))
        state["count"].index_add_(0, ids, torch.ones_like(ids, dtype=torch.float32))

    @torch.no_grad()
    def _grow_gs(self, params: Params, optimizers: Optimizers, state: dict[str, Any]) -> tuple[int, int]:
        """Duplicate small and split large Gaussians whose mean 2D gradient is high."""
        opts = self.options
        grads = state["grad2d"] / state["count"].clamp_min(1)
        threshold = opts.grow_grad2d
        if opts.max_gaussians is not None:
            room = opts.max_gaussians - len(params["means"])
            if room <= 0:
                return 0, 0
            candidates = grads > opts.grow_grad2d
            if int(candidates.sum()) > room:
                # each duplicate or split adds one Gaussian: keep the `room` highest gradients
                threshold = float(torch.topk(grads[candidates], room + 1).values[-1])
        is_grad_high = grads > threshold
        is_small = torch.exp(params["scales"]).max(dim=-1).values <= opts.grow_scale3d * state["scene_scale"]
        is_dupli = is_grad_high & is_small
        is_split = is_grad_high & ~is_small
        n_dupli = int(is_dupli.sum().item())
        n_split = int(is_split.sum().item())
        if n_dupli > 0:
            duplicate(params, optimizers, state, is_dupli)
        # the copies just appended are not split
        is_split = torch.cat([is_split, torch.zeros(n_dupli, dtype=torch.bool, device=grads.device)])
        if n_split > 0:
            split(params, optimizers, state, is_split)
        return n_dupli, n_split

    @torch.no_grad()
    def _prune_gs(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int) -> int:
        """Remove transparent Gaussians and, after the first reset period, world-space giants."""
        opts = self.options
        is_prune = torch.sigmoid(params["opacities"].flatten()) < opts.prune_opa
        if step > opts.reset_every:
            is_prune |= torch.exp(params["scales"]).max(dim=-1).values > opts.prune_scale3d * state["scene_scale"]
        n_prune = int(is_prune.sum().item())
        if n_prune > 0:
            remove(params, optimizers, state, is_prune)
        return n_prune


# ---------------------------------------------------------------- in-place edits (gsplat's ops)
@torch.no_grad()
def duplicate(params: Params, optimizers: Optimizers, state: dict[str, Any], mask: Tensor) -> None:
    """Append a copy of each masked Gaussian (fresh optimiser moments)."""
    sel = torch.where(mask)[0]
    _replace_params(params, optimizers,
                    lambda name, p: torch.cat([p, p[sel]]),
                    lambda v: torch.cat([v, torch.zeros((len(sel), *v.shape[1:]), device=mask.device)]))
    _edit_running_state(state, lambda v: torch.cat((v, v[sel])))


@torch.no_grad()
def split(params: Params, optimizers: Optimizers, state: dict[str, Any], mask: Tensor) -> None:
    """Replace each masked Gaussian by two, drawn from it, 1.6 times smaller (moved to the end)."""
    sel = torch.where(mask)[0]
    rest = torch.where(~mask)[0]
    scales = torch.exp(params["scales"][sel])
    rotmats = _quat_to_rotmat(F.normalize(params["quats"][sel], dim=-1))
    samples = torch.einsum("nij,nj,bnj->bni", rotmats, scales,
                           torch.randn(2, len(scales), 3, device=mask.device))  # [2, n, 3]

    def new_param(name: str, p: Tensor) -> Tensor:
        if name == "means":
            halves = (p[sel] + samples).reshape(-1, 3)
        elif name == "scales":
            halves = torch.log(scales / 1.6).repeat(2, 1)
        else:
            halves = p[sel].repeat([2] + [1] * (p.dim() - 1))
        return torch.cat([p[rest], halves])

    _replace_params(params, optimizers, new_param,
                    lambda v: torch.cat([v[rest], torch.zeros((2 * len(sel), *v.shape[1:]), device=mask.device)]))
    _edit_running_state(state, lambda v: torch.cat((v[rest], v[sel].repeat([2] + [1] * (v.dim() - 1)))))


@torch.no_grad()
def remove(params: Params, optimizers: Optimizers, state: dict[str, Any], mask: Tensor) -> None:
    """Drop the masked Gaussians."""
    keep = torch.where(~mask)[0]
    _replace_params(params, optimizers, lambda name, p: p[keep], lambda v: v[keep])
    _edit_running_state(state, lambda v: v[keep])


@torch.no_grad()
def reset_opacities(params: Params, optimizers: Optimizers, value: float) -> None:
    """Clamp every opacity to at most ``value`` (after the sigmoid); zero its optimiser moments."""
    ceiling = torch.logit(torch.tensor(value)).item()
    _replace_params(params, optimizers, lambda name, p: torch.clamp(p, max=ceiling), torch.zeros_like,
                    names=["opacities"])


def _replace_params(params: Params, optimizers: Optimizers, new_param: Callable[[str, Tensor], Tensor],
                    new_moment: Callable[[Tensor], Tensor], names: list[str] | None = None) -> None:
    """Swap each parameter for ``new_param(name, p)``, carrying its optimiser state along
    (every tensor state but ``step`` rewritten by ``new_moment``)."""
    for name in list(params) if names is None else names:
        old = params[name]
        new = torch.nn.Parameter(new_param(name, old), requires_grad=old.requires_grad)
        params[name] = new
        if name not in optimizers:
            if old.requires_grad:
                raise ValueError(f"parameter {name!r} is trainable but has no optimizer")
            continue
        optimizer = optimizers[name]
        for group in optimizer.param_groups:
            moments = optimizer.state.pop(old, {})  # no moments before the first optimiser step
            for key in moments:
                if key != "step":
                    moments[key] = new_moment(moments[key])
            group["params"] = [new]
            optimizer.state[new] = moments


def _edit_running_state(state: dict[str, Any], edit: Callable[[Tensor], Tensor]) -> None:
    for key, value in state.items():
        if isinstance(value, Tensor):
            state[key] = edit(value)


def _quat_to_rotmat(quats: Tensor) -> Tensor:
    """[n, 4] unit quaternions (w, x, y, z) -> [n, 3, 3] (gsplat's ``normalized_quat_to_rotmat``)."""
    w, x, y, z = torch.unbind(quats, dim=-1)
    mat = torch.stack([
        1 - 2 * (y**2 + z**2), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x**2 + z**2), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x**2 + y**2),
    ], dim=-1)
    return mat.reshape(quats.shape[:-1] + (3, 3))

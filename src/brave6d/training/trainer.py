"""The 3DGS training loop: one camera per step, Adam, densification, checkpoints, guards.

Every length is a multiple of the scene's extent (``data.scene_extent()``: the near plane, the
densification's size limits, the positions' learning rate and their Adam epsilon, the initial
scales' floor; :mod:`brave6d.training.scene_frame`), so the same scene in other units trains the
same; :func:`brave6d.training.train` goes further and trains in the scene's training frame (extent 1).

Per step (gsplat's ``simple_trainer`` order): render the next training view (views are drawn
without replacement, a new random order every epoch), loss
``(1 - lambda) * L1 + lambda * (1 - SSIM)`` (plus ``depth_lambda`` times the relative depth error
against the captured depth, :mod:`brave6d.training.depth_targets`, when the preset asks), backward, Adam step for every parameter, then the
densification strategy. The means' learning rate is Inria's (times the scene extent) with an
exponential decay over the run; the SH degree grows by one every ``schedule.sh_degree_interval`` steps.

Stability: NaN or inf in the loss or in a parameter stops training with :class:`TrainingDiverged`
naming the step; checkpoints are only written from finite states, so the last one stays good.
On a GPU the step is lean (``Trainer(lean=...)``): it never waits for the device; the same checks
become a flag on the device, read at each curve point, checkpoint and the run's end, that still
names the step where the NaN first appeared.
Checkpoints (every ``schedule.checkpoint_every`` steps, atomic) hold parameters, optimiser and strategy
state and every RNG, so that ``resume=True`` continues exactly where the run stopped: on the
CPU a resumed run ends with the same parameters as an uninterrupted one, and equal seeds give
equal results. They hold tensors and plain values (numbers, strings, lists, dicts) only and are
read with ``torch.load(weights_only=True)``: a checkpoint from elsewhere cannot run code, and
one that needs anything else to load is refused with an error naming it.

The time budget (``preset.time_budget_s``) is wall time from ``budget_started_at`` (``brave6d
train`` passes the start of the command, so loading and the initial points count; by default the
start of :meth:`Trainer.train`), checked before each step: evaluations and checkpoints during the
run count, the holdout evaluation and the writing after the last step do not. A resumed run is a new
command and gets the whole budget again.
"""

from __future__ import annotations

import logging
import math
import os
import pickle
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from brave6d.core.atomic import atomic_write
from brave6d.core.errors import BraveError, DataError
from brave6d.core.progress import progress_bar
from brave6d.training.views import TrainingData, image_tensor
from brave6d.training.device import resolve_device  # noqa: F401 - also importable from here
from brave6d.training.depth_targets import DepthTarget, depth_loss, load_depth_targets
from brave6d.training.losses import fill_invalid, photometric_loss, psnr, psnr_tensor
from brave6d.training.model import PARAM_NAMES, GaussianModel
from brave6d.training.presets import Preset
from brave6d.training.scene_frame import SceneFrame, near_far
from brave6d.training.strategy import DensifyStrategy

log = logging.getLogger(__name__)

#: 2: parameters in the run's frame, recorded with it (``frame``); version 1 (world units, no frame) still loads.
CHECKPOINT_VERSION = 2
_CKPT = re.compile(r"^ckpt_(\d{6,})\.pt$")


class TrainingDiverged(BraveError):
    """The loss or a parameter became NaN/inf; training stopped (the last checkpoint is kept)."""


class UnreadableCheckpoint(DataError):
    """A checkpoint file that is torn or not a checkpoint at all (an older one may still be good)."""


@dataclass
class TrainResult:
    """What a training run did."""

    steps: int
    train_seconds: float
    num_gaussians: int
    stopped_by: str  # "steps" | "time budget"
    curve: list[dict[str, float]] = field(default_factory=list)
    resumed_from: int | None = None
    checkpoints: list[str] = field(default_factory=list)
    train_cpu_seconds: float = 0.0  # process CPU time of the steps (wall time x busy threads)
    planned_steps: int = 0  # the preset's steps
    budget_s: float | None = None  # the time budget it ran under (None: none)
    budget_used_s: float = 0.0  # wall seconds counted against the budget when training stopped


def means_lr(step: int, preset: Preset, extent: float) -> float:
    """Inria's position learning rate at ``step``: log-linear from init to final, times the extent."""
    t = min(max(step / max(preset.steps, 1), 0.0), 1.0)
    rates = preset.learning_rates
    return extent * math.exp((1.0 - t) * math.log(rates.means_lr_init) + t * math.log(rates.means_lr_final))


def adam_epsilon(name: str, preset: Preset, extent: float) -> float:
    """Adam's epsilon for parameter ``name``: the preset's, divided by the extent for the positions (their
    gradients scale as 1 / extent; every other parameter is without units)."""
    return preset.learning_rates.adam_eps / (extent if name == "means" else 1.0)


def base_lrs(preset: Preset) -> dict[str, float]:
    """The learning rates of every parameter but the positions, before annealing."""
    rates = preset.learning_rates
    return {"quats": rates.quats_lr, "scales": rates.scales_lr, "opacities": rates.opacities_lr,
            "sh0": rates.sh0_lr, "shN": rates.shN_lr}


def other_lr_factor(step: int, preset: Preset) -> float:
    """Factor on the quats / scales / opacities / SH learning rates at ``step``: 1 until
    ``lr_decay_start``, then log-linear down to ``lr_decay_final`` at the last step (and after)."""
    rates = preset.learning_rates
    span = preset.steps - rates.lr_decay_start
    if rates.lr_decay_final == 1.0 or step <= rates.lr_decay_start or span <= 0:
        return 1.0
    t = min((step - rates.lr_decay_start) / span, 1.0)
    return math.exp(t * math.log(rates.lr_decay_final))


def sh_degree_at(step: int, preset: Preset, max_degree: int) -> int:
    return min(step // max(preset.schedule.sh_degree_interval, 1), max_degree)


class Trainer:
    """Trains ``model`` on ``data.train`` with ``preset``; writes checkpoints to ``checkpoint_dir``."""

    def __init__(
        self,
        data: TrainingData,
        model: GaussianModel,
        preset: Preset,
        checkpoint_dir: Path | None = None,
        device: torch.device | str = "cpu",
        show_progress: bool = True,
        step_callback: Callable[[Trainer, int], None] | None = None,
        eval_callback: Callable[[Trainer], float] | None = None,
        checkpoint_hook: Callable[[Trainer], None] | None = None,
        lean: bool | None = None,
        budget_started_at: float | None = None,
    ) -> None:
        """``lean`` (default: on a GPU, off on the CPU): the step never waits for the device. The
        cameras are checked once here, renders skip the rasterizer's per-call value checks, the
        depth loss is taken as masked sums, and a non-finite loss or parameter raises a flag on
        the device (with the first step it happened at) that is read at each curve point,
        checkpoint and the end of the run (TrainingDiverged then names that step); the step's
        figures stay tensors until then. Off, every step checks on the host (the CPU's path).
        ``budget_started_at``: the ``time.perf_counter()`` the time budget counts from (the module doc)."""
        self.data = data
        self.preset = preset
        self.device = torch.device(device)
        self.model = model
        if model.device != self.device:
            self.model = GaussianModel.from_tensors({k: v.detach() for k, v in model.params.items()},
                                                    model.sh_degree, self.device)
        self.checkpoint_dir = checkpoint_dir
        self.show_progress = show_progress
        self.step_callback = step_callback
        self.eval_callback = eval_callback
        self.checkpoint_hook = checkpoint_hook  # called after each checkpoint is written
        try:
            self.extent = data.scene_extent()  # every length below is a multiple of it
        except DataError as exc:
            raise DataError(f"training cameras: viewmats are not finite ({exc})") from None
        self.near_plane, self.far_plane = near_far(self.extent)
        self.budget_started_at = budget_started_at
        self.strategy = DensifyStrategy(preset.densification)
        self.strategy_state = self.strategy.initialize_state(scene_scale=self.extent)
        self.optimizers = self._make_optimizers()
        self.strategy.check_sanity(self.model.params, self.optimizers)
        torch.manual_seed(preset.seed)
        self.view_rng = torch.Generator().manual_seed(preset.seed)
        self.order: list[int] = []
        self.step = 0  # steps completed
        self.elapsed = 0.0  # training seconds so far (evaluation excluded)
        self.cpu_elapsed = 0.0  # process CPU seconds of those steps (all threads)
        self.curve: list[dict[str, float]] = []
        self.psnr_ema: float | None = None
        self.loss_ema: float | None = None
        self.last_checkpoint: Path | None = None
        # per-view tensors on the device
        cams = [torch.from_numpy(v.viewmat).float() for v in data.train]
        self.viewmats = torch.stack(cams).to(self.device)
        self.K = torch.from_numpy(data.camera.K).float().to(self.device)
        self.images = [torch.from_numpy(v.image).to(self.device) for v in data.train]
        self.valid = data.valid_tensor(self.device)
        self.lean = self.device.type != "cpu" if lean is None else bool(lean)
        self._bad_step = torch.full((), -1, dtype=torch.long, device=self.device)  # lean: first bad step
        self._bad_what = torch.zeros((), dtype=torch.long, device=self.device)  # 1 loss, 2 parameters
        if self.lean:
            self._check_cameras()
        self._coarse: CoarseLevel | None = None  # half-resolution copies, made when a coarse step first needs them
        self._depth_targets: list[DepthTarget | None] | None = None  # loaded when a depth step first needs them
        self._filter_means: Tensor | None = None  # the means Parameter the 3D filter was computed for
        self._filter_step = 0
        self.refresh_filter_3d()

    # ------------------------------------------------------------------ setup
    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        p = self.preset
        lrs = {"means": means_lr(0, p, self.extent), **base_lrs(p)}
        eps = {name: adam_epsilon(name, p, self.extent) for name in PARAM_NAMES}
        # fused Adam: the same update, one kernel per tensor (25x faster than the default on CPU)
        return {name: torch.optim.Adam([{"params": self.model.params[name], "lr": lrs[name], "name": name}],
                                       eps=eps[name], betas=(0.9, 0.999), fused=True)
                for name in PARAM_NAMES}

    def _next_view(self) -> int:
        if not self.order:
            self.order = torch.randperm(len(self.data.train), generator=self.view_rng).tolist()
        return self.order.pop()

    # ------------------------------------------------------------------ one step
    def render(self, viewmat: Tensor, sh_degree: int | None = None,
               level: CoarseLevel | None = None, validate: bool = True) -> tuple[Tensor, Tensor, dict[str, Any]]:
        """Render the current model into one camera: ``(rgb [H, W, 3], alpha [H, W, 1], info)``
        (at the half resolution of ``level`` when given)."""
        from brave6d.training.rasterizer import rasterize

        m = self.model
        d = m.sh_degree if sh_degree is None else sh_degree
        coeffs = m.sh_coeffs(d)
        cam = self.data.camera
        K, width, height = (self.K, cam.width, cam.height) if level is None else (level.K, level.width, level.height)
        scales, opacities = m.render_scales_opacities()
        colors, depth, alphas, info = rasterize(
            m.means, m.quats, scales, opacities, coeffs, viewmat[None], K[None],
            width, height, sh_degree=d, near_plane=self.near_plane, far_plane=self.far_plane,
            antialiased=m.antialiased, validate=validate)
        info["render_depth"] = depth[0]
        return colors[0], alphas[0], info

    def depth_targets(self) -> list[DepthTarget | None]:
        """Each training view's depth target at the training resolution (loaded once; None: no depth)."""
        if self._depth_targets is None:
            self._depth_targets = load_depth_targets(self.data, self.preset.loss.depth_edge_ratio, self.device)
        return self._depth_targets

    def refresh_filter_3d(self, force: bool = False) -> None:
        """With ``antialiasing: mip``, (re)compute the model's 3D filter from the training cameras
        (at the training resolution): when missing, after densification replaced the Gaussians,
        every ``filter_3d_every`` steps (the means move), or when ``force``d (the end of a run).
        Called wherever the Gaussians change (start, each step, a loaded checkpoint), so that every
        render of the model, the trainer's or a holdout evaluation's, draws a filter that fits it."""
        from brave6d.training.filter3d import compute_filter_3d

        aa = self.preset.antialias
        m = self.model
        if aa.antialiasing != "mip":
            m.filter_3d = None  # classic: no filter (not even one a loaded splat came with)
            return
        means = m.params["means"]
        stale = (m.filter_3d is None or m.filter_3d.shape[0] != m.num_gaussians
                 or self._filter_means is not means or self.step - self._filter_step >= aa.filter_3d_every)
        if force or stale:
            cam = self.data.camera
            m.filter_3d = compute_filter_3d(means, self.viewmats, self.K, cam.width, cam.height,
                                            aa.filter_3d_scale, near_plane=self.near_plane)
            self._filter_means, self._filter_step = means, self.step

    def coarse_level(self) -> CoarseLevel:
        """The half-resolution training images, intrinsics and valid mask (made once)."""
        if self._coarse is None:
            depths = None
            if self.preset.loss.depth_lambda > 0:
                ratio = self.preset.loss.depth_edge_ratio
                depths = [None if t is None else t.halved(ratio) for t in self.depth_targets()]
            self._coarse = CoarseLevel.of(self.images, self.K, self.valid, depths)
        return self._coarse

    def _check_cameras(self) -> None:
        """The lean step's one check of what every render would otherwise re-check."""
        bad = [name for name, t in (("viewmats", self.viewmats), ("K", self.K)) if not bool(torch.isfinite(t).all())]
        if bad:
            raise DataError(f"training cameras: {' and '.join(bad)} are not finite")
        if not bool((self.K[[0, 1], [0, 1]] > 0).all()):
            raise DataError(f"training cameras: the focal lengths must be positive, K = {self.K.tolist()}")

    def _flag(self, finite: Tensor, code: int) -> None:
        """Lean: remember (on the device) the first step whose loss or parameters were not finite."""
        first = (~finite) & (self._bad_step < 0)
        self._bad_step = torch.where(first, torch.full_like(self._bad_step, self.step), self._bad_step)
        self._bad_what = torch.where(first, torch.full_like(self._bad_what, code), self._bad_what)

    def raise_if_flagged(self) -> None:
        """Lean: read the device's flag (one wait) and stop as the host checks would have."""
        if not self.lean:
            return
        bad_step = int(self._bad_step)
        if bad_step < 0:
            return
        what = "the loss is not finite" if int(self._bad_what) == 1 else "parameters hold NaN/inf"
        bad = self.model.non_finite()
        if bad:
            what += f" (now in {', '.join(bad)})"
        self.step = bad_step  # _diverged names the step after the last good one
        raise self._diverged(f"{what}, first at this step (flagged on the device)")

    def _params_finite(self) -> Tensor:
        """A device bool: every parameter finite (a NaN/inf anywhere makes its sum non-finite: one
        cheap reduction per tensor; an overflowing sum is told apart by ``non_finite``)."""
        return torch.isfinite(torch.stack([p.detach().sum() for p in self.model.params.values()])).all()

    def _check_params(self, when: str) -> None:
        if bool(self._params_finite()):
            return
        bad = self.model.non_finite()  # exact check (empty when only the sum overflowed)
        if bad:
            raise self._diverged(f"parameter(s) {', '.join(bad)} hold NaN/inf {when}")

    def _diverged(self, what: str) -> TrainingDiverged:
        kept = (f"the last good checkpoint is {self.last_checkpoint} (step {_step_of(self.last_checkpoint)})"
                if self.last_checkpoint else "no checkpoint was written before")
        return TrainingDiverged(f"training diverged at step {self.step + 1}: {what}; stopped, {kept}")

    def train_step(self) -> dict[str, float]:
        """Run one optimisation step (``self.step`` counts completed steps)."""
        step = self.step
        p = self.preset
        if step == 0 or self.step_callback is not None:  # otherwise checked at the end of the last step
            self._check_params("before the step")
        for group in self.optimizers["means"].param_groups:
            group["lr"] = means_lr(step, p, self.extent)
        if p.learning_rates.lr_decay_final != 1.0:
            factor = other_lr_factor(step, p)
            for name, lr in base_lrs(p).items():
                for group in self.optimizers[name].param_groups:
                    group["lr"] = lr * factor
        i = self._next_view()
        level = self.coarse_level() if step < p.schedule.coarse_steps else None
        gt = (self.images[i] if level is None else level.images[i]).float() / 255.0
        valid = self.valid if level is None else level.valid
        render, alpha, info = self.render(self.viewmats[i], sh_degree_at(step, p, self.model.sh_degree), level,
                                          validate=not self.lean)
        self.strategy.step_pre_backward(self.model.params, self.optimizers, self.strategy_state, step, info)
        gt = fill_invalid(gt, render, valid)
        loss, l1, _ = photometric_loss(render, gt, p.loss.ssim_lambda)
        if p.loss.depth_lambda > 0:
            targets = self.depth_targets() if level is None else level.depths
            target = targets[i] if targets else None
            if target is not None:
                loss = loss + p.loss.depth_lambda * depth_loss(info["render_depth"], alpha, target,
                                                               masked_sums=self.lean)
        if self.lean:
            self._flag(torch.isfinite(loss.detach()), 1)
        else:
            loss_value = float(loss.detach())
            if not math.isfinite(loss_value):
                raise self._diverged(f"the loss is {loss_value} (view {self.data.train[i].view_id})")
        loss.backward()
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        self.strategy.step_post_backward(self.model.params, self.optimizers, self.strategy_state, step, info,
                                         packed=False)
        if self.lean:
            self._flag(self._params_finite(), 2)
        else:
            self._check_params("after the optimiser step")
        self.step += 1
        self.refresh_filter_3d()
        if self.lean:  # tensors on the device: read at the curve interval
            loss_t, value_t = loss.detach(), psnr_tensor(render, gt, valid)
            self.psnr_ema = value_t if self.psnr_ema is None else 0.9 * self.psnr_ema + 0.1 * value_t
            self.loss_ema = loss_t if self.loss_ema is None else 0.9 * self.loss_ema + 0.1 * loss_t
            return {"loss": loss_t, "l1": l1.detach(), "psnr": value_t}
        value = psnr(render, gt, valid)
        self.psnr_ema = value if self.psnr_ema is None else 0.9 * self.psnr_ema + 0.1 * value
        self.loss_ema = loss_value if self.loss_ema is None else 0.9 * self.loss_ema + 0.1 * loss_value
        return {"loss": loss_value, "l1": float(l1.detach()), "psnr": value}

    # ------------------------------------------------------------------ the loop
    def train(self, resume: bool = False, max_steps: int | None = None) -> TrainResult:
        """Train until ``preset.steps`` (or ``max_steps``) steps or the time budget; see the module doc."""
        resumed_from = None
        if resume:
            resumed_from = self.load_latest_checkpoint()
        end = self.preset.steps if max_steps is None else min(max_steps, self.preset.steps)
        budget = self.preset.time_budget_s
        started = time.perf_counter() if self.budget_started_at is None else self.budget_started_at
        used = 0.0
        schedule = self.preset.schedule
        bar = progress_bar(total=self.preset.steps, desc="train", unit="step", initial=self.step) \
            if self.show_progress else None
        stopped_by = "steps"
        written: list[str] = []
        try:
            if not self.curve:
                self._record_curve()
            while self.step < end:
                used = time.perf_counter() - started
                if budget is not None and used >= budget:
                    stopped_by = "time budget"
                    log.warning("time budget of %.0f s reached after %d of %d steps", budget, self.step,
                                self.preset.steps)
                    break
                t0, c0 = time.perf_counter(), time.process_time()
                self.train_step()
                self.elapsed += time.perf_counter() - t0
                self.cpu_elapsed += time.process_time() - c0
                if self.step % schedule.curve_every == 0 or self.step == end:
                    self._record_curve()
                if schedule.eval_every and self.step % schedule.eval_every == 0 and self.eval_callback:
                    if self.curve[-1]["step"] != self.step:
                        self._record_curve()
                    self.curve[-1]["holdout_psnr"] = float(self.eval_callback(self))
                if self.checkpoint_dir is not None and (self.step % schedule.checkpoint_every == 0
                                                        or self.step == self.preset.steps):
                    written.append(str(self.save_checkpoint()))
                if bar is not None:
                    bar.update(1)
                    # lean: the figures are device tensors, read at curve points only
                    every = schedule.curve_every if self.lean else 10
                    if self.step % every == 0 or self.step == end:
                        bar.set_postfix(loss=f"{self.loss_ema:.4f}", psnr=f"{self.psnr_ema:.2f}",
                                        n=self.model.num_gaussians, refresh=False)
                if self.step_callback is not None:
                    self.step_callback(self, self.step)
            if self.curve and self.curve[-1]["step"] != self.step:
                self._record_curve()
            self.raise_if_flagged()
        finally:
            if bar is not None:
                bar.close()
        self.refresh_filter_3d(force=True)  # the exported filter matches the final means
        if self.checkpoint_dir is not None and stopped_by == "time budget":
            written.append(str(self.save_checkpoint()))
        if stopped_by == "steps":
            used = time.perf_counter() - started
        return TrainResult(self.step, self.elapsed, self.model.num_gaussians, stopped_by, self.curve,
                           resumed_from, written, self.cpu_elapsed, self.preset.steps, budget, used)

    def _record_curve(self) -> None:
        self.raise_if_flagged()
        self.curve.append({"step": float(self.step), "time_s": self.elapsed, "cpu_s": self.cpu_elapsed,
                           "train_psnr": float(self.psnr_ema) if self.psnr_ema is not None else float("nan"),
                           "loss": float(self.loss_ema) if self.loss_ema is not None else float("nan"),
                           "num_gaussians": float(self.model.num_gaussians)})

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly (CPU tensors)."""
        return {
            "version": CHECKPOINT_VERSION,
            "step": self.step,
            "elapsed_s": self.elapsed,
            "cpu_s": self.cpu_elapsed,
            "sh_degree": self.model.sh_degree,
            "params": {k: v.detach().cpu().clone() for k, v in self.model.params.items()},
            "optimizers": {k: _to_cpu(opt.state_dict()) for k, opt in self.optimizers.items()},
            "strategy_state": _to_cpu(self.strategy_state),
            "rng": {"torch": torch.get_rng_state(), "views": self.view_rng.get_state(), "order": list(self.order),
                    "cuda": torch.cuda.get_rng_state_all() if self.device.type == "cuda" else None},
            "ema": [None if v is None else float(v) for v in (self.psnr_ema, self.loss_ema)],
            "curve": list(self.curve),
            "preset": self.preset.to_json(),
            "train_views": self.data.fingerprint(),
            "extent": self.extent,
            "frame": None if self.data.frame is None else self.data.frame.to_json(),
        }

    def load_state_dict(self, ckpt: dict[str, Any], source: str = "checkpoint") -> None:
        """Continue from ``ckpt``; a checkpoint of another version, split or shape raises naming ``source``."""
        try:
            self._load_state(ckpt, source)
        except DataError:
            raise
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise DataError(f"{source}: not a usable brave6d checkpoint ({type(exc).__name__}: {exc})") from None

    def _load_state(self, ckpt: dict[str, Any], source: str) -> None:
        if ckpt.get("version") not in (1, CHECKPOINT_VERSION):
            raise DataError(f"{source}: checkpoint version {ckpt.get('version')} is not {CHECKPOINT_VERSION}")
        if ckpt["train_views"] != self.data.fingerprint():
            raise DataError(f"{source}: the checkpoint was trained on other views (the capture, the holdout "
                            "or the skipped frames changed); start again without --resume")
        ckpt = _in_frame(ckpt, self.data.frame, source)
        self.model = GaussianModel.from_tensors(ckpt["params"], int(ckpt["sh_degree"]), self.device)
        self.optimizers = self._make_optimizers()
        for name, opt in self.optimizers.items():
            opt.load_state_dict(ckpt["optimizers"][name])
        self.strategy_state = {k: v.to(self.device) if isinstance(v, Tensor) else v
                               for k, v in ckpt["strategy_state"].items()}
        torch.set_rng_state(ckpt["rng"]["torch"])
        self.view_rng.set_state(ckpt["rng"]["views"])
        if ckpt["rng"].get("cuda") is not None and self.device.type == "cuda":
            torch.cuda.set_rng_state_all(ckpt["rng"]["cuda"])
        self.order = list(ckpt["rng"]["order"])
        self.step = int(ckpt["step"])
        self.elapsed = float(ckpt["elapsed_s"])
        self.cpu_elapsed = float(ckpt.get("cpu_s", 0.0))
        self.psnr_ema, self.loss_ema = ckpt["ema"]
        self.curve = list(ckpt["curve"])
        self.extent = float(ckpt["extent"])
        self.near_plane, self.far_plane = near_far(self.extent)
        self._filter_means = None  # a new model: its filter is computed again
        self.refresh_filter_3d()

    def save_checkpoint(self) -> Path:
        """Write ``ckpt_<step>.pt`` atomically (only from a finite state), prune old ones, call the hook.

        Returns where the checkpoint is once the hook has run (it may move the folder).
        """
        assert self.checkpoint_dir is not None
        self.raise_if_flagged()
        self._check_params("at the checkpoint")
        path = self.checkpoint_dir / f"ckpt_{self.step:06d}.pt"
        state = self.state_dict()
        atomic_write(path, lambda handle: torch.save(state, handle))
        self.last_checkpoint = path
        for old in list_checkpoints(self.checkpoint_dir)[: -self.preset.schedule.keep_checkpoints]:
            old.unlink(missing_ok=True)
        if self.checkpoint_hook is not None:
            self.checkpoint_hook(self)
        return self.last_checkpoint

    def move_checkpoints(self, target: Path) -> None:
        """Rename the checkpoint folder to ``target`` (which must not exist) and keep writing there."""
        assert self.checkpoint_dir is not None
        os.rename(self.checkpoint_dir, target)
        if self.last_checkpoint is not None:
            self.last_checkpoint = target / self.last_checkpoint.name
        self.checkpoint_dir = target

    def load_latest_checkpoint(self) -> int | None:
        """Restore the newest readable checkpoint; returns its step (None when there is none).

        A torn file is skipped for an older one; when every file is unreadable, or one is refused
        (see :func:`read_checkpoint`), this raises instead of quietly starting from step 0.
        """
        if self.checkpoint_dir is None:
            return None
        paths = list_checkpoints(self.checkpoint_dir)
        for path in reversed(paths):
            try:
                ckpt = read_checkpoint(path)
            except UnreadableCheckpoint as exc:
                log.warning("%s; trying an older one", exc)
                continue
            self.load_state_dict(ckpt, str(path))
            self.last_checkpoint = path
            log.info("resumed from %s (step %d, %.0f s trained)", path, self.step, self.elapsed)
            return self.step
        if paths:
            raise DataError(f"{self.checkpoint_dir}: none of the {len(paths)} checkpoint(s) can be read; "
                            "start again without --resume")
        log.warning("--resume: no checkpoint in %s; starting from step 0", self.checkpoint_dir)
        return None


def _in_frame(ckpt: dict[str, Any], frame: SceneFrame | None, source: str) -> dict[str, Any]:
    """``ckpt`` with its parameters in ``frame`` (the run's training frame; None: world units).

    A checkpoint records the frame its parameters are in (version 2). It must be the run's: the
    frame comes from the camera centres, so another one means the cameras moved. A version 1
    checkpoint (world units, written before training frames) is moved into ``frame``: the
    positions and their Adam moments, the log scales, the extent."""
    saved = ckpt.get("frame")
    if saved is not None or ckpt.get("version") == CHECKPOINT_VERSION:
        theirs = None if saved is None else SceneFrame.from_json(saved)
        if theirs != frame:
            raise DataError(f"{source}: the checkpoint was trained in another frame ({saved} against "
                            f"{None if frame is None else frame.to_json()}): the cameras moved since; start again "
                            "without --resume")
        return ckpt
    if frame is None:
        return ckpt
    u = frame.unit
    params = dict(ckpt["params"])
    params["means"] = torch.from_numpy(frame.points(params["means"].double().numpy())).float()
    params["scales"] = (params["scales"].double() - math.log(u)).float()
    optimizers = dict(ckpt["optimizers"])
    means_opt = {**optimizers["means"], "state": {k: {**v} for k, v in optimizers["means"]["state"].items()}}
    for moments in means_opt["state"].values():
        if "exp_avg" in moments:
            moments["exp_avg"] = moments["exp_avg"] / u
        if "exp_avg_sq" in moments:
            moments["exp_avg_sq"] = moments["exp_avg_sq"] / (u * u)
    optimizers["means"] = means_opt
    strategy = {**ckpt["strategy_state"], "scene_scale": 1.0}
    log.info("%s: a version 1 checkpoint (world units) moved into the training frame (unit %.6g)", source, u)
    return {**ckpt, "params": params, "optimizers": optimizers, "strategy_state": strategy, "extent": 1.0,
            "frame": frame.to_json()}


_UNSUPPORTED_GLOBAL = re.compile(r"Unsupported global: GLOBAL ([\w.]+)")


def read_checkpoint(path: Path) -> dict[str, Any]:
    """Load a checkpoint as tensors and plain values only (``weights_only``): never runs code.

    A file that needs any other object to unpickle (an old format, or one crafted to run code)
    is refused with a :class:`DataError` naming it; a torn or foreign file raises
    :class:`UnreadableCheckpoint`.
    """
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        found = _UNSUPPORTED_GLOBAL.search(str(exc))
        what = f"it needs {found.group(1)} to load" if found else "it holds more than tensors and plain values"
        raise DataError(f"{path}: refused to load this checkpoint: {what} (an old format or not written by "
                        "brave6d; loading it could run code); move it away or train without --resume") from None
    except Exception as exc:  # noqa: BLE001 - torch raises many types for a torn or foreign file
        raise UnreadableCheckpoint(f"{path}: unreadable checkpoint ({type(exc).__name__}: "
                                   f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    if not isinstance(ckpt, dict):
        raise UnreadableCheckpoint(f"{path}: not a brave6d checkpoint (holds a {type(ckpt).__name__})")
    return ckpt


def list_checkpoints(folder: Path) -> list[Path]:
    """Checkpoint files in ``folder``, oldest step first."""
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _CKPT.match(p.name))]
    return [p for _, p in sorted(found)]


def _step_of(path: Path | None) -> int | None:
    m = _CKPT.match(path.name) if path else None
    return int(m.group(1)) if m else None


def _to_cpu(obj: Any) -> Any:
    if isinstance(obj, Tensor):
        return obj.detach().cpu().clone()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_to_cpu(v) for v in obj]
    return obj


def half_intrinsics(K: Tensor) -> Tensor:
    """``K`` of the image made by averaging 2x2 pixel blocks: focal lengths halved, and the
    principal point moved so that pixel centres stay at integer coordinates
    (``c' = (c + 0.5) / 2 - 0.5``): a point at full-resolution pixel ``u`` lands at ``(u + 0.5) / 2 - 0.5``."""
    out = K.clone()
    out[0, 0], out[1, 1] = K[0, 0] / 2, K[1, 1] / 2
    out[0, 2], out[1, 2] = (K[0, 2] + 0.5) / 2 - 0.5, (K[1, 2] + 0.5) / 2 - 0.5
    return out


def half_image(image: Tensor) -> Tensor:
    """A uint8 ``[H, W, C]`` image averaged over 2x2 blocks (odd last row/column dropped), rounded."""
    h, w = image.shape[0] // 2 * 2, image.shape[1] // 2 * 2
    x = image[:h, :w].float().reshape(h // 2, 2, w // 2, 2, -1).mean(dim=(1, 3))
    return x.round().clamp(0, 255).to(torch.uint8)


@dataclass(frozen=True)
class CoarseLevel:
    """The training images at half width and height (coarse-to-fine schedule of :class:`Preset`)."""

    images: list[Tensor]
    K: Tensor
    valid: Tensor | None  # a coarse pixel is valid when its four fine pixels are
    width: int
    height: int
    depths: list[DepthTarget | None] | None = None  # the depth targets at half size (None: no depth loss)

    @classmethod
    def of(cls, images: list[Tensor], K: Tensor, valid: Tensor | None,
           depths: list[DepthTarget | None] | None = None) -> CoarseLevel:
        if not images or images[0].shape[0] < 2 or images[0].shape[1] < 2:
            raise BraveError("coarse-to-fine training needs images of at least 2x2 pixels")
        small = [half_image(im) for im in images]
        if valid is not None:
            h, w = valid.shape[0] // 2 * 2, valid.shape[1] // 2 * 2
            valid = valid[:h, :w].reshape(h // 2, 2, w // 2, 2).all(dim=3).all(dim=1)
        return cls(small, half_intrinsics(K), valid, int(small[0].shape[1]), int(small[0].shape[0]), depths)


def image_of(view_index: int, data: TrainingData, device: torch.device | str = "cpu") -> Tensor:
    """Training image ``view_index`` as float [H, W, 3] (helper for callers and tests)."""
    return image_tensor(data.train[view_index], device)


def set_seed(seed: int) -> None:
    """Seed torch and NumPy's legacy global generator (gsplat's strategy ops use both)."""
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))

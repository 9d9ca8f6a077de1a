"""Training presets: the hyperparameters of one training run, as frozen dataclasses composed of parts.

A :class:`Preset` has a name, the run's length (``steps``), the image size, a time budget and a seed,
and one part per job: :class:`Schedule` (when things happen: coarse-to-fine, SH growth, curve,
holdout and checkpoint cadence), :class:`LearningRates` (Adam's rates and their decay),
:class:`Loss`, :class:`Initialisation` (the model training starts from) and :class:`Densification`
(the densification strategy's own options: :class:`brave6d.training.strategy.DensifyStrategy` reads
that object).

A field counted in optimiser steps is declared as one, with :func:`every` (a period) or :func:`at`
(a step of the run); :meth:`Preset.with_steps` scales every such field of every part, so a new step
field scales by being declared as one. :meth:`Preset.with_overrides` and :meth:`Preset.with_values`
name a field by its path (``densification.max_gaussians``) or by its name alone: names are unique
across the parts, and they are the keys of :meth:`Preset.to_json`, the same flat record as before
the parts (so ``metrics.json`` and benchmark JSON of older and newer runs compare key by key).

``default`` follows the Inria reference (30k steps, learning rates, densification schedule;
see docs/ARCHITECTURE.md). ``quality`` trains longer (50k steps, densifying until 25k) and with
Mip-Splatting's anti-aliasing (:class:`Antialiasing`). ``fast`` is
tuned for the CPU demo (2 cores, no GPU) to reach a given holdout PSNR in the least time: half-resolution
images (320x200 for the demo), 2000 steps of which the first 600 on 2x2-averaged images
(coarse-to-fine), densification from step 100 to 1200 every 50 steps without opacity reset, at most
100k Gaussians, SH degree 2, the captured depth as a second loss term and Mip-Splatting's filters
(``fast`` and ``quality``), learning rates raised for the short run and, from step 600, annealed to a
tenth (all but the positions, which decay as Inria's), and a 14-minute budget.
``benchmarks/time_to_quality.py`` compares it with any other configuration, interleaved on one machine.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import Field, dataclass, field, fields, is_dataclass, replace
from typing import Any

from brave6d.core.errors import BraveError, DataError

#: The metadata key of a field counted in optimiser steps; its value scales the field (:func:`every`, :func:`at`).
STEPS = "steps"


@dataclass(frozen=True)
class Every:
    """How a period in steps scales: proportionally, never below 1; 0 (``may_be_off``: never) stays 0."""

    may_be_off: bool = False

    def scale(self, value: int, factor: float, steps: int) -> int:
        return 0 if value == 0 else max(1, round(value * factor))

    def problem(self, value: int) -> str | None:
        lowest, note = (0, " (0: never)") if self.may_be_off else (1, "")
        return None if value >= lowest else f"must be >= {lowest}{note}, got {value}"


@dataclass(frozen=True)
class At:
    """How a step of the run scales: proportionally, at least ``minimum`` and at most the run's steps."""

    minimum: int = 0

    def scale(self, value: int, factor: float, steps: int) -> int:
        return min(steps, max(self.minimum, round(value * factor)))

    def problem(self, value: int) -> str | None:
        return None if value >= 0 else f"must be >= 0, got {value}"


def every(default: int, *, may_be_off: bool = False) -> Any:
    """A field holding a period in optimiser steps ("every ``k`` steps"): :meth:`Preset.with_steps`
    scales it with the run, never below 1; ``may_be_off``: 0 means never and stays 0."""
    return field(default=default, metadata={STEPS: Every(may_be_off)})


def at(default: int, *, minimum: int = 0) -> Any:
    """A field holding a step of the run (a start, a stop, the end of a phase): :meth:`Preset.with_steps`
    scales it with the run, keeps it within the run and never below ``minimum``."""
    return field(default=default, metadata={STEPS: At(minimum)})


def step_fields(part: Any) -> list[tuple[Field[Any], Every | At]]:
    """The fields of a part declared as counted in steps, with how each scales."""
    return [(f, f.metadata[STEPS]) for f in fields(part) if STEPS in f.metadata]


Problems = Iterator[tuple[str, str]]  # (field, what is wrong with it)


@dataclass(frozen=True)
class Schedule:
    """When things happen during a run (all in optimiser steps)."""

    # coarse-to-fine: the first `coarse_steps` steps train on 2x2-averaged images (half width and
    # height, a quarter of the pixels per step); 0: every step at the training resolution
    coarse_steps: int = at(0)
    sh_degree_interval: int = every(1000)  # the SH degree grows by one every this many steps
    curve_every: int = every(100)  # record (time, train PSNR, #Gaussians) for the training curves
    eval_every: int = every(0, may_be_off=True)  # holdout evaluation during training (0: only at the end)
    checkpoint_every: int = every(5000)
    keep_checkpoints: int = 2

    def problems(self, steps: int) -> Problems:
        if not 0 <= self.coarse_steps <= steps:
            yield "coarse_steps", f"must be in 0..steps ({steps}), got {self.coarse_steps}"
        if self.keep_checkpoints < 1:
            yield "keep_checkpoints", f"must be >= 1, got {self.keep_checkpoints}"


@dataclass(frozen=True)
class LearningRates:
    """Adam's learning rates (Inria's) and their decay. The positions' rate is times the scene extent
    and decays exponentially from ``means_lr_init`` to ``means_lr_final`` over the run; the others
    (quats, scales, opacities, SH) fall log-linearly from their value at ``lr_decay_start`` to
    ``lr_decay_final`` times it at the last step (1.0, or a start at or after the last step: constant,
    as Inria)."""

    means_lr_init: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20.0
    opacities_lr: float = 5e-2
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    adam_eps: float = 1e-15
    lr_decay_final: float = 1.0
    lr_decay_start: int = at(0)

    def problems(self, steps: int) -> Problems:
        if not (math.isfinite(self.lr_decay_final) and 0.0 < self.lr_decay_final <= 1.0):
            yield "lr_decay_final", f"must be in (0, 1], got {self.lr_decay_final}"


@dataclass(frozen=True)
class Loss:
    """The photometric loss ``(1 - ssim_lambda) * L1 + ssim_lambda * (1 - SSIM)``, plus ``depth_lambda``
    times the relative L1 error of the rendered depth against the captured depth
    (:mod:`brave6d.training.depth_targets`: only where the sensor has data and no depth edge, a step of
    more than ``depth_edge_ratio`` times the depth; 0: colour only)."""

    ssim_lambda: float = 0.2
    depth_lambda: float = 0.0
    depth_edge_ratio: float = 0.02

    def problems(self, steps: int) -> Problems:
        if not 0.0 <= self.ssim_lambda <= 1.0:
            yield "ssim_lambda", f"must be in [0, 1], got {self.ssim_lambda}"
        if not (math.isfinite(self.depth_lambda) and self.depth_lambda >= 0.0):
            yield "depth_lambda", f"must be a finite number >= 0, got {self.depth_lambda}"
        if not (math.isfinite(self.depth_edge_ratio) and 0.0 < self.depth_edge_ratio <= 1.0):
            yield "depth_edge_ratio", f"must be in (0, 1], got {self.depth_edge_ratio}"


@dataclass(frozen=True)
class Initialisation:
    """The model training starts from: at most ``max_init_points`` points (COLMAP's, the depth
    frames' or random ones), spherical harmonics up to ``sh_degree``, an opacity, and scales of
    ``init_scale`` times the mean distance to the 3 nearest neighbours."""

    max_init_points: int = 300_000
    sh_degree: int = 3
    init_opacity: float = 0.1
    init_scale: float = 1.0

    def problems(self, steps: int) -> Problems:
        if not 0 <= self.sh_degree <= 3:
            yield "sh_degree", f"must be in 0..3, got {self.sh_degree}"


@dataclass(frozen=True)
class Densification:
    """The densification strategy's options (gsplat DefaultStrategy's, Inria's values): refine (grow
    and prune) every ``refine_every`` steps after ``refine_start`` until ``refine_stop``, reset the
    opacities every ``reset_every`` steps while refining; ``max_gaussians``: growth is limited to the
    highest gradients beyond this many Gaussians (None: no limit).

    ``photo_set_pixels_per_gaussian``: for a photo set (no training view has depth), the cap is
    also at most one Gaussian per this many training pixels (None: off). Without depth only the
    photos constrain the Gaussians, and a sparse set's surplus fits the training views at the
    cost of new ones: on the shipped skull sample (58 photos at 240x160, 2.2M pixels) at 500 steps,
    74k Gaussians gave 18.9 dB holdout PSNR, 10k-30k 21.7-22.5 dB; the fox (45 at 135x240) is flat
    from 20k to 100k (28.7-29.1 dB) and loses 0.5 dB at 15k. ``fast``: 70 (docs/BENCHMARKS.md).
    Captures with depth (the robot's) keep ``max_gaussians``."""

    refine_start: int = at(500, minimum=1)
    refine_stop: int = at(15_000, minimum=1)
    refine_every: int = every(100)
    reset_every: int = every(3000)
    grow_grad2d: float = 2e-4
    grow_scale3d: float = 0.01
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1
    max_gaussians: int | None = None
    photo_set_pixels_per_gaussian: float | None = None

    def problems(self, steps: int) -> Problems:
        ppg = self.photo_set_pixels_per_gaussian
        if ppg is not None and not (math.isfinite(ppg) and ppg > 0.0):
            yield "photo_set_pixels_per_gaussian", f"must be None or a finite number > 0, got {ppg}"

    def photo_set_cap(self, training_pixels: int) -> int | None:
        """The Gaussian cap of a photo set with ``training_pixels`` pixels (train views x W x H):
        the smaller of ``max_gaussians`` and the per-pixel budget; ``max_gaussians`` when off."""
        if self.photo_set_pixels_per_gaussian is None:
            return self.max_gaussians
        budget = max(1, int(training_pixels / self.photo_set_pixels_per_gaussian))
        return budget if self.max_gaussians is None else min(self.max_gaussians, budget)


@dataclass(frozen=True)
class Antialiasing:
    """Anti-aliasing for views closer or farther than the training views (Mip-Splatting):
    ``classic`` renders as gsplat's classic mode (the 0.3 px^2 dilation only); ``mip`` trains with
    the 3D smoothing filter (variance ``filter_3d_scale / rate^2`` with ``rate`` the highest
    sampling rate of the training cameras that see a Gaussian, recomputed every
    ``filter_3d_every`` steps and after each densification) and the 2D mip filter (the
    rasterizer's ``antialiased`` mode). The splat records it (the PLY's ``filter_3d``, the bundle's
    ``render.antialiasing``), so that every renderer draws it as it was trained."""

    antialiasing: str = "classic"
    filter_3d_scale: float = 0.2
    filter_3d_every: int = every(100)

    def problems(self, steps: int) -> Problems:
        if self.antialiasing not in ANTIALIASING_MODES:
            yield "antialiasing", f"must be one of {', '.join(ANTIALIASING_MODES)}, got {self.antialiasing!r}"
        if not (math.isfinite(self.filter_3d_scale) and self.filter_3d_scale > 0.0):
            yield "filter_3d_scale", f"must be a finite number > 0, got {self.filter_3d_scale}"


#: ``classic``: no anti-aliasing beyond gsplat's dilation; ``mip``: Mip-Splatting's 3D and 2D filters.
ANTIALIASING_MODES = ("classic", "mip")


@dataclass(frozen=True)
class Preset:
    """Everything that shapes a training run (all steps count optimiser iterations); see the module doc."""

    name: str
    steps: int = 30_000
    downscale: int = 1  # images are resampled to 1/downscale of the undistorted resolution
    time_budget_s: float | None = None  # stop (and evaluate) when training has run this long
    seed: int = 0
    schedule: Schedule = field(default_factory=Schedule)
    learning_rates: LearningRates = field(default_factory=LearningRates)
    loss: Loss = field(default_factory=Loss)
    initialisation: Initialisation = field(default_factory=Initialisation)
    antialias: Antialiasing = field(default_factory=Antialiasing)
    densification: Densification = field(default_factory=Densification)

    def __post_init__(self) -> None:
        self._paths()  # names unique across the parts
        for where, problem in self._problems():
            raise BraveError(f"preset {self.name}: {where} {problem}")

    def _problems(self) -> Problems:
        if self.steps < 1:
            yield "steps", f"must be >= 1, got {self.steps}"
        if self.downscale < 1:
            yield "downscale", f"must be >= 1, got {self.downscale}"
        for part_name, part in self.parts().items():
            for f, how in step_fields(part):
                if (problem := how.problem(getattr(part, f.name))) is not None:
                    yield f"{part_name}.{f.name}", problem
            check = getattr(part, "problems", None)
            for name, problem in check(self.steps) if check is not None else ():
                yield f"{part_name}.{name}", problem

    def parts(self) -> dict[str, Any]:
        """The parts (the dataclass-valued fields) by field name: ``schedule``, ``learning_rates``, ..."""
        return {f.name: v for f in fields(self) if is_dataclass(v := getattr(self, f.name)) and not isinstance(v, type)}

    def _paths(self) -> dict[str, str]:
        """Every settable value's path (``steps``, ``densification.max_gaussians``) by its name."""
        parts = self.parts()
        paths = {f.name: f.name for f in fields(self) if f.name not in parts}
        for part_name, part in parts.items():
            for f in fields(part):
                if f.name in paths or f.name in parts:
                    raise BraveError(f"preset {self.name}: the field name {f.name!r} is in both "
                                     f"{paths.get(f.name, f.name)} and "
                                     f"{part_name}.{f.name}; names must be unique across the parts (they are the "
                                     "keys of to_json and of overrides)")
                paths[f.name] = f"{part_name}.{f.name}"
        return paths

    def paths(self) -> list[str]:
        """The path of every value (``name``, ``steps``, ..., ``densification.max_gaussians``)."""
        return list(self._paths().values())

    def path_of(self, key: str) -> str:
        """The path of ``key``: a path, a field name (``max_gaussians`` -> ``densification.max_gaussians``)
        or a part's name."""
        paths = self._paths()
        if key in paths:
            return paths[key]
        if key in paths.values() or key in self.parts():
            return key
        raise BraveError(f"preset {self.name}: no field {key!r} (fields: {', '.join(paths.values())})")

    def with_values(self, **changes: Any) -> Preset:
        """A copy with the values at these paths or names replaced (``None`` included: no time budget,
        no cap on the Gaussians); a whole part may be given by its name."""
        top: dict[str, Any] = {}
        by_part: dict[str, dict[str, Any]] = {}
        for key, value in changes.items():
            part_name, _, name = self.path_of(key).rpartition(".")
            if part_name:
                by_part.setdefault(part_name, {})[name] = value
            else:
                top[name] = value
        for part_name, values in by_part.items():
            top[part_name] = replace(top.get(part_name, getattr(self, part_name)), **values)
        return replace(self, **top)

    def with_overrides(self, **changes: Any) -> Preset:
        """A copy with some values replaced, by path or name (``None`` values are ignored: options left unset)."""
        return self.with_values(**{k: v for k, v in changes.items() if v is not None})

    def with_steps(self, steps: int) -> Preset:
        """A copy for a run of ``steps`` steps: every field of every part declared with :func:`every`
        or :func:`at` scales with it."""
        if steps == self.steps:
            return self
        factor = steps / self.steps
        scaled = {name: replace(part, **{f.name: how.scale(getattr(part, f.name), factor, steps)
                                         for f, how in step_fields(part)})
                  for name, part in self.parts().items()}
        return replace(self, steps=steps, **scaled)

    def to_json(self) -> dict[str, Any]:
        """The values by name, flat (the record ``metrics.json`` and the benchmarks keep)."""
        parts = self.parts()
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in parts}
        for part in parts.values():
            out.update({f.name: getattr(part, f.name) for f in fields(part)})
        return out

    @classmethod
    def from_json(cls, record: Mapping[str, Any]) -> Preset:
        """The preset of a :meth:`to_json` record; names this version does not know are left out (a
        record of another version), missing ones keep their defaults. A record without a name or
        with an invalid value raises :class:`DataError`."""
        if not isinstance(record.get("name"), str):
            raise DataError(f"a preset record needs a name, got {record.get('name')!r}")
        base = cls(name=record["name"])
        known = set(base._paths())
        try:
            return base.with_values(**{k: v for k, v in record.items() if k in known and k != "name"})
        except BraveError as exc:
            raise DataError(f"preset record: {exc}") from None


DEFAULT = Preset(name="default")

#: The captured depth's weight in the shipped ``fast`` and ``quality`` presets (issue 34: on the demo it
#: brings the splat's expected depth on the objects from 2.2-3.7 mm to 0.6-0.8 mm, median, at no PSNR cost).
DEPTH_LAMBDA = 2.0

QUALITY = Preset(
    name="quality", steps=50_000, densification=Densification(refine_stop=25_000),
    loss=Loss(depth_lambda=DEPTH_LAMBDA),
    antialias=Antialiasing(antialiasing="mip"),
)

FAST = Preset(
    name="fast",
    steps=2000,
    downscale=2,
    time_budget_s=14 * 60.0,
    schedule=Schedule(
        coarse_steps=600,  # the first 600 steps on 2x2-averaged images
        sh_degree_interval=400,
        checkpoint_every=500,
        curve_every=20,
    ),
    # learning rates for a short run (tuned on the demo capture, issue 22): colours 5x, scales 3x,
    # positions 3x Inria's, the positions decaying to 5e-6 (x extent) instead of 1.6e-6
    learning_rates=LearningRates(
        sh0_lr=0.012,
        shN_lr=0.0006,
        scales_lr=0.015,
        means_lr_init=5e-4,
        means_lr_final=5e-6,
        lr_decay_final=0.1,  # from the first full-resolution step, all but the positions' rates fall to 1/10
        lr_decay_start=600,
    ),
    loss=Loss(depth_lambda=DEPTH_LAMBDA),
    # Mip-Splatting's filters (issue 34): on the demo +1.0-1.7 dB image PSNR against the truth at 10-50 cm
    # and +0.3-1.4 dB in the objects' boxes, the same holdout PSNR
    antialias=Antialiasing(antialiasing="mip"),
    initialisation=Initialisation(sh_degree=2, max_init_points=60_000),
    densification=Densification(
        refine_start=100,
        refine_stop=1200,
        refine_every=50,
        reset_every=1_000_000,  # no opacity reset: too few steps remain to recover from one
        grow_grad2d=2e-4,
        max_gaussians=100_000,
        photo_set_pixels_per_gaussian=70.0,  # issue 47: sparse photo sets overfit with 100k
    ),
)

PRESETS: dict[str, Preset] = {p.name: p for p in (FAST, DEFAULT, QUALITY)}

#: ``fast`` before issue 22 (3000 steps at full resolution, Inria's learning rates, 150k Gaussians),
#: kept for ``benchmarks/time_to_quality.py`` (``--a old=fast-3000``) and for reproducing older runs.
FAST_3000 = Preset(
    name="fast-3000",
    steps=3000,
    downscale=2,
    time_budget_s=14 * 60.0,
    schedule=Schedule(sh_degree_interval=600, checkpoint_every=750, curve_every=30),
    initialisation=Initialisation(sh_degree=2, max_init_points=60_000),
    densification=Densification(refine_start=300, refine_stop=1800, refine_every=150, reset_every=1_000_000,
                                grow_grad2d=2e-4, max_gaussians=150_000),
)
#: ``fast`` before the learning-rate annealing (the same schedule with constant rates but the positions'),
#: for ``--a old=fast-2000``.
FAST_2000 = FAST.with_values(name="fast-2000", lr_decay_final=1.0, lr_decay_start=0, depth_lambda=0.0,
                             antialiasing="classic")
BENCHMARK_PRESETS: dict[str, Preset] = {**PRESETS, FAST_3000.name: FAST_3000, FAST_2000.name: FAST_2000}


def get_preset(name: str, known: dict[str, Preset] = PRESETS) -> Preset:
    """The preset called ``name`` (``fast``, ``default`` or ``quality``; benchmarks also pass
    :data:`BENCHMARK_PRESETS`, which adds ``fast-3000`` and ``fast-2000``)."""
    try:
        return known[name]
    except KeyError:
        raise BraveError(f"unknown preset {name!r}; choose one of {sorted(known)}") from None

"""The pipeline's training stage: ``brave6d.training.demo:stage_train`` (see ``brave6d.pipeline``).

It trains with the preset the run chose (``RunContext.preset``; none: :data:`DEFAULT_PRESET`, the
CPU demo's), in its miniature variant (:func:`quick_variant`) when the run is ``quick``.
``brave6d train`` resolves its ``--preset`` through the same :func:`run_preset`.
"""

from __future__ import annotations

import logging
from typing import Any

from brave6d.core.progress import StageResult
from brave6d.core.run_context import RunContext
from brave6d.training.colmap_init import ColmapOptions
from brave6d.training.presets import Preset, get_preset
from brave6d.training.run_outcome import budget_stop_line

log = logging.getLogger(__name__)

#: The preset of a run that chooses none: ``fast``, tuned for the CPU demo (a GPU cluster chooses
#: ``default``: ``brave6d dataset run --preset default`` or ``preset: default`` in its ``cluster`` block).
DEFAULT_PRESET = "fast"


def quick_variant(preset: Preset) -> Preset:
    """The miniature run of ``preset`` (``--quick``, what CI runs): small images, few steps,
    named ``<preset>-quick``."""
    return preset.with_steps(150).with_overrides(name=f"{preset.name}-quick", downscale=4, time_budget_s=180.0,
                                                 max_gaussians=30_000, max_init_points=20_000)


#: The miniature run of ``brave6d demo --quick`` (CI): ``fast-quick``.
QUICK = quick_variant(get_preset(DEFAULT_PRESET))


def run_preset(name: str | None, quick: bool = False) -> Preset:
    """The preset a run trains with: ``name`` (``RunContext.preset``; None: :data:`DEFAULT_PRESET`),
    its :func:`quick_variant` when ``quick``; an unknown name is a :class:`BraveError` listing the known."""
    preset = get_preset(name or DEFAULT_PRESET)
    return quick_variant(preset) if quick else preset


def stage_train(ctx: RunContext) -> StageResult:
    """Train the scene with the run's preset (:func:`run_preset`) and evaluate the holdout."""
    from brave6d.training.pipeline import require_capture, train_scene

    preset = run_preset(ctx.preset, ctx.quick)  # an unknown name fails here, before anything is loaded
    require_capture(ctx.scene)
    colmap = ColmapOptions(max_features=1024) if ctx.quick else ColmapOptions()
    m = train_scene(ctx.scene, preset, device=ctx.device, colmap=colmap, resume=ctx.resume)
    hold = m["holdout"]
    figures: dict[str, Any] = {
        "holdout PSNR": round(hold["psnr"], 2),
        "SSIM": round(hold["ssim"], 4),
    }
    for m_level in hold["per_level"].values():
        figures[f"PSNR@{m_level['distance_m']:.2f}m"] = round(m_level["psnr"], 2)
    figures.update({"gaussians": m["num_gaussians"], "steps": m["steps"], "planned steps": m["planned_steps"],
                    "stopped by": m["stopped_by"], "train s": round(m["train_time_s"], 1),
                    "init": m["init"].get("source", "?")})
    # the way to continue (a quick run's miniature preset has no command-line name: it says what stopped it only)
    line = None if ctx.quick else budget_stop_line(m, ctx.scene.root, ctx.preset or DEFAULT_PRESET)
    if line:
        log.warning("%s", line)
    return StageResult("train", figures=figures)

"""The pipeline's training stage: ``brave6d.training.demo:stage_train`` (see ``brave6d.pipeline``)."""

from __future__ import annotations

from typing import Any

from brave6d.core.progress import StageResult
from brave6d.core.run_context import RunContext
from brave6d.training.colmap_init import ColmapOptions
from brave6d.training.presets import FAST, Preset

#: The miniature run of ``brave6d demo --quick`` (CI): small images, few steps.
QUICK = FAST.with_steps(150).with_overrides(name="fast-quick", downscale=4, time_budget_s=180.0,
                                            max_gaussians=30_000, max_init_points=20_000)


def demo_preset(quick: bool) -> Preset:
    return QUICK if quick else FAST


def stage_train(ctx: RunContext) -> StageResult:
    """Train the demo scene with the ``fast`` preset (``quick``: a miniature run)."""
    from brave6d.training.pipeline import require_capture, train_scene

    require_capture(ctx.scene)
    colmap = ColmapOptions(max_features=1024) if ctx.quick else ColmapOptions()
    m = train_scene(ctx.scene, demo_preset(ctx.quick), device=ctx.device, colmap=colmap,
                    resume=ctx.resume)
    hold = m["holdout"]
    figures: dict[str, Any] = {
        "holdout PSNR": round(hold["psnr"], 2),
        "SSIM": round(hold["ssim"], 4),
    }
    for m_level in hold["per_level"].values():
        figures[f"PSNR@{m_level['distance_m']:.2f}m"] = round(m_level["psnr"], 2)
    figures.update({"gaussians": m["num_gaussians"], "steps": m["steps"], "train s": round(m["train_time_s"], 1),
                    "init": m["init"].get("source", "?")})
    return StageResult("train", figures=figures)

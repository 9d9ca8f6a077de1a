"""The demo's ``learn`` stage: render a synthetic train_pbr of the scene's objects (``brave6d synth``)
and train the learned estimator on it, so that the evaluation stage plays the learned agents beside
the weight-free baselines.

Writes ``<workdir>/learned/synth/`` (the split; resumable), ``<workdir>/learned/heldout/`` (a
smaller split of another seed, never trained on, that the card's held-out figures are scored on)
and ``<workdir>/learned/model/`` (``model.pt``, its card). A rerun with the same inputs renders
nothing and trains nothing: the splits skip the images they have, the model is reused by its
inputs' checksum.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from brave6d.core.progress import StageResult
    from brave6d.core.run_context import RunContext

#: train_pbr images the full demo renders, and the quick (CI) run.
DEMO_IMAGES = 300
QUICK_IMAGES = 24
#: Images of a second split (another seed, never trained on) the card's held-out figures are scored
#: on: the training split's every-10th slice is 30 images, where one missed detection moves an
#: object's recall by 0.05-0.1.
DEMO_HELDOUT_IMAGES = 100
QUICK_HELDOUT_IMAGES = 4
HELDOUT_SEED = 1
#: The preset of the full demo and of the quick run.
DEMO_PRESET = "fast"
QUICK_PRESET = "tiny"


def learned_dir(workdir: Path) -> Path:
    """Where the demo keeps its split and model."""
    return Path(workdir) / "learned"


def demo_model_dir(workdir: Path) -> Path:
    """The demo's trained model folder (what the evaluation stage gives the learned agents)."""
    return learned_dir(workdir) / "model"


def stage_learn(ctx: RunContext) -> StageResult:
    """Demo stage (module docstring)."""
    import os

    from brave6d.annotation import BopLayout
    from brave6d.core.progress import StageResult
    from brave6d.evaluation.learned.pipeline import learn_and_card
    from brave6d.evaluation.learned.presets import get_learn_preset
    from brave6d.synth import SynthOptions, synthesize

    models = BopLayout.of_scene(ctx.scene).models_dir
    out = learned_dir(ctx.workdir)
    images = QUICK_IMAGES if ctx.quick else DEMO_IMAGES
    size = {"width": 320, "height": 200} if ctx.quick else {}
    t0 = time.perf_counter()
    synth = synthesize(ctx.scene.spec_path, out / "synth",
                       SynthOptions(images=images, seed=0, workers=min(4, os.cpu_count() or 1), **size))
    heldout = synthesize(ctx.scene.spec_path, out / "heldout",
                         SynthOptions(images=QUICK_HELDOUT_IMAGES if ctx.quick else DEMO_HELDOUT_IMAGES,
                                      seed=HELDOUT_SEED, workers=min(4, os.cpu_count() or 1), **size))
    synth_seconds = time.perf_counter() - t0
    preset = get_learn_preset(QUICK_PRESET if ctx.quick else DEMO_PRESET)
    card = learn_and_card(out / "synth", models, demo_model_dir(ctx.workdir), preset, ctx.device,
                          heldout_pbr=out / "heldout")
    held = card.get("heldout") or {}
    ar = held.get("pose_ar", {})
    recall = held.get("detection_recall_iou50", {})
    return StageResult("learn", figures={
        "train_pbr images": images, "rendered": synth.rendered + heldout.rendered,
        "synth s": round(synth_seconds, 1),
        "train s": card["train_seconds"], "preset": preset.name,
        "held-out images": held.get("images", "n/a"), "held-out recall min": min(recall.values()) if recall else "n/a",
        "held-out AR true box": ar.get("true_box_rgb", "n/a"), "held-out AR detected": ar.get("detected_rgb", "n/a"),
    })

"""The learned estimator: a detector and a pose network in GDR-Net's spirit, trained from scratch
on a dataset's own synthetic ``train_pbr`` (``brave6d synth``), no downloaded weights.

Public API (imported lazily: ``import brave6d.evaluation.learned`` loads no torch):

- training: ``train_learned`` (``brave6d learn train``), ``LearnResult``, ``LearnPreset``,
  ``get_learn_preset``, ``PRESETS``, ``resolve_precision`` (a preset as it runs on a device); ``learn_and_card`` (train or reuse, score the held-out images, write
  the card: the demo's stage and a dataset run);
- the trained model: ``read_model``, ``write_model``, ``LearnedModel`` (``model.pt``), ``write_card`` /
  ``read_card`` (``card.json``, ``MODEL_CARD.md``), ``training_seconds`` (a run's wall-clock time);
- inference: ``LearnedEstimator`` (``detect``, ``best_detection``, ``refine_box``, ``estimate``,
  ``estimate_both``, ``refine_views``), ``Detection``,
  ``LearnedPose``, ``LearnedRefused`` (``cause`` in ``REFUSAL_CAUSES``), ``solve_pnp``;
- ONNX: ``export_onnx`` (``brave6d learn export-onnx``: both networks, opset ``ONNX_OPSET``),
  ``OnnxEstimator`` (the estimator on an export, ONNX Runtime, no torch; ``from_export``) and
  ``use_onnx`` (one in place of a torch estimator of the same model); the ``onnx`` extra;
- held-out figures: ``score_heldout``, ``HeldoutScores``, ``DETECTION_THRESHOLD`` (the score a
  detection needs there and, by default, in the learned agents); the data: ``load_training_data``,
  ``TrainingData``.

Modules, one job each: ``data`` (train_pbr -> images, boxes, model coordinates), ``crops`` (zoomed-in
crops), ``silhouette`` (the RGB-only distance from the mask's area), ``targets`` (training
batches), ``networks``, ``losses``, ``training``, ``model_file``, ``onnx_export``
(the model and checkpoint files), ``inference``, ``heldout``, ``card``, ``cli``.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "train_learned": ".training", "LearnResult": ".training", "resolve_precision": ".training", "learn_and_card": ".pipeline",
    "LearnPreset": ".presets", "get_learn_preset": ".presets", "PRESETS": ".presets",
    "read_model": ".model_file", "write_model": ".model_file", "LearnedModel": ".model_file",
    "write_card": ".card", "read_card": ".card", "training_seconds": ".card",
    "LearnedEstimator": ".inference", "Detection": ".inference", "LearnedPose": ".inference",
    "LearnedRefused": ".inference", "REFUSAL_CAUSES": ".inference", "solve_pnp": ".inference",
    "score_heldout": ".heldout", "HeldoutScores": ".heldout", "DETECTION_THRESHOLD": ".presets",
    "load_training_data": ".data", "TrainingData": ".data",
    "export_onnx": ".onnx_export", "use_onnx": ".onnx_export", "ONNX_OPSET": ".onnx_export",
    "OnnxEstimator": ".onnx_export",
}

__all__ = sorted(_LAZY)

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

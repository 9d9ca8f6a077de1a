"""The trained networks as ONNX, and the estimator running them in ONNX Runtime (the ``onnx`` extra).

``brave6d learn export-onnx MODEL_DIR`` writes ``MODEL_DIR/onnx/``:

- ``detector.onnx``: input ``image`` (B, 3, H, W) float32, normalised as
  :func:`~brave6d.evaluation.learned.crops.normalise` does, any H and W (multiples of 16 keep the
  strides exact, as in torch); outputs ``heatmap`` (B, C, H/4, W/4) logits, ``box_size`` (B, 2, ...)
  log pixels, ``offset`` (B, 2, ...) cells;
- ``coordinate_net.onnx``: inputs ``crops`` (B, 3, S, S) float32 and ``class_index`` (B,) int64;
  outputs ``coords`` (B, 3, S/4, S/4) in [-1, 1] and ``mask`` (B, 1, S/4, S/4) logits;
- ``onnx.json``: the opset (:data:`OPSET`), the names and the sha256 of the ``model.pt`` they were
  exported from (a stale export is refused by :func:`use_onnx`).

Opset 17 with torch's TorchScript exporter (``dynamo=False``): it exports both networks in seconds
with dynamic batch and image sizes and needs nothing beyond ``onnx``; torch's newer exporter gives
the same graphs (outputs equal to 1e-6) but takes minutes on two cores and needs ``onnxscript``.

:func:`use_onnx` makes a :class:`~brave6d.evaluation.learned.LearnedEstimator` run its two networks
in ONNX Runtime (CPU) instead of torch; everything around them (resizing, crops, peak finding, PnP,
ICP) is unchanged, so the estimates agree with torch's to the networks' float rounding
(docs/BENCHMARKS.md: accuracy and milliseconds per estimate both ways).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.core.errors import DataError

#: ONNX opset of the exported graphs.
OPSET = ONNX_OPSET = 17
FOLDER = "onnx"
DETECTOR_FILE, POSE_FILE, INDEX_FILE = "detector.onnx", "coordinate_net.onnx", "onnx.json"
DETECTOR_IO = (("image",), ("heatmap", "box_size", "offset"))
POSE_IO = (("crops", "class_index"), ("coords", "mask"))
#: What the tests hold ONNX Runtime's outputs to, against torch's on the same inputs (max abs difference
#: of logits, log sizes, offsets and coordinates, all O(1) numbers).
TOLERANCE = 1e-4


@dataclass(frozen=True)
class OnnxExport:
    """Where an export went: the two graphs and the index."""

    folder: Path
    detector: Path
    pose: Path
    opset: int


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def export_onnx(model_dir: Path | str, out: Path | str | None = None) -> OnnxExport:
    """Write the detector and the coordinate net of ``model_dir/model.pt`` as ONNX into ``out``
    (default ``model_dir/onnx``), atomically each (module docstring)."""
    import io
    import warnings

    import torch

    from brave6d.core.atomic import atomic_write_bytes, atomic_write_text
    from brave6d.core.extras import require
    from brave6d.evaluation.learned.inference import LearnedEstimator
    from brave6d.evaluation.learned.model_file import MODEL

    require("onnx", "onnx", "brave6d learn export-onnx")
    model_dir = Path(model_dir)
    folder = Path(out) if out is not None else model_dir / FOLDER
    estimator = LearnedEstimator.load(model_dir)
    width = int(estimator.preset["work_width"])
    crop = int(estimator.preset["crop_px"])
    graphs = (
        (estimator.detector, (torch.zeros(1, 3, (width * 3 // 4) // 16 * 16, width),), DETECTOR_IO, DETECTOR_FILE,
         {"image": {0: "batch", 2: "height", 3: "width"}} | {n: {0: "batch", 2: "rows", 3: "cols"} for n in DETECTOR_IO[1]}),
        (estimator.pose, (torch.zeros(2, 3, crop, crop), torch.zeros(2, dtype=torch.int64)), POSE_IO, POSE_FILE,
         {"crops": {0: "batch", 2: "side", 3: "side"}, "class_index": {0: "batch"}}
         | {n: {0: "batch", 2: "cells", 3: "cells"} for n in POSE_IO[1]}),
    )
    folder.mkdir(parents=True, exist_ok=True)
    for module, example, (inputs, outputs), name, axes in graphs:
        buf = io.BytesIO()
        with warnings.catch_warnings():  # the TorchScript exporter's deprecation notice (module docstring)
            warnings.simplefilter("ignore")
            torch.onnx.export(module, example, buf, dynamo=False, opset_version=OPSET, input_names=list(inputs),
                              output_names=list(outputs), dynamic_axes=axes)
        atomic_write_bytes(folder / name, buf.getvalue())
    index = {"format": "brave6d-learned-onnx/1", "opset": OPSET, "model_sha256": _sha256(model_dir / MODEL),
             "detector": {"file": DETECTOR_FILE, "inputs": list(DETECTOR_IO[0]), "outputs": list(DETECTOR_IO[1])},
             "coordinate_net": {"file": POSE_FILE, "inputs": list(POSE_IO[0]), "outputs": list(POSE_IO[1])},
             "classes": estimator.obj_ids}
    atomic_write_text(folder / INDEX_FILE, json.dumps(index, indent=1) + "\n")
    return OnnxExport(folder, folder / DETECTOR_FILE, folder / POSE_FILE, OPSET)


class _OrtNetwork:
    """An ONNX Runtime session called like the torch module it was exported from (tensors in, a
    tuple of tensors out), so the estimator's code around it is the same."""

    def __init__(self, path: Path, inputs: tuple[str, ...], threads: int | None) -> None:
        ort = _onnxruntime()
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = int(threads)
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        self.inputs = inputs

    def __call__(self, *tensors: Any) -> tuple[Any, ...]:
        import torch

        feed = {name: t.detach().cpu().numpy() for name, t in zip(self.inputs, tensors)}
        return tuple(torch.from_numpy(np.ascontiguousarray(o)) for o in self.session.run(None, feed))


def _onnxruntime() -> Any:
    from brave6d.core.extras import require

    return require("onnxruntime", "onnx", "the learned estimator on ONNX Runtime")


def use_onnx(estimator: Any, model_dir: Path | str, onnx_dir: Path | str | None = None,
             threads: int | None = None) -> Any:
    """``estimator`` (loaded from ``model_dir``) with its two networks run by ONNX Runtime on the CPU
    from ``onnx_dir`` (default ``model_dir/onnx``); refused in one line when the export is missing or
    was made from another ``model.pt``. ``threads``: ONNX Runtime's intra-op threads (None: its default)."""
    from brave6d.evaluation.learned.model_file import MODEL

    folder = Path(onnx_dir) if onnx_dir is not None else Path(model_dir) / FOLDER
    index_path = folder / INDEX_FILE
    if not index_path.is_file():
        raise DataError(f"{index_path}: not found (write it with: brave6d learn export-onnx {model_dir})")
    try:
        index = json.loads(index_path.read_text(encoding="utf-8"))
        digest = str(index["model_sha256"])
    except (ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{index_path}: not an ONNX export index ({type(exc).__name__}: {exc})") from None
    if digest != _sha256(Path(model_dir) / MODEL):
        raise DataError(f"{index_path}: field 'model_sha256' does not match {Path(model_dir) / MODEL}: the export "
                        f"is of another model (export again: brave6d learn export-onnx {model_dir})")
    for name in (DETECTOR_FILE, POSE_FILE):
        if not (folder / name).is_file():
            raise DataError(f"{folder / name}: not found (export again: brave6d learn export-onnx {model_dir})")
    estimator.detector = _OrtNetwork(folder / DETECTOR_FILE, DETECTOR_IO[0], threads)
    estimator.pose = _OrtNetwork(folder / POSE_FILE, POSE_IO[0], threads)
    estimator.runtime = "onnxruntime"
    return estimator

"""The trained networks as ONNX, and the estimator running them in ONNX Runtime (the ``onnx`` extra).

``brave6d learn export-onnx MODEL_DIR`` writes ``MODEL_DIR/onnx/``:

- ``detector.onnx``: input ``image`` (B, 3, H, W) float32, normalised as
  :func:`~brave6d.evaluation.learned.crops.normalise` does, any H and W (multiples of 16 keep the
  strides exact, as in torch); outputs ``heatmap`` (B, C, H/4, W/4) logits, ``box_size`` (B, 2, ...)
  log pixels, ``offset`` (B, 2, ...) cells;
- ``coordinate_net.onnx``: inputs ``crops`` (B, 3, S, S) float32 and ``class_index`` (B,) int64;
  outputs ``coords`` (B, 3, S/4, S/4) in [-1, 1] and ``mask`` (B, 1, S/4, S/4) logits;
- ``onnx.json``: the opset (:data:`OPSET`), the names, the sha256 of the ``model.pt`` they were
  exported from (a stale export is refused by :func:`use_onnx`) and what inference needs besides
  the weights (the preset, the objects' normalisation, the detector's stride).

Opset 17 with torch's TorchScript exporter (``dynamo=False``): it exports both networks in seconds
with dynamic batch and image sizes and needs nothing beyond ``onnx``; torch's newer exporter gives
the same graphs (outputs equal to 1e-6) but takes minutes on two cores and needs ``onnxscript``.

:class:`OnnxEstimator` is the :class:`~brave6d.evaluation.learned.LearnedEstimator` with its two
networks in ONNX Runtime (CPU) and its peak finding in NumPy: it reads only the export folder and
never imports torch (the robot's computer needs numpy, OpenCV, Open3D and onnxruntime); everything
else (resizing, crops, PnP, ICP) is the same code, so the estimates agree with torch's to the
networks' float rounding (docs/BENCHMARKS.md: accuracy and milliseconds per estimate both ways).
:func:`use_onnx` makes one from a torch estimator's model folder, checking the export is of that model.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError
from brave6d.evaluation.learned.crops import normalise
from brave6d.evaluation.learned.inference import MAX_DETECTIONS, Array, LearnedEstimator
from brave6d.evaluation.learned.model_file import LearnedModel, ObjectNorm

#: ONNX opset of the exported graphs.
OPSET = ONNX_OPSET = 17
FOLDER = "onnx"
INDEX_FORMAT = "brave6d-learned-onnx/1"
DETECTOR_FILE, POSE_FILE, INDEX_FILE = "detector.onnx", "coordinate_net.onnx", "onnx.json"
DETECTOR_IO = (("image",), ("heatmap", "box_size", "offset"))
POSE_IO = (("crops", "class_index"), ("coords", "mask"))
#: What the tests hold ONNX Runtime's outputs to, against torch's on the same inputs (max abs difference
#: of logits, log sizes, offsets and coordinates, all O(1) numbers).
TOLERANCE = 1e-4
#: An export index larger than this is refused unread (it holds a preset and a few objects).
MAX_INDEX_BYTES = 1 << 20


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
    from brave6d.evaluation.learned.networks import DETECTOR_STRIDE

    objects = {str(o.obj_id): {"class_index": o.class_index, "centre_mm": [float(x) for x in o.centre_mm],
                               "radius_mm": o.radius_mm, "diameter_mm": o.diameter_mm}
               for o in estimator.model.objects.values()}
    index = {"format": INDEX_FORMAT, "opset": OPSET, "model_sha256": _sha256(model_dir / MODEL),
             "detector": {"file": DETECTOR_FILE, "inputs": list(DETECTOR_IO[0]), "outputs": list(DETECTOR_IO[1])},
             "coordinate_net": {"file": POSE_FILE, "inputs": list(POSE_IO[0]), "outputs": list(POSE_IO[1])},
             "detector_stride": DETECTOR_STRIDE, "preset": estimator.model.preset, "objects": objects,
             "inputs_key": estimator.model.inputs_key}
    atomic_write_text(folder / INDEX_FILE, json.dumps(index, indent=1) + "\n")
    return OnnxExport(folder, folder / DETECTOR_FILE, folder / POSE_FILE, OPSET)


class _OrtNetwork:
    """An ONNX Runtime session on the CPU: arrays in (by the graph's input names), arrays out."""

    def __init__(self, path: Path, inputs: tuple[str, ...], threads: int | None) -> None:
        ort = _onnxruntime()
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = int(threads)
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        self.inputs = inputs

    def __call__(self, *arrays: NDArray[Any]) -> list[NDArray[Any]]:
        return list(self.session.run(None, dict(zip(self.inputs, arrays))))


def _onnxruntime() -> Any:
    from brave6d.core.extras import require

    return require("onnxruntime", "onnx", "the learned estimator on ONNX Runtime")


def read_index(folder: Path | str, model_dir: Path | str | None = None) -> dict[str, Any]:
    """``folder/onnx.json`` (size-bounded), with both graphs present; refused in one line naming the
    file and field when it is missing, malformed, or (``model_dir`` given) of another ``model.pt``."""
    from brave6d.evaluation.learned.model_file import MODEL

    folder = Path(folder)
    path = folder / INDEX_FILE
    again = f"brave6d learn export-onnx {model_dir if model_dir is not None else 'MODEL_DIR'}"
    if not path.is_file():
        raise DataError(f"{path}: not found (write it with: {again})")
    if path.stat().st_size > MAX_INDEX_BYTES:
        raise DataError(f"{path}: {path.stat().st_size} bytes, more than an export index holds ({MAX_INDEX_BYTES})")
    try:
        index = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(index, dict) or index.get("format") != INDEX_FORMAT:
            raise ValueError(f"field 'format' is not {INDEX_FORMAT!r}")
        for field in ("model_sha256", "preset", "objects", "detector_stride"):
            if field not in index:
                raise KeyError(field)
    except (ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{path}: not an ONNX export index ({type(exc).__name__}: {exc}; export again: {again})") from None
    if model_dir is not None and str(index["model_sha256"]) != _sha256(Path(model_dir) / MODEL):
        raise DataError(f"{path}: field 'model_sha256' does not match {Path(model_dir) / MODEL}: the export "
                        f"is of another model (export again: {again})")
    for name in (DETECTOR_FILE, POSE_FILE):
        if not (folder / name).is_file():
            raise DataError(f"{folder / name}: not found (export again: {again})")
    return index


def _sigmoid(x: NDArray[np.float32]) -> NDArray[np.float32]:
    return (1.0 / (1.0 + np.exp(-x))).astype(np.float32)  # type: ignore[no-any-return]


def _max_pool3(p: NDArray[np.float32]) -> NDArray[np.float32]:
    """3x3 max over each (C, H, W) map's neighbourhood (stride 1, outside = -inf): torch's
    ``max_pool2d(p, 3, 1, 1)``."""
    padded = np.pad(p, ((0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
    h, w = p.shape[1:]
    return np.max([padded[:, dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)], axis=0)  # type: ignore[no-any-return]


class OnnxEstimator(LearnedEstimator):
    """The learned estimator on an ONNX export (module docstring): the same methods and answers as
    :class:`~brave6d.evaluation.learned.LearnedEstimator`, without torch."""

    def __init__(self, folder: Path | str, threads: int | None = None, model_dir: Path | str | None = None) -> None:
        index = read_index(folder, model_dir)
        try:
            objects = {int(k): ObjectNorm(int(k), int(v["class_index"]), np.asarray(v["centre_mm"], dtype=np.float64),
                                          float(v["radius_mm"]), float(v["diameter_mm"]))
                       for k, v in index["objects"].items()}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise DataError(f"{Path(folder) / INDEX_FILE}: field 'objects' is malformed ({type(exc).__name__}: {exc})") \
                from None
        self._init_state(LearnedModel(dict(index["preset"]), objects, {}, {}, str(index.get("inputs_key", ""))))
        self.runtime = "onnxruntime"
        self.device = "cpu"
        self.stride = int(index["detector_stride"])
        self.detector = _OrtNetwork(Path(folder) / DETECTOR_FILE, DETECTOR_IO[0], threads)
        self.pose = _OrtNetwork(Path(folder) / POSE_FILE, POSE_IO[0], threads)

    @classmethod
    def from_export(cls, folder: Path | str, models_dir: Path | str | None = None,
                    threads: int | None = None) -> OnnxEstimator:
        """The estimator of the export in ``folder``; ``models_dir`` (a BOP models folder) gives it the
        surfaces, as :meth:`LearnedEstimator.load`'s. ``threads``: ONNX Runtime's (None: its default)."""
        estimator = cls(folder, threads)
        if models_dir is not None:
            estimator.add_surfaces(models_dir)
        return estimator

    def _detector_peaks(self, work: NDArray[np.uint8], min_score: float, obj_id: int | None
                        ) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], int]:
        heat, size, offset = self.detector(normalise(work)[None])
        p = _sigmoid(heat[0])
        if obj_id is not None:
            keep = np.zeros((p.shape[0], 1, 1), dtype=np.float32)
            keep[self.model.objects[int(obj_id)].class_index] = 1.0
            p = p * keep
        peaks = (p == _max_pool3(p)) & (p >= min_score)
        scores = p[peaks]
        order = np.argsort(-scores, kind="stable")[:MAX_DETECTIONS]
        return np.argwhere(peaks)[order], scores[order], size[0], offset[0], self.stride

    def _coordinates(self, crop: NDArray[np.uint8], class_index: int) -> tuple[Array, Array]:
        coords, mask = self.pose(normalise(crop)[None], np.array([class_index], dtype=np.int64))
        return coords[0].astype(np.float64), _sigmoid(mask[0, 0]).astype(np.float64)


def use_onnx(estimator: Any, model_dir: Path | str, onnx_dir: Path | str | None = None,
             threads: int | None = None) -> OnnxEstimator:
    """An :class:`OnnxEstimator` on ``onnx_dir`` (default ``model_dir/onnx``) in place of ``estimator``
    (loaded from ``model_dir``: the export must be of its ``model.pt``, else refused in one line),
    with its surfaces and settings."""
    onnx = OnnxEstimator(Path(onnx_dir) if onnx_dir is not None else Path(model_dir) / FOLDER, threads, model_dir)
    onnx.surfaces, onnx.silhouettes = dict(estimator.surfaces), dict(estimator.silhouettes)
    onnx.icp_max_points, onnx.detect_scales = estimator.icp_max_points, estimator.detect_scales
    onnx.upscaled_max_box_px = estimator.upscaled_max_box_px
    onnx.mask_area_distance, onnx.crop_zooms = estimator.mask_area_distance, estimator.crop_zooms
    return onnx

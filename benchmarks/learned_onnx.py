"""The learned estimator with its networks in torch and in ONNX Runtime (CPU), side by side: the same
held-out split scored both ways (``brave6d learn heldout``'s figures) and the milliseconds each way.

    python benchmarks/learned_onnx.py MODEL_DIR MODELS_DIR HELDOUT_PBR --out DIR [--max-images N]
        [--pnp-hypotheses H]

Exports the model into ``DIR/onnx`` (``brave6d learn export-onnx``), then scores every image of
``HELDOUT_PBR`` (a split the model never trained on) three times: torch, ONNX Runtime, and torch
with its networks' outputs moved by seeded noise of 1e-6 (the size of the two runtimes' float
differences): pose AR of the four held-out variants and detection AP, and how many estimates of the
same instance differ between the runs (by > 1e-3 and > 1 deg or mm, per variant; the robust PnP is
continuous in its inputs, so what still differs comes after it or from a moved box);
``--pnp-hypotheses`` prices the PnP's fixed hypothesis count. Timing: for every true box, one
estimate (coordinate net on three zooms + PnP, RGB and depth poses from the same crops) with each
runtime in turn, and one detector pass per image each, interleaved so both see the same machine
load; medians. Both at their libraries' default thread counts. Writes ``DIR/onnx_vs_torch.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads (see brave6d.core.runtime)

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(ROOT / "src"))

REPORT_FILE = "onnx_vs_torch.json"


def _pose_differences(a: Any, b: Any) -> dict[str, Any]:
    """The largest rotation (deg) and translation (mm) difference between the two runs' estimates of
    the same instance and variant, how many estimates one run has that the other lacks, and how many
    differ by more than 1e-3 deg or 1e-3 mm, and by more than 1 deg or 1 mm."""
    worst_deg, worst_mm, unmatched, over_1e3, over_1 = 0.0, 0.0, 0, 0, 0
    per_variant: dict[str, str] = {}
    for variant, ests in a.estimates.items():
        before = (over_1e3, over_1, worst_deg, worst_mm)
        worst_deg, worst_mm = 0.0, 0.0
        other = {gt: e for gt, e in b.estimates[variant]}
        for gt, e in ests:
            f = other.pop(gt, None)
            if f is None:
                unmatched += 1
                continue
            cos = (np.trace(np.asarray(e.R).T @ np.asarray(f.R)) - 1.0) / 2.0
            deg = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
            mm = float(np.linalg.norm(np.asarray(e.t).reshape(3) - np.asarray(f.t).reshape(3)))
            worst_deg, worst_mm = max(worst_deg, deg), max(worst_mm, mm)
            over_1e3 += int(deg > 1e-3 or mm > 1e-3)
            over_1 += int(deg > 1.0 or mm > 1.0)
        unmatched += len(other)
        per_variant[variant] = (f"{over_1e3 - before[0]} > 1e-3, {over_1 - before[1]} > 1 (at most {worst_deg:.3g} deg, "
                                f"{worst_mm:.3g} mm)")
        worst_deg, worst_mm = max(worst_deg, before[2]), max(worst_mm, before[3])
    return {"max_rotation_deg": worst_deg, "max_translation_mm": worst_mm, "unmatched_estimates": unmatched,
            "estimates_over_1e-3": over_1e3, "estimates_over_1": over_1, "per_variant": per_variant}


class _Noisy:
    """A torch network whose outputs are moved by seeded uniform noise of ``size``."""

    def __init__(self, module: Any, size: float, seed: int) -> None:
        import torch

        self.module, self.size, self.generator = module, size, torch.Generator().manual_seed(seed)

    def __call__(self, *tensors: Any) -> tuple[Any, ...]:
        import torch

        out = self.module(*tensors)
        return tuple(o + self.size * (2 * torch.rand(o.shape, generator=self.generator) - 1) for o in out)


def _timings(estimators: dict[str, Any], data: Any, images: list[int]) -> dict[str, dict[str, float]]:
    """Median ms per estimate and per detector pass of each estimator, calls interleaved."""
    per: dict[str, dict[str, list[float]]] = {k: {"estimate": [], "detect": []} for k in estimators}
    for i in images:
        record = data.images[i]
        rgb, K = record.rgb_crop, record.K_crop
        for name, e in estimators.items():
            t0 = time.perf_counter()
            e.detect(rgb, K, min_score=0.05)
            per[name]["detect"].append(time.perf_counter() - t0)
        for j in record.instances:
            inst = data.instances[j]
            for name, e in estimators.items():
                t0 = time.perf_counter()
                try:
                    e.estimate_both(rgb, K, inst.obj_id, inst.box_crop, None, 1.0)
                except Exception:  # noqa: BLE001 - a refusal costs its time too
                    pass
                per[name]["estimate"].append(time.perf_counter() - t0)
    return {name: {f"ms_per_{k}": 1000.0 * float(np.median(v)) for k, v in d.items()} | {"estimates": len(d["estimate"])}
            for name, d in per.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="a trained model folder (model.pt)")
    parser.add_argument("models", type=Path, help="BOP models folder")
    parser.add_argument("heldout_pbr", type=Path, help="a split never trained on (every image is scored)")
    parser.add_argument("--out", type=Path, required=True, help="folder of onnx/ and onnx_vs_torch.json")
    parser.add_argument("--max-images", type=int, default=None, help="the first N images only")
    parser.add_argument("--pnp-hypotheses", type=int, default=None,
                        help="robust PnP's fixed hypothesis count (default: the estimator's PNP_HYPOTHESES)")
    args = parser.parse_args(argv)
    if args.pnp_hypotheses is not None:
        from brave6d.evaluation.learned import inference

        inference.PNP_HYPOTHESES = args.pnp_hypotheses

    from brave6d.core.atomic import atomic_write_json
    from brave6d.evaluation.learned import LearnedEstimator, load_training_data, read_model, score_heldout
    from brave6d.evaluation.learned.onnx_export import export_onnx, use_onnx

    t0 = time.perf_counter()
    export = export_onnx(args.model, args.out / "onnx")
    export_s = time.perf_counter() - t0
    preset = read_model(args.model).preset
    data = load_training_data(args.heldout_pbr, args.models, int(preset["work_width"]), 2, show_progress=False,
                              crop_width=int(preset.get("crop_source_width", preset["work_width"])))
    images = list(range(len(data.images)))[:args.max_images]
    estimators = {name: LearnedEstimator.load(args.model, models_dir=args.models)
                  for name in ("torch", "onnxruntime", "torch + 1e-6 noise")}
    estimators["onnxruntime"] = use_onnx(estimators["onnxruntime"], args.model, export.folder)
    noisy = estimators["torch + 1e-6 noise"]
    noisy.detector, noisy.pose = _Noisy(noisy.detector, 1e-6, 1), _Noisy(noisy.pose, 1e-6, 2)
    runs, rows = {}, []
    for name, estimator in estimators.items():
        held = score_heldout(estimator, data, args.models, show_progress=False, images=images, keep_estimates=True)
        runs[name] = held
        rows.append({"runtime": name, "pose_ar": dict(held.pose_ar), "ap": dict(held.ap), "recall": dict(held.recall)})
        print(json.dumps(rows[-1]), flush=True)
    timing = _timings({k: estimators[k] for k in ("torch", "onnxruntime")}, data, images)
    diffs = {name: _pose_differences(runs["torch"], runs[name]) for name in ("onnxruntime", "torch + 1e-6 noise")}
    from brave6d.evaluation.learned import inference

    report = {"model": str(args.model), "heldout_pbr": str(args.heldout_pbr), "images": len(images),
              "pnp_hypotheses": getattr(inference, "PNP_HYPOTHESES", None),
              "opset": export.opset, "export_seconds": export_s, "rows": rows, "timing": timing,
              "pose_differences_from_torch": diffs, "load_average": os.getloadavg()[0], "cpus": os.cpu_count()}
    path = args.out / REPORT_FILE
    atomic_write_json(path, report)
    print("| runtime | AR true box RGB / + depth | AR detected RGB / + depth | mean AP | ms per estimate | ms per detector pass |")
    for r in rows:
        ar, t = r["pose_ar"], timing.get(r["runtime"], {})
        print(f"| {r['runtime']} | {ar['true_box_rgb']:.4f} / {ar['true_box_depth']:.4f} | {ar['detected_rgb']:.4f} / "
              f"{ar['detected_depth']:.4f} | {np.mean(list(r['ap'].values())):.4f} | "
              f"{t.get('ms_per_estimate', float('nan')):.1f} | {t.get('ms_per_detect', float('nan')):.1f} |")
    for name, d in diffs.items():
        print(f"poses torch vs {name}: at most {d['max_rotation_deg']:.3g} deg, {d['max_translation_mm']:.3g} mm; "
              f"{d['estimates_over_1e-3']} estimates differ by > 1e-3 deg or mm, {d['estimates_over_1']} by > 1 deg or mm; "
              f"{d['unmatched_estimates']} estimates in one run only; per variant: {d['per_variant']}")
    print(f"export {export_s:.1f} s (opset {export.opset}); load average {report['load_average']:.1f} on "
          f"{report['cpus']} CPUs")
    print(f"written: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

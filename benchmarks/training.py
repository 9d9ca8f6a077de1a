"""Accuracy against time for 3DGS training: holdout PSNR/SSIM at several points of a run.

Trains a scene (default: the demo scene ``runs/demo/scene``) with a preset and evaluates the
holdout views every ``--every`` steps (evaluation time is excluded from the training clock),
then writes a JSON table and a PNG with holdout PSNR against steps and against training time
(default: ``<scene>/splat/benchmark_training.{json,png}``). No checkpoint, PLY or metrics.json is
written, so a trained splat in the scene stays as it is; COLMAP points are reused when
``sparse/0`` matches the frames.

    python benchmarks/training.py [SCENE_DIR] [--preset fast] [--steps N] [--every K] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))

DEFAULT_SCENE = REPO / "runs" / "demo" / "scene"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene_dir", type=Path, nargs="?", default=DEFAULT_SCENE,
                   help="scene directory (default: %(default)s)")
    p.add_argument("--preset", choices=["fast", "default", "quality"], default="fast")
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--every", type=int, default=None, help="evaluate every K steps (default: steps / 10)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    p.add_argument("--init", choices=["auto", "colmap", "depth", "random"], default="auto")
    p.add_argument("--no-sparse-model", action="store_true",
                   help="do not write the scene's sparse/0 (with --init depth or random: no pycolmap needed)")
    p.add_argument("--json", type=Path, default=None, help="output JSON (default: <scene>/splat/benchmark_training.json)")
    p.add_argument("--png", type=Path, default=None, help="output plot (default: next to the JSON)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from brave6d.core.atomic import atomic_write
    from brave6d.core.layout import SceneDir
    from brave6d.core.progress import format_table, setup_logging
    from brave6d.training.colmap_init import initial_points
    from brave6d.training.views import load_scene
    from brave6d.training.holdout_eval import evaluate_holdout, json_safe, peak_memory_mb, write_metrics
    from brave6d.training.model import GaussianModel
    from brave6d.training.pipeline import require_capture
    from brave6d.training.presets import get_preset
    from brave6d.training.trainer import Trainer, resolve_device

    setup_logging(1)
    log = logging.getLogger("benchmarks.training")
    scene = SceneDir(args.scene_dir)
    require_capture(scene)
    preset = get_preset(args.preset)
    if args.steps:
        preset = preset.with_steps(args.steps)
    every = args.every or max(1, preset.steps // 10)
    preset = preset.with_values(eval_every=every, time_budget_s=None)  # the benchmark times the whole schedule: no budget
    device = resolve_device(args.device)
    t0 = time.perf_counter()
    data = load_scene(scene, preset.downscale)
    start = preset.initialisation
    init = initial_points(scene, data, max_points=start.max_init_points, seed=preset.seed, method=args.init,
                          write_sparse=not args.no_sparse_model)
    init_s = time.perf_counter() - t0
    frame = data.training_frame()  # training in the scene's frame, as brave6d train does
    data = data.in_frame(frame)
    model = GaussianModel.from_points(frame.points(init.points), init.colors, start.sh_degree, start.init_opacity,
                                      start.init_scale, device=device)
    rows: list[dict[str, Any]] = []

    def evaluate(trainer: Trainer) -> float:
        m = evaluate_holdout(trainer.model, data)
        rows.append({"step": trainer.step, "train_time_s": trainer.elapsed, "holdout_psnr": m.psnr,
                     "holdout_ssim": m.ssim, "num_gaussians": trainer.model.num_gaussians,
                     "per_level_psnr": {str(k): v["psnr"] for k, v in m.per_level.items()}})
        log.info("step %d (%.0f s): holdout PSNR %.2f dB, SSIM %.4f, %d Gaussians", trainer.step, trainer.elapsed,
                 m.psnr, m.ssim, trainer.model.num_gaussians)
        return m.psnr

    trainer = Trainer(data, model, preset, None, device, eval_callback=evaluate)
    evaluate(trainer)
    result = trainer.train()
    if rows[-1]["step"] != result.steps:
        evaluate(trainer)
    out_json = args.json or scene.splat_dir / "benchmark_training.json"
    out_png = args.png or out_json.with_suffix(".png")
    report = {"scene": str(scene.root), "preset": preset.name, "device": str(device), "steps": result.steps,
              "init": {"source": init.source, "points": len(init), "seconds": init_s},
              "image_size": [data.camera.width, data.camera.height], "n_train": len(data.train),
              "n_holdout": len(data.test), "memory": peak_memory_mb(device), "points": rows}
    write_metrics(out_json, report)
    _plot(out_png, rows, f"{scene.root.name}: preset {preset.name} on {device}", atomic_write)
    print(format_table(["step", "train s", "PSNR", "SSIM", "#G"],
                       [(r["step"], f"{r['train_time_s']:.0f}", f"{r['holdout_psnr']:.2f}", f"{r['holdout_ssim']:.4f}",
                         r["num_gaussians"]) for r in rows]))
    print(f"\n{out_json}\n{out_png}")
    json.dumps(json_safe(report))
    return 0


def _plot(path: Path, rows: list[dict[str, Any]], title: str, atomic_write: Any) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6))
    steps = [r["step"] for r in rows]
    secs = [r["train_time_s"] for r in rows]
    psnrs = [r["holdout_psnr"] for r in rows]
    a1.plot(steps, psnrs, "o-")
    a1.set_xlabel("steps")
    a2.plot(secs, psnrs, "o-")
    a2.set_xlabel("training time [s]")
    for a in (a1, a2):
        a.set_ylabel("holdout PSNR [dB]")
        a.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    atomic_write(path, lambda handle: fig.savefig(handle, format="png", dpi=110))
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())

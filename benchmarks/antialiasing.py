"""Anti-aliasing benchmark (issue 34): what Mip-Splatting's filters cost in training time and what
they buy closer to and farther from the scene than the training views.

A random Gaussian scene (scales from 0.3 to 6 mm, so that it has detail below a training pixel)
is rendered supersampled (3x3 per pixel, box-averaged: an alias-free truth) from one ring of
training cameras at ``--train-distance``. Two trainings from the same start, ``classic`` and
``mip`` (the ``fast`` preset scaled to ``--steps`` with ``antialiasing`` set), run interleaved
step by step on the CPU so that both see the same machine load; each step's wall time is kept
and the medians are compared. Then both splats render (each as it was trained) at closer and
farther distances and are scored against the supersampled truth (PSNR over the image).

    python benchmarks/antialiasing.py                  # ~5 min on 2 cores
    python benchmarks/antialiasing.py --steps 200      # smoke run
    python benchmarks/antialiasing.py --json out.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see benchmarks/rasterizer.py

import numpy as np  # noqa: E402
import torch  # noqa: E402

from brave6d.core.camera import PinholeCamera  # noqa: E402
from brave6d.training import rasterize  # noqa: E402
from brave6d.training.holdout_eval import render_view  # noqa: E402
from brave6d.training.model import GaussianModel  # noqa: E402
from brave6d.training.presets import FAST  # noqa: E402
from brave6d.training.toy_scenes import ring_poses  # noqa: E402
from brave6d.training.trainer import Trainer  # noqa: E402
from brave6d.training.views import TrainingData, View  # noqa: E402

MODES = ("classic", "mip")


def truth_scene(n: int, seed: int = 0, extent: float = 0.05) -> dict[str, torch.Tensor]:
    """Activated parameters of ``n`` Gaussians with log-uniform scales from 0.3 to 6 mm."""
    g = torch.Generator().manual_seed(seed)
    log_s = math.log(3e-4) + (math.log(6e-3) - math.log(3e-4)) * torch.rand(n, 3, generator=g)
    return {"means": (torch.rand(n, 3, generator=g) * 2 - 1) * extent * torch.tensor([1.0, 1.0, 0.3]),
            "quats": torch.randn(n, 4, generator=g), "scales": torch.exp(log_s),
            "opacities": torch.rand(n, generator=g) * 0.5 + 0.45, "colors": torch.rand(n, 3, generator=g)}


@torch.no_grad()
def render_truth(scene: dict[str, torch.Tensor], camera: PinholeCamera, pose: np.ndarray, ss: int = 3) -> np.ndarray:
    """uint8 image of the scene, rendered at ``ss`` x the resolution and box-averaged (alias-free)."""
    big = camera.scaled(camera.width * ss, camera.height * ss)
    viewmat = torch.from_numpy(np.linalg.inv(pose)).float()[None]
    rgb, _, _, _ = rasterize(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                             viewmat, torch.from_numpy(big.K).float()[None], big.width, big.height,
                             backgrounds=torch.full((1, 3), 0.0))
    img = rgb[0].reshape(camera.height, ss, camera.width, ss, 3).mean(dim=(1, 3))
    return (img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) / 255 - b.astype(np.float64) / 255) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def render_step_ms(trainer: Trainer, data: TrainingData, reps: int) -> dict[str, float]:
    """Median ms of one training render + backward of the same Gaussians without and with the
    filters (3D filter computed from the training cameras, then the 2D mip filter), interleaved."""
    from brave6d.training import apply_filter_3d, compute_filter_3d

    m = trainer.model
    cam = data.camera
    f3d = compute_filter_3d(m.means, trainer.viewmats, trainer.K, cam.width, cam.height)
    out: dict[str, list[float]] = {mode: [] for mode in MODES}
    for r in range(reps):
        for mode in (MODES if r % 2 == 0 else MODES[::-1]):
            t0 = time.perf_counter()
            scales, opac = m.scales(), m.opacities()
            if mode == "mip":
                scales, opac = apply_filter_3d(scales, opac, f3d)
            rgb, _, _, _ = rasterize(m.means, m.quats, scales, opac, m.sh_coeffs(), trainer.viewmats[r % 4][None],
                                     trainer.K[None], cam.width, cam.height, sh_degree=m.sh_degree,
                                     antialiased=mode == "mip")
            rgb.sum().backward()
            out[mode].append(time.perf_counter() - t0)
            for p in m.params.values():
                p.grad = None
    return {mode: 1000 * statistics.median(v) for mode, v in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--size", default="160x120", help="image size WxH")
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--train-distance", type=float, default=0.3)
    ap.add_argument("--distances", default="0.1,0.15,0.3,0.6,1.0")
    ap.add_argument("--reps", type=int, default=21, help="repetitions of the same-model timing")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    w, h = (int(x) for x in args.size.split("x"))
    camera = PinholeCamera.from_hfov(w, h, 60.0)
    scene = truth_scene(args.gaussians)
    train_poses = [p for _, _, p in ring_poses([args.train_distance], 16, elevation_deg=50)]
    views = [View(i, f"t{i:02d}", 0, args.train_distance, p, render_truth(scene, camera, p))
             for i, p in enumerate(train_poses)]
    data = TrainingData(camera, views, views[:1])
    rng = np.random.default_rng(1)
    start = scene["means"].numpy() + rng.normal(0, 0.002, scene["means"].shape)
    trainers = {}
    for mode in MODES:
        preset = FAST.with_steps(args.steps).with_values(name=f"bench-{mode}", antialiasing=mode, time_budget_s=None)
        model = GaussianModel.from_points(start, scene["colors"].numpy(), sh_degree=preset.initialisation.sh_degree,
                                          init_opacity=0.3)
        trainers[mode] = Trainer(data, model, preset, show_progress=False)
    times: dict[str, list[float]] = {m: [] for m in MODES}
    for step in range(args.steps):
        for mode in (MODES if step % 2 == 0 else MODES[::-1]):  # alternate who goes first
            t0 = time.perf_counter()
            trainers[mode].train_step()
            times[mode].append(time.perf_counter() - t0)
    for t in trainers.values():
        t.refresh_filter_3d(force=True)
    same_model = render_step_ms(trainers["classic"], data, reps=args.reps)
    distances = [float(x) for x in args.distances.split(",")]
    table: dict[str, dict[str, float]] = {m: {} for m in MODES}
    for d in distances:
        poses = [p for _, _, p in ring_poses([d], 12, elevation_deg=50)][1::2]  # between the training azimuths
        truths = [render_truth(scene, camera, p) for p in poses]
        for mode, trainer in trainers.items():
            scores = []
            for i, (p, gt) in enumerate(zip(poses, truths)):
                img = render_view(trainer.model, View(i, f"e{i}", 0, d, p, gt), data)
                scores.append(psnr((img.numpy() * 255 + 0.5).astype(np.uint8), gt))
            table[mode][f"{d:g}"] = statistics.median(scores)
    result = {
        "steps": args.steps, "size": [w, h], "gaussians_truth": args.gaussians, "train_distance_m": args.train_distance,
        "torch_threads": torch.get_num_threads(),
        "step_ms_median": {m: 1000 * statistics.median(times[m]) for m in MODES},
        "final_gaussians": {m: trainers[m].model.num_gaussians for m in MODES},
        "render_backward_ms_same_model": same_model,
        "psnr_by_distance_db": table,
    }
    print(f"{args.steps} steps at {w}x{h}, trained at {args.train_distance} m, {torch.get_num_threads()} threads")
    for m in MODES:
        print(f"  {m:8s} step median {result['step_ms_median'][m]:7.1f} ms, {result['final_gaussians'][m]} Gaussians")
    n_same = trainers["classic"].model.num_gaussians
    print(f"  render+backward of the same {n_same} Gaussians (median of {args.reps}): "
          + ", ".join(f"{m} {same_model[m]:.1f} ms" for m in MODES))
    print("  PSNR (dB, median of 6 views) by distance: " + "  ".join(f"{d:g} m" for d in distances))
    for m in MODES:
        print(f"  {m:8s} " + "  ".join(f"{table[m][f'{d:g}']:6.2f}" for d in distances))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

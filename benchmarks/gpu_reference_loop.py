"""gsplat's minimal training loop beside the project's trainer: the yardstick of issue #46 item 3.

Both train the same scene (a ``brave6d`` scene folder, e.g. ``gpu_checks``' synthetic textured plane)
from the same seed, initial points and schedule (the ``fast`` preset's learning rates, SH schedule and
densification thresholds), in one process, one after the other:

* **project**: :class:`brave6d.training.trainer.Trainer` (on a GPU its lean step);
* **reference**: what gsplat's ``simple_trainer`` does per step and nothing else: one
  ``gsplat.rasterization`` call, L1 + D-SSIM (the same SSIM function, as gsplat's fallback when
  ``fused_ssim`` is absent), ``backward``, one fused Adam per parameter, gsplat's own
  ``DefaultStrategy`` with the preset's thresholds. On the CPU (wiring only) the project's CPU
  rasterizer stands in for ``gsplat.rasterization`` (its ``info`` is ``DefaultStrategy``'s).

Per loop: ms per step over steps ``--from-step``..``--steps`` with a device sync at each end; host
syncs per step counted with ``torch.cuda.set_sync_debug_mode`` over ``--sync-steps`` steps just
before that window (GPU only); holdout PSNR at the end.

    python benchmarks/gpu_reference_loop.py SCENE [--steps 2000] [--from-step 300] [--device cuda]
        [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))

import torch  # noqa: E402


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class SyncCounter:
    """Counts the host-device synchronisations inside the block (CUDA's sync debug mode warns once
    per sync); on the CPU there are none to count (``count`` stays None)."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.count: int | None = None

    def __enter__(self) -> SyncCounter:
        if self.device.type == "cuda":
            self._catch = warnings.catch_warnings(record=True)
            self._log = self._catch.__enter__()
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.device.type == "cuda":
            torch.cuda.set_sync_debug_mode("default")
            self._catch.__exit__(*exc)
            self.count = sum("synchroniz" in str(w.message) for w in self._log)


def load(scene_dir: Path, steps: int, device: torch.device) -> tuple[Any, Any, Any]:
    """The scene's training data, the fast preset cut to ``steps`` and the initial model."""
    from brave6d.core.layout import SceneDir
    from brave6d.training.colmap_init import initial_points
    from brave6d.training.model import GaussianModel
    from brave6d.training.presets import get_preset
    from brave6d.training.views import load_scene

    preset = get_preset("fast").with_steps(steps).with_values(time_budget_s=None)
    scene = SceneDir(scene_dir)
    data = load_scene(scene, preset.downscale)
    start = preset.initialisation
    init = initial_points(scene, data, max_points=start.max_init_points, seed=preset.seed, method="random",
                          write_sparse=False)  # no sparse/0 (nor pycolmap) for a benchmark
    frame = data.training_frame()  # training in the scene's frame, as brave6d train does
    model = GaussianModel.from_points(frame.points(init.points), init.colors, start.sh_degree, start.init_opacity,
                                      start.init_scale, device=device)
    return data.in_frame(frame), preset, model


def run_project(data: Any, preset: Any, model: Any, device: torch.device, first: int, sync_steps: int
                ) -> dict[str, Any]:
    from brave6d.training.holdout_eval import evaluate_holdout
    from brave6d.training.trainer import Trainer, set_seed

    set_seed(preset.seed)
    trainer = Trainer(data, model, preset, None, device, show_progress=False)
    trainer.train(max_steps=first)
    with SyncCounter(device) as counter:
        trainer.train(max_steps=first + sync_steps)
    sync(device)
    t0 = time.perf_counter()
    trainer.train()
    sync(device)
    window = trainer.step - first - sync_steps
    return {"ms_per_step": 1000 * (time.perf_counter() - t0) / max(window, 1), "timed_steps": window,
            "syncs_per_step": None if counter.count is None else counter.count / sync_steps,
            "lean": trainer.lean, "gaussians": trainer.model.num_gaussians,
            "holdout_psnr": evaluate_holdout(trainer.model, data).psnr}


def run_reference(data: Any, preset: Any, model: Any, device: torch.device, first: int, sync_steps: int
                  ) -> dict[str, Any]:
    """gsplat's minimal loop (see the module doc) on the same start."""
    from gsplat.strategy import DefaultStrategy

    from brave6d.training.holdout_eval import evaluate_holdout
    from brave6d.training.losses import ssim
    from brave6d.training.model import PARAM_NAMES, GaussianModel
    from brave6d.training.trainer import base_lrs, means_lr, set_seed, sh_degree_at

    if device.type == "cuda":
        from gsplat import rasterization

        def draw(**kw: Any) -> tuple[Any, Any, dict[str, Any]]:
            return rasterization(**kw, packed=False)
    else:
        from brave6d.training.rasterizer import rasterize

        def draw(**kw: Any) -> tuple[Any, Any, dict[str, Any]]:
            mode, deg = kw.pop("rasterize_mode"), kw.pop("sh_degree")
            rgb, _, alpha, info = rasterize(*kw.values(), sh_degree=deg, antialiased=mode == "antialiased",
                                            validate=False)
            return rgb, alpha, info

    set_seed(preset.seed)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(model.params[k].detach().clone()) for k in PARAM_NAMES})
    extent = data.scene_extent()
    lrs = {"means": means_lr(0, preset, extent), **base_lrs(preset)}
    optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": lrs[k], "name": k}], eps=1e-15, fused=True)
                  for k in PARAM_NAMES}
    d = preset.densification
    strategy = DefaultStrategy(prune_opa=d.prune_opa, grow_grad2d=d.grow_grad2d, grow_scale3d=d.grow_scale3d,
                               prune_scale3d=d.prune_scale3d, refine_start_iter=d.refine_start,
                               refine_stop_iter=d.refine_stop, refine_every=d.refine_every,
                               reset_every=d.reset_every, verbose=False)
    state = strategy.initialize_state(scene_scale=extent)
    cam = data.camera
    K = torch.from_numpy(cam.K).float().to(device)
    K[:2, 2] += 0.5  # gsplat's pixel centres (the project's rasterizer shifts its K the same way)
    viewmats = torch.stack([torch.from_numpy(v.viewmat).float() for v in data.train]).to(device)
    images = [torch.from_numpy(v.image).to(device) for v in data.train]
    mode = "antialiased" if preset.antialias.antialiasing == "mip" else "classic"
    order = torch.Generator().manual_seed(preset.seed)
    views: list[int] = []
    lam = preset.loss.ssim_lambda

    def step_once(step: int) -> None:
        for g in optimizers["means"].param_groups:
            g["lr"] = means_lr(step, preset, extent)
        if not views:
            views.extend(torch.randperm(len(images), generator=order).tolist())
        i = views.pop()
        deg = sh_degree_at(step, preset, model.sh_degree)
        colors = torch.cat([params["sh0"], params["shN"]], 1)[:, : (deg + 1) ** 2]
        kw = dict(means=params["means"], quats=params["quats"], scales=torch.exp(params["scales"]),
                  opacities=torch.sigmoid(params["opacities"]), colors=colors, viewmats=viewmats[i: i + 1],
                  Ks=K[None], width=cam.width, height=cam.height, sh_degree=deg, rasterize_mode=mode)
        if device.type != "cuda":
            kw["Ks"] = torch.from_numpy(cam.K).float()[None]  # the project's own convention
        render, _, info = draw(**kw)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        gt = images[i].float() / 255.0
        loss = (1 - lam) * (render[0] - gt).abs().mean() + lam * (1 - ssim(render[0], gt))
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)

    for step in range(first):
        step_once(step)
    with SyncCounter(device) as counter:
        for step in range(first, first + sync_steps):
            step_once(step)
    sync(device)
    t0 = time.perf_counter()
    for step in range(first + sync_steps, preset.steps):
        step_once(step)
    sync(device)
    window = preset.steps - first - sync_steps
    trained = GaussianModel.from_tensors({k: v.detach() for k, v in params.items()}, model.sh_degree, device)
    return {"ms_per_step": 1000 * (time.perf_counter() - t0) / max(window, 1), "timed_steps": window,
            "syncs_per_step": None if counter.count is None else counter.count / sync_steps,
            "gaussians": int(params["means"].shape[0]), "holdout_psnr": evaluate_holdout(trained, data).psnr}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene_dir", type=Path)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--from-step", type=int, default=300, help="first step of the timed window")
    p.add_argument("--sync-steps", type=int, default=20, help="steps whose host syncs are counted (GPU)")
    p.add_argument("--device", choices=["cuda", "cpu"], default="cuda")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    if args.from_step + args.sync_steps >= args.steps:
        p.error("--from-step + --sync-steps must be below --steps")
    device = torch.device(args.device)
    data, preset, model = load(args.scene_dir, args.steps, device)
    report: dict[str, Any] = {"scene": str(args.scene_dir), "device": str(device), "steps": args.steps,
                              "window": [args.from_step + args.sync_steps, args.steps],
                              "image_size": [data.camera.width, data.camera.height]}
    if device.type == "cuda":
        report["card"] = torch.cuda.get_device_name(device)
    from brave6d.training.model import GaussianModel

    start = {k: v.detach().clone() for k, v in model.params.items()}  # the trainer trains its model in place
    report["project"] = run_project(data, preset, model, device, args.from_step, args.sync_steps)
    model = GaussianModel.from_tensors(start, model.sh_degree, device)
    report["reference"] = run_reference(data, preset, model, device, args.from_step, args.sync_steps)
    report["project_over_reference"] = report["project"]["ms_per_step"] / max(report["reference"]["ms_per_step"], 1e-9)
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

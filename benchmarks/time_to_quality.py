"""Time to quality of two training configurations, interleaved in one process (issue #22).

Trains configuration A and configuration B on the same scene, alternating chunks of ``--chunk``
steps (A, B, A, B, ...) so that both see the same machine load; each keeps its own wall and CPU
clocks of training steps only (holdout evaluation, every ``--every`` steps, is not counted). It
reports, per configuration: wall and CPU time to reach 27 dB and 30 dB holdout PSNR (and the
other configuration's final PSNR), final holdout PSNR and SSIM, Gaussians and Gaussians per
pixel, the model's parameter + optimiser memory, and the ratio that matters: **time for A to
reach its final PSNR / time for B to reach that PSNR** (> 1: B gets there faster). Times to a
level are interpolated linearly between evaluations; a level not reached is reported as such.
Writes a JSON table and one PNG with both PSNR-vs-time curves (what the report's training
section plots).

Configurations are ``NAME=PRESET[,field=value...]`` with any :class:`training.Preset` field:

    python benchmarks/time_to_quality.py runs/demo/scene [--a old=fast-3000] [--b new=fast,steps=1000] \\
        [--every 250] [--chunk 50] [--json out.json]

``fast-3000`` is the ``fast`` preset before issue 22 (:data:`training.presets.FAST_3000`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

LEVELS_DB = (27.0, 30.0)


def parse_config(text: str) -> tuple[str, str, dict[str, Any]]:
    """``NAME=PRESET[,field=value...]`` -> (name, preset name, overrides with typed values)."""
    from training import Preset

    name, _, rest = text.partition("=")
    if not name or not rest:
        raise SystemExit(f"--a/--b: expected NAME=PRESET[,field=value...], got {text!r}")
    preset, *pairs = rest.split(",")
    fields = {f.name: f.type for f in dataclasses.fields(Preset)}
    overrides: dict[str, Any] = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if key not in fields:
            raise SystemExit(f"{text}: {key!r} is not a Preset field (fields: {', '.join(sorted(fields))})")
        overrides[key] = None if value.lower() == "none" else json.loads(value) if value[:1] in "[{" else (
            float(value) if "." in value or "e" in value.lower() else int(value))
    return name, preset, overrides


def time_to(points: list[dict[str, float]], level: float, clock: str) -> float | None:
    """The ``clock`` time (``time_s`` or ``cpu_s``) at which holdout PSNR first reaches ``level``
    (linear between evaluations), or None when it never does."""
    for prev, cur in zip(points, points[1:]):
        if cur["psnr"] >= level:
            if prev["psnr"] >= level:
                return prev[clock]
            f = (level - prev["psnr"]) / (cur["psnr"] - prev["psnr"])
            return prev[clock] + f * (cur[clock] - prev[clock])
    if points and points[0]["psnr"] >= level:
        return points[0][clock]
    return None


class Run:
    """One configuration's trainer and its evaluations."""

    def __init__(self, name: str, preset: Any, scene: Any, every: int, device: Any, init_method: str) -> None:
        from training import GaussianModel, load_scene
        from training.colmap_init import initial_points
        from training.trainer import Trainer

        self.name, self.preset = name, preset.with_overrides(eval_every=every, time_budget_s=None)
        self.data = load_scene(scene, self.preset.downscale)
        init = initial_points(scene, self.data, max_points=self.preset.max_init_points, seed=self.preset.seed,
                              method=init_method)
        model = GaussianModel.from_points(init.points, init.colors, self.preset.sh_degree, self.preset.init_opacity,
                                          self.preset.init_scale, device=device)
        self.points: list[dict[str, float]] = []
        self.trainer = Trainer(self.data, model, self.preset, None, device, show_progress=False,
                               eval_callback=self.evaluate)
        self.evaluate(self.trainer)

    def evaluate(self, trainer: Any) -> float:
        from training import evaluate_holdout

        m = evaluate_holdout(trainer.model, self.data)
        self.points.append({"step": trainer.step, "time_s": trainer.elapsed, "cpu_s": trainer.cpu_elapsed,
                            "psnr": m.psnr, "ssim": m.ssim, "gaussians": trainer.model.num_gaussians})
        return m.psnr

    @property
    def done(self) -> bool:
        return self.trainer.step >= self.preset.steps

    def advance(self, chunk: int) -> None:
        self.trainer.train(max_steps=self.trainer.step + chunk)
        if self.done and self.points[-1]["step"] != self.trainer.step:
            self.evaluate(self.trainer)

    def summary(self, other_final_psnr: float) -> dict[str, Any]:
        last = self.points[-1]
        cam = self.data.camera
        params = self.trainer.model.params
        param_bytes = sum(p.numel() * p.element_size() for p in params.values())
        return {
            "name": self.name, "preset": self.preset.to_json(), "steps": self.trainer.step,
            "final_psnr": last["psnr"], "final_ssim": last["ssim"], "gaussians": last["gaussians"],
            "image_size": [cam.width, cam.height],
            "gaussians_per_pixel": last["gaussians"] / (cam.width * cam.height),
            "train_s": self.trainer.elapsed, "train_cpu_s": self.trainer.cpu_elapsed,
            "model_mb": param_bytes * 3 / 2**20,  # parameters + Adam's two moments
            "time_to_db": {f"{lv:g}": time_to(self.points, lv, "time_s") for lv in LEVELS_DB},
            "cpu_to_db": {f"{lv:g}": time_to(self.points, lv, "cpu_s") for lv in LEVELS_DB},
            "time_to_other_final": time_to(self.points, other_final_psnr, "time_s"),
            "time_to_own_final": time_to(self.points, last["psnr"], "time_s"),
            "points": self.points,
        }


def plot(path: Path, runs: list[dict[str, Any]], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from brave6d.atomic import atomic_write

    fig, ax = plt.subplots(figsize=(7, 4))
    for r in runs:
        ax.plot([p["time_s"] for p in r["points"]], [p["psnr"] for p in r["points"]], "o-", ms=3,
                label=f"{r['name']}: {r['final_psnr']:.2f} dB, {r['gaussians']:,} G, {r['train_s']:.0f} s")
    for lv in LEVELS_DB:
        ax.axhline(lv, color="0.7", lw=0.8, ls="--")
    ax.set_xlabel("training time [s] (evaluation excluded)")
    ax.set_ylabel("holdout PSNR [dB]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_write(path, lambda handle: fig.savefig(handle, format="png", dpi=110))
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene_dir", type=Path, help="a captured scene directory (e.g. runs/demo/scene)")
    parser.add_argument("--a", default="old=fast-3000",
                        help="configuration A (default: old=fast-3000, the fast preset before issue 22)")
    parser.add_argument("--b", default="new=fast", help="configuration B (default: new=fast), e.g. new=fast,steps=1000")
    parser.add_argument("--every", type=int, default=250, help="holdout evaluation every K steps (default 250)")
    parser.add_argument("--chunk", type=int, default=50, help="steps per turn when interleaving (default 50)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--init", choices=["auto", "colmap", "depth", "random"], default="auto")
    parser.add_argument("--json", type=Path, default=None, help="output JSON (default: <scene>/splat/time_to_quality.json)")
    args = parser.parse_args(argv)

    from brave6d.atomic import atomic_write_json
    from brave6d.layout import SceneDir
    from brave6d.progress import format_table, progress_bar
    from brave6d.runtime import prepare_process

    prepare_process()
    from training import get_preset, resolve_device
    from training.presets import BENCHMARK_PRESETS
    from training.evaluate import json_safe, peak_memory_mb

    scene = SceneDir(args.scene_dir)
    device = resolve_device(args.device)
    runs = []
    for text in (args.a, args.b):
        name, preset_name, overrides = parse_config(text)
        preset = get_preset(preset_name, BENCHMARK_PRESETS).with_overrides(**overrides)
        runs.append(Run(name, preset, scene, args.every, device, args.init))
    total = sum(r.preset.steps for r in runs)
    bar = progress_bar(total=total, desc="interleaved training", unit="step")
    while not all(r.done for r in runs):
        for r in runs:
            if not r.done:
                before = r.trainer.step
                r.advance(args.chunk)
                bar.update(r.trainer.step - before)
    bar.close()
    a, b = runs
    sa, sb = a.summary(b.points[-1]["psnr"]), b.summary(a.points[-1]["psnr"])
    a_own = sa["time_to_own_final"]
    ratio = (a_own / sb["time_to_other_final"]) if a_own and sb["time_to_other_final"] else None
    out = {"scene": str(scene.root), "device": str(device), "every": args.every, "chunk": args.chunk,
           "memory": peak_memory_mb(device), "a": sa, "b": sb,
           "ratio_time_to_a_final": ratio,
           "note": "ratio = time for A to reach its final holdout PSNR / time for B to reach it (> 1: B is faster)"}

    def cell(v: float | None, fmt: str = "{:.0f}") -> str:
        return "not reached" if v is None or not math.isfinite(v) else fmt.format(v)

    rows = [[s["name"], s["steps"], cell(s["train_s"]), cell(s["train_cpu_s"]), cell(s["time_to_db"]["27"]),
             cell(s["time_to_db"]["30"]), f"{s['final_psnr']:.2f}", f"{s['final_ssim']:.4f}", f"{s['gaussians']:,}",
             f"{s['gaussians_per_pixel']:.2f}", f"{s['model_mb']:.0f}"] for s in (sa, sb)]
    print(format_table(["config", "steps", "train s", "CPU s", "s to 27 dB", "s to 30 dB", "PSNR", "SSIM",
                        "Gaussians", "G / px", "model MB"], rows))
    print(f"\ntime to A's final PSNR ({sa['final_psnr']:.2f} dB): A {cell(a_own, '{:.1f} s')}, "
          f"B {cell(sb['time_to_other_final'], '{:.1f} s')} -> ratio A/B = {cell(ratio, '{:.2f}')}")
    print(f"peak RSS of the process (both runs): {out['memory']['peak_rss_mb']:.0f} MB")
    path = args.json or scene.splat_dir / "time_to_quality.json"
    atomic_write_json(path, json_safe(out))
    plot(path.with_suffix(".png"), [sa, sb], f"{scene.root.name}: {sa['name']} vs {sb['name']} on {device}")
    print(f"{path}\n{path.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

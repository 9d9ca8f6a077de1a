"""Agent steps per second of N agents on one scene: batched renders vs a loop of single renders.

Issue #46 item 4. For each N in ``--agents`` (default 1, 8, 64) at ``--width`` x ``--height``
(default 320x240), in one run, side by side:

* ``render``: views per second of the serving renderer alone, N poses in one
  ``SplatRenderer.render_batch`` call vs N ``render`` calls (the agents' start poses);
* ``env``: agent steps per second of ``BraveVectorEnv`` (N in-process agents, seeded random
  twists): its steps render in one batch (``EpisodeManager.move_many``) vs the same env whose
  scene renders the views one by one. A step also integrates the twist, checks collisions and
  computes the visible fractions (Open3D; skipped, with a warning, where Open3D is missing).

Each figure is the median of ``--repeats`` timed runs of ``--steps`` steps (renders: batches)
after one warm-up. The scene is the demo bundle (``runs/demo/scene/bundle``) when present, else a
synthetic bundle like ``benchmarks/serve.py``'s (``--gaussians``, SH degree 2, 30 % blobs).

    python benchmarks/vector_env_throughput.py [--device cpu|cuda|auto] [--agents 1 8 64] [--json out.json]

``benchmarks/gpu_checks.py run`` calls it with ``--device cuda`` on a lent GPU. Like ``brave6d serve``
it sets ``OMP_WAIT_POLICY=PASSIVE`` unless the environment sets it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from brave6d.serve.episodes import RenderedView, SceneServer  # noqa: E402

DEMO_BUNDLE = REPO / "runs" / "demo" / "scene" / "bundle"


class OneByOneScene(SceneServer):
    """The same scene, but a batch of views is rendered one ``render`` call at a time (the baseline)."""

    def observe_batch(self, poses: Sequence[np.ndarray], camera: Any, target_gt_ids: Sequence[int | None],
                      targets_only: bool = False, stride: int = 1, out: Any = None) -> list[RenderedView]:
        """Each view as a single env's move gives it (every object's truth, whatever ``targets_only``; its own
        images, whatever ``out``: the vector env copies them into its batch)."""
        return [self.observe(T, camera, gt_id, stride) for T, gt_id in zip(poses, target_gt_ids)]


def median_seconds(runs: dict[str, Callable[[], Any]], repeats: int, sync: Callable[[], None]) -> dict[str, float]:
    """Median wall time of each of ``runs`` over ``repeats`` timed calls after one warm-up each,
    the runs interleaved (a shared machine's load then weighs on both alike)."""
    for run in runs.values():
        run()
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            sync()
            t0 = time.perf_counter()
            run()
            sync()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def render_rates(scene: SceneServer, poses: np.ndarray, camera: Any, repeats: int, sync: Callable[[], None]
                 ) -> dict[str, float]:
    """Views per second: one ``render_batch`` of all poses vs a loop of ``render``."""
    r = scene.renderer
    seconds = median_seconds({"batched": lambda: r.render_batch(poses, camera),
                              "loop": lambda: [r.render(T, camera) for T in poses]}, repeats, sync)
    return {name: len(poses) / s for name, s in seconds.items()}


def env_rates(scenes: dict[str, SceneServer], n: int, steps: int, repeats: int, width: int, height: int,
              sync: Callable[[], None]) -> tuple[dict[str, float], float, np.ndarray]:
    """Agent steps per second of ``n`` agents stepping together on each of ``scenes`` (the same
    seeded episodes and twists), the share of their steps that rendered a view (accepted moves: a
    refused move is not rendered), and their start poses."""
    from brave6d.serve.vector_env import BraveVectorEnv

    envs = {name: BraveVectorEnv(scene, n, width=width, height=height, max_steps=10**6)
            for name, scene in scenes.items()}
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-0.3, 0.3, (n, 6)) for _ in range(steps)]
    starts = next(iter(envs.values())).reset(seed=0)[0]["world_T_cam"]
    rendered: list[int] = []

    def episode(env: BraveVectorEnv) -> None:
        env.reset(seed=0)
        rendered.clear()
        for a in actions:
            rendered.append(int(np.sum(env.step(a)[4]["accepted"])))

    seconds = median_seconds({name: (lambda env=env: episode(env)) for name, env in envs.items()}, repeats, sync)
    for env in envs.values():
        env.close()
    return {name: n * steps / s for name, s in seconds.items()}, sum(rendered) / (n * steps), starts


def open_scene(args: argparse.Namespace, workdir: Path) -> tuple[Path, str]:
    """The bundle folder to measure on and where it comes from."""
    if args.bundle is not None:
        return args.bundle, "given"
    if DEMO_BUNDLE.is_dir():
        return DEMO_BUNDLE, "demo"
    from brave6d.serve.toy_scene import make_synthetic_bundle

    print(f"no demo bundle: building a synthetic one with {args.gaussians} Gaussians ...", flush=True)
    bundle = make_synthetic_bundle(workdir / "scene", n_gaussians=args.gaussians, sh_degree=2, volume_fraction=0.3)
    return bundle, "synthetic"


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Every figure of the run (see the module docstring)."""
    import torch

    from brave6d.serve.bundle import load_bundle

    sync = torch.cuda.synchronize if args.device == "cuda" else (lambda: None)
    with tempfile.TemporaryDirectory() as tmp:
        bundle_dir, source = open_scene(args, Path(tmp))
        bundle = load_bundle(bundle_dir)
        if args.depth_mode is not None:  # e.g. "expected" on CUDA, where gsplat has no median depth yet
            bundle = dataclasses.replace(bundle, render=dataclasses.replace(bundle.render, depth_mode=args.depth_mode))
        scene = SceneServer(bundle, args.device)
        baseline = OneByOneScene(bundle, renderer=scene.renderer)
        camera = scene.camera_for(args.width, args.height)
        rows = []
        for n in args.agents:
            env, rendered, starts = env_rates({"batched": scene, "loop": baseline}, n, args.steps, args.repeats,
                                              args.width, args.height, sync)
            renders = render_rates(scene, starts, camera, args.repeats, sync)
            rows.append({"agents": n, "env_batched": env["batched"], "env_loop": env["loop"], "rendered": rendered,
                         "render_batched": renders["batched"], "render_loop": renders["loop"]})
            print(row_line(rows[-1]), flush=True)
        return {"bundle": str(bundle_dir), "source": source, "gaussians": scene.renderer.num_gaussians,
                "device": scene.device, "depth_mode": bundle.render.depth_mode, "size": [args.width, args.height], "steps": args.steps,
                "repeats": args.repeats, "cpu_threads": torch.get_num_threads(), "machine": platform.machine(),
                "rows": rows}


def row_line(row: dict[str, Any]) -> str:
    """One table row: agent steps/s and views/s, batched vs loop."""
    return (f"| {row['agents']} | {row['env_batched']:.1f} | {row['env_loop']:.1f} | "
            f"{row['env_batched'] / row['env_loop']:.2f}x | {row['rendered']:.0%} | {row['render_batched']:.1f} | "
            f"{row['render_loop']:.1f} | {row['render_batched'] / row['render_loop']:.2f}x |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda", "auto"))
    ap.add_argument("--agents", type=int, nargs="+", default=[1, 8, 64], help="numbers of agents (default 1 8 64)")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--steps", type=int, default=3, help="steps per timed run (default 3)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per figure, median taken (default 3)")
    ap.add_argument("--bundle", type=Path, default=None, help="bundle folder (default: the demo's, else synthetic)")
    ap.add_argument("--gaussians", type=int, default=150_000, help="synthetic bundle size (default 150000)")
    ap.add_argument("--depth-mode", choices=("median", "expected"), default=None,
                    help="the depth rendered (default: the bundle's; on CUDA the median comes from the CPU kernels)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    if args.device == "auto":
        import torch

        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    print("| agents | env steps/s batched | loop | speed-up | steps rendered | renders/s batched | loop | speed-up |\n"
          "|---|---|---|---|---|---|---|---|", flush=True)
    report = measure(args)
    print(f"\n{report['source']} bundle, {report['gaussians']} Gaussians, {report['device']}, "
          f"{report['depth_mode']} depth, "
          f"{report['size'][0]}x{report['size'][1]}, {report['cpu_threads']} CPU threads; median of "
          f"{report['repeats']} runs of {report['steps']} steps", flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

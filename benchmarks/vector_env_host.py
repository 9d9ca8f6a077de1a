"""Host time per agent step of the vector env, renders left out: everything but the render.

Issue #68 item 1. ``BraveVectorEnv`` with ``--agents`` agents (default 64) at ``--width`` x
``--height`` (320x240) takes seeded random twists on a synthetic scene with reference geometry (two
cubes, a post, a wall, the table). **The renders are a stand-in**: a renderer that returns fixed
images (a grey RGB, a flat depth) without drawing anything; the time spent inside it is measured
and subtracted, so what is left is the host side: twist integration, collision and workspace
checks, visible fractions (Open3D ray casts), refusals, logs, observation packing and infos.

Figures: process CPU time and wall time per agent step (the machine may be shared: CPU time is
the steadier one), each the median over ``--repeats`` child processes of the median over
``--steps`` steps. With ``--baseline REV`` the same measurement runs on the package as committed at
``REV`` (``git archive``), the two alternating, child by child, in one run.

    python benchmarks/vector_env_host.py [--agents 64] [--mode scored|training] [--baseline REV] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent


def child(src: str, bundle: str, agents: int, steps: int, width: int, height: int, mode: str) -> dict[str, float]:
    """One measurement in this process on the package under ``src`` (see the module docstring)."""
    sys.path.insert(0, src)
    import numpy as np

    from brave6d.serve.bundle import load_bundle
    from brave6d.serve.episodes import SceneServer
    from brave6d.serve.renderer import RenderOutput
    from brave6d.serve.vector_env import BraveVectorEnv

    class StandInRenderer:
        """Returns fixed images (slices of one batch array, as the real renderer's) and records its own time."""

        device, num_gaussians = "cpu", 0

        def __init__(self) -> None:
            self.seconds = 0.0
            self.rgb = np.full((agents, height, width, 3), 128, np.uint8)
            self.depth = np.full((agents, height, width), 0.3, np.float32)
            self.alpha = np.ones((agents, height, width), np.float32)

        def render_batch(self, poses: Any, camera: Any, **_: Any) -> list[Any]:
            t0 = time.perf_counter()
            out = [RenderOutput(self.rgb[i], self.depth[i], self.alpha[i], 0.0, 0.0, 0) for i in range(len(poses))]
            self.seconds += time.perf_counter() - t0
            return out

        def render(self, pose: Any, camera: Any, **kw: Any) -> Any:
            return self.render_batch([pose], camera, **kw)[0]

    stand_in = StandInRenderer()
    scene = SceneServer(load_bundle(bundle), "cpu", renderer=stand_in)
    env = BraveVectorEnv(scene, agents, target="cube_red", width=width, height=height, max_steps=10**6, mode=mode)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-0.5, 0.5, (agents, 6)) for _ in range(steps + 1)]
    env.reset(seed=0)
    env.step(actions[0])  # warm-up
    cpu, wall, accepted = [], [], 0
    for a in actions[1:]:
        stand_in.seconds = 0.0
        c0, t0 = time.process_time(), time.perf_counter()
        info = env.step(a)[4]
        c1, t1 = time.process_time(), time.perf_counter()
        cpu.append((c1 - c0 - stand_in.seconds) / agents * 1000.0)
        wall.append((t1 - t0 - stand_in.seconds) / agents * 1000.0)
        accepted += int(np.sum(info["accepted"]))
    env.close()
    return {"cpu_ms": statistics.median(cpu), "wall_ms": statistics.median(wall),
            "accepted": accepted / (agents * steps)}


def baseline_src(rev: str, workdir: Path) -> Path:
    """The package as committed at ``rev``, extracted under ``workdir``."""
    archive = workdir / "baseline.tar"
    subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", "-o", str(archive), rev, "src/brave6d"],
                   check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(workdir / "baseline", filter="data")
    return workdir / "baseline" / "src"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--agents", type=int, default=64)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--steps", type=int, default=5, help="timed steps per child (default 5)")
    ap.add_argument("--repeats", type=int, default=3, help="child processes per variant (default 3)")
    ap.add_argument("--mode", choices=("scored", "training"), default="scored")
    ap.add_argument("--baseline", default=None, help="also measure the package at this git revision")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--child", nargs=2, metavar=("SRC", "BUNDLE"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child[0], args.child[1], args.agents, args.steps, args.width, args.height,
                               args.mode)))
        return 0
    sys.path.insert(0, str(REPO / "src"))
    from brave6d.serve.toy_scene import make_synthetic_bundle

    with tempfile.TemporaryDirectory() as tmp:
        bundle = make_synthetic_bundle(Path(tmp) / "scene", n_gaussians=2000, depth=True)
        variants = {"current": REPO / "src"}
        if args.baseline:
            variants[f"baseline {args.baseline}"] = baseline_src(args.baseline, Path(tmp))
        runs: dict[str, list[dict[str, float]]] = {name: [] for name in variants}
        env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
        for _ in range(args.repeats):
            for name, src in variants.items():
                out = subprocess.run([sys.executable, __file__, "--child", str(src), str(bundle),
                                      "--agents", str(args.agents), "--steps", str(args.steps), "--width",
                                      str(args.width), "--height", str(args.height), "--mode", args.mode],
                                     check=True, capture_output=True, text=True, env=env)
                runs[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"{args.agents} agents, {args.width}x{args.height}, {args.mode} mode, renders replaced by a stand-in "
          f"(fixed images, its time subtracted); median of {args.repeats} processes x {args.steps} steps")
    print("| variant | host CPU ms / agent step | host wall ms / agent step | moves accepted |\n|---|---|---|---|")
    report: dict[str, Any] = {"agents": args.agents, "size": [args.width, args.height], "mode": args.mode,
                              "steps": args.steps, "repeats": args.repeats, "rows": {}}
    for name, rows in runs.items():
        row = {k: statistics.median(r[k] for r in rows) for k in ("cpu_ms", "wall_ms", "accepted")}
        report["rows"][name] = row
        print(f"| {name} | {row['cpu_ms']:.3f} | {row['wall_ms']:.3f} | {row['accepted']:.0%} |")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

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
``REV`` (``git archive``), the two alternating, child by child, in one run. ``--breakdown`` (the
current tree only) also splits the CPU time: the Open3D ray casts (every ``cast_rays``), the rest of
the visible fractions (``VisibilityComputer.compute_many`` without its casts), the log records
(``format_action``: an action's JSON line), the observation batch (``_batch_obs``: the images of
the views not rendered into it copied in, K and poses stacked) and everything else (moves, checks, views, infos), each summed over the timed steps.

``--logs``: the vector env gets a manager with a log folder (every action's line made, written and
flushed, as a server's); without it (the default) the vector env's own manager has none, and a log
without a file makes no lines.

    python benchmarks/vector_env_host.py [--agents 64] [--mode scored|training] [--baseline REV] [--breakdown]
                                         [--logs] [--json out.json]
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


def child(src: str, bundle: str, agents: int, steps: int, width: int, height: int, mode: str,
          breakdown: bool = False, log_dir: str | None = None) -> dict[str, Any]:
    """One measurement in this process on the package under ``src`` (see the module docstring)."""
    sys.path.insert(0, src)
    import numpy as np

    from brave6d.serve.bundle import load_bundle
    from brave6d.serve.episodes import SceneServer
    from brave6d.serve.renderer import RenderOutput
    from brave6d.serve.vector_env import BraveVectorEnv

    class StandInRenderer:
        """Returns fixed images (slices of one batch array, as the real renderer's, or written into the
        caller's ``out`` arrays, as the real renderer does) and records its own time."""

        device, num_gaussians = "cpu", 0

        def __init__(self) -> None:
            self.seconds = 0.0
            self.rgb = np.full((agents, height, width, 3), 128, np.uint8)
            self.depth = np.full((agents, height, width), 0.3, np.float32)
            self.alpha = np.ones((agents, height, width), np.float32)

        def render_batch(self, poses: Any, camera: Any, out: Any = None, **_: Any) -> list[Any]:
            t0 = time.perf_counter()
            views = []
            for i in range(len(poses)):
                rgb, depth = self.rgb[i], self.depth[i]
                if out is not None and out[i] is not None:  # as SplatRenderer: the images written into ``out``
                    np.copyto(out[i][0], rgb)
                    np.copyto(out[i][1], depth)
                    rgb, depth = out[i]
                views.append(RenderOutput(rgb, depth, self.alpha[i], 0.0, 0.0, 0))
            self.seconds += time.perf_counter() - t0
            return views

        def render(self, pose: Any, camera: Any, **kw: Any) -> Any:
            return self.render_batch([pose], camera, **kw)[0]

    stand_in = StandInRenderer()
    parts = timed_parts() if breakdown else None
    scene = SceneServer(load_bundle(bundle), "cpu", renderer=stand_in)
    if log_dir is None:  # the vector env's own manager: no log folder, nothing written
        env = BraveVectorEnv(scene, agents, target="cube_red", width=width, height=height, max_steps=10**6, mode=mode)
    else:  # --logs: every episode's log written (and flushed) line by line, as a server's
        from brave6d.serve.episode_manager import EpisodeManager

        try:  # the vector env's own stride
            from brave6d.serve.vector_env import VECTOR_VISIBILITY_STRIDE
            stride = {"visibility_stride": VECTOR_VISIBILITY_STRIDE}
        except ImportError:  # a revision before the stride: every pixel
            stride = {}
        manager = EpisodeManager(scene, log_dir, max_episodes=agents, mode=mode, log_key=None, **stride)
        env = BraveVectorEnv(manager, agents, target="cube_red", width=width, height=height, max_steps=10**6,
                             mode=mode)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-0.5, 0.5, (agents, 6)) for _ in range(steps + 1)]
    env.reset(seed=0)
    env.step(actions[0])  # warm-up
    cpu, wall, accepted = [], [], 0
    if parts is not None:
        parts.update(dict.fromkeys(parts, 0.0))
    for a in actions[1:]:
        stand_in.seconds = 0.0
        c0, t0 = time.process_time(), time.perf_counter()
        info = env.step(a)[4]
        c1, t1 = time.process_time(), time.perf_counter()
        cpu.append((c1 - c0 - stand_in.seconds) / agents * 1000.0)
        wall.append((t1 - t0 - stand_in.seconds) / agents * 1000.0)
        accepted += int(np.sum(info["accepted"]))
    env.close()
    out: dict[str, Any] = {"cpu_ms": statistics.median(cpu), "wall_ms": statistics.median(wall),
                           "accepted": accepted / (agents * steps)}
    if parts is not None:  # CPU ms per agent step, each part summed over the timed steps
        per = {k: v * 1000.0 / (agents * steps) for k, v in parts.items()}
        total = statistics.fmean(cpu)
        out["parts"] = {"ray casts (Open3D)": per["casts"],
                        "visible fractions' array code": per["visibility"] - per["casts"],
                        "log records (format_action)": per["log"], "observation batch": per["obs"],
                        "the rest (moves, checks, views, infos)": total - per["visibility"] - per["log"] - per["obs"],
                        "total (mean)": total}
    return out


def timed_parts() -> dict[str, float]:
    """Wraps the parts of a step that ``--breakdown`` reports so that each adds its CPU seconds to
    the returned dict (this child process only; the arithmetic is unchanged)."""
    import open3d as o3d

    from brave6d.serve import episode_manager, vector_env, visibility

    parts = {"casts": 0.0, "visibility": 0.0, "log": 0.0, "obs": 0.0}

    def timing(key: str, fn: Any) -> Any:
        def run(*args: Any, **kwargs: Any) -> Any:
            t0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                parts[key] += time.process_time() - t0
        return run

    scene_class = o3d.t.geometry.RaycastingScene
    scene_class.cast_rays = timing("casts", scene_class.cast_rays)
    computer = visibility.VisibilityComputer
    computer.compute_many = timing("visibility", computer.compute_many)
    episode_manager.format_action = timing("log", episode_manager.format_action)  # type: ignore[assignment]
    env_class = vector_env.BraveVectorEnv
    env_class._batch_obs = timing("obs", env_class._batch_obs)
    return parts


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
    ap.add_argument("--breakdown", action="store_true", help="split the current tree's CPU time into its parts")
    ap.add_argument("--logs", action="store_true",
                    help="give the vector env a manager with a log folder (every action's line written and flushed)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--child", nargs=2, metavar=("SRC", "BUNDLE"), help=argparse.SUPPRESS)
    ap.add_argument("--child-logs", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child[0], args.child[1], args.agents, args.steps, args.width, args.height,
                               args.mode, args.breakdown, args.child_logs)))
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
                split = ["--breakdown"] if args.breakdown and name == "current" else []
                if args.logs:
                    logs = Path(tmp) / "logs" / f"{name.replace(' ', '_')}_{len(runs[name])}"
                    split += ["--child-logs", str(logs)]
                out = subprocess.run([sys.executable, __file__, "--child", str(src), str(bundle),
                                      "--agents", str(args.agents), "--steps", str(args.steps), "--width",
                                      str(args.width), "--height", str(args.height), "--mode", args.mode, *split],
                                     check=True, capture_output=True, text=True, env=env)
                runs[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"{args.agents} agents, {args.width}x{args.height}, {args.mode} mode, renders replaced by a stand-in "
          f"(fixed images, its time subtracted); median of {args.repeats} processes x {args.steps} steps; "
          + ("logs written to a folder" if args.logs else "no log folder (the vector env's default)"))
    print("| variant | host CPU ms / agent step | host wall ms / agent step | moves accepted |\n|---|---|---|---|")
    report: dict[str, Any] = {"agents": args.agents, "size": [args.width, args.height], "mode": args.mode,
                              "steps": args.steps, "repeats": args.repeats, "logs": args.logs, "rows": {}}
    for name, rows in runs.items():
        row = {k: statistics.median(r[k] for r in rows) for k in ("cpu_ms", "wall_ms", "accepted")}
        report["rows"][name] = row
        print(f"| {name} | {row['cpu_ms']:.3f} | {row['wall_ms']:.3f} | {row['accepted']:.0%} |")
    split = [r["parts"] for r in runs["current"] if "parts" in r]
    if split:
        parts = {k: statistics.median(p[k] for p in split) for k in split[0]}
        report["breakdown"] = parts
        print("\n| current tree, CPU ms per agent step (median of the processes, mean over their steps) | ms |"
              "\n|---|---|")
        for k, v in parts.items():
            print(f"| {k} | {v:.3f} |")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

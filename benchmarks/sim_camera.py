"""Benchmark the simulated camera: frames per second at 640x400 and the time of each effect.

Runs on the demo scene (``data/demo/scene.yaml``) when present, otherwise on a small
demo-like scene built in a temporary folder (a textured table, four small objects with vertex
colours, two clutter meshes). Reports medians over N frames::

    python benchmarks/sim_camera.py [--quick] [--json out.json] [--frames N] [--spec PATH]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))

from brave6d.core.spec import EffectsSpec, SceneSpec, load_scene_spec, parse_scene_spec  # noqa: E402
from brave6d.core.transforms import look_at  # noqa: E402
from brave6d.capture.effects import CAMERA_EFFECTS, GEOMETRIC_EFFECTS  # noqa: E402
from brave6d.capture.scene_model import SceneModel  # noqa: E402
from brave6d.capture.sim_camera import SimCamera  # noqa: E402

DEMO_SPEC = REPO / "data" / "demo" / "scene.yaml"


def build_fallback_scene(folder: Path) -> SceneSpec:
    """A demo-like tabletop: textured OBJ table, coloured PLY objects, plain clutter."""
    import trimesh
    from PIL import Image

    rng = np.random.default_rng(0)
    grain = rng.normal(0, 1, (1024, 1024)).cumsum(axis=1)
    grain = (grain - grain.min()) / (np.ptp(grain) + 1e-9)
    wood = np.stack([120 + 80 * grain, 80 + 50 * grain, 40 + 30 * grain], axis=-1).astype(np.uint8)
    table = trimesh.Trimesh([[-0.5, -0.4, 0], [0.5, -0.4, 0], [0.5, 0.4, 0], [-0.5, 0.4, 0]], [[0, 1, 2], [0, 2, 3]],
                            visual=trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]],
                                                                  image=Image.fromarray(wood)), process=False)
    table.export(folder / "table.obj")
    shapes = [trimesh.creation.icosphere(3, radius=0.025), trimesh.creation.box((0.05, 0.03, 0.04)),
              trimesh.creation.cylinder(0.02, 0.07, sections=48), trimesh.creation.capsule(0.04, 0.015)]
    objects = []
    for i, mesh in enumerate(shapes):
        mesh.visual.vertex_colors = np.c_[rng.integers(30, 230, (len(mesh.vertices), 3)), np.full(len(mesh.vertices), 255)]
        mesh.export(folder / f"obj{i}.ply")
        angle = i * math.pi / 2
        objects.append({"name": f"obj{i}", "mesh": f"obj{i}.ply", "category": "industry",
                        "pose": {"xyz": [0.08 * math.cos(angle), 0.08 * math.sin(angle), 0.04]}})
    trimesh.creation.torus(0.04, 0.01).export(folder / "clutter0.stl")
    trimesh.creation.cone(0.03, 0.06).export(folder / "clutter1.stl")
    data = {"name": "bench", "capture": {"target": [0, 0, 0.03]}, "workspace": {"min": [-1, -1, -1], "max": [1, 1, 1]},
            "objects": objects,
            "static_meshes": [{"name": "table", "mesh": "table.obj"},
                              {"name": "clutter0", "mesh": "clutter0.stl", "pose": {"xyz": [-0.15, 0.1, 0.01]}},
                              {"name": "clutter1", "mesh": "clutter1.stl", "pose": {"xyz": [0.15, -0.1, 0.0]}}],
            "simulation": {"true_tcp_T_camera": {}}}
    (folder / "scene.yaml").write_text("# benchmark scene\n")
    return parse_scene_spec(data, source=folder / "scene.yaml")


def ring_pose(target: np.ndarray, t: float, radius: float = 0.3) -> np.ndarray:
    """Camera on a 45-degree ring around ``target``, moving slowly with time (0.05 rad/s)."""
    azimuth = 0.05 * t
    eye = target + radius * np.array([math.cos(azimuth) * 0.707, math.sin(azimuth) * 0.707, 0.707])
    return look_at(eye, target)


def median_ms(samples: list[float]) -> float:
    return 1000.0 * statistics.median(samples)


class Timer:
    """Wall and CPU (all threads of this process) time of a block, appended to two lists."""

    def __init__(self, wall: list[float], cpu: list[float]) -> None:
        self.wall, self.cpu = wall, cpu

    def __enter__(self) -> Timer:
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall.append(time.perf_counter() - self.t0)
        self.cpu.append(time.process_time() - self.c0)


def run(spec: SceneSpec, frames: int, supersample_levels: list[int], edge_levels: list[int]) -> dict[str, Any]:
    start = time.perf_counter()
    model = SceneModel.from_spec(spec)
    load_s = time.perf_counter() - start
    target = np.asarray(spec.capture.target, dtype=np.float64)
    intrinsics = spec.camera.pinhole().without_distortion()
    clock_state = {"t": 0.0}

    def clock() -> float:
        clock_state["t"] += 2.0  # a new viewpoint per frame
        return clock_state["t"]

    def camera(effects: EffectsSpec, supersample: int = 1, edge_supersample: int = 1) -> SimCamera:
        return SimCamera(model, intrinsics, effects, lambda t: ring_pose(target, t), clock,
                         depth_range=(spec.camera.depth_min_m, spec.camera.depth_max_m), supersample=supersample,
                         edge_supersample=edge_supersample)

    results: dict[str, Any] = {"scene": str(spec.source), "triangles": model.n_triangles,
                               "cpu_count": os.cpu_count(), "load_average_before": os.getloadavg()[0],
                               "textures": len(model.textures), "width": intrinsics.width,
                               "height": intrinsics.height, "frames": frames, "load_s": load_s}
    for key, s, e in [(f"supersample_{s}", s, 1) for s in supersample_levels] + \
            [(f"edge_supersample_{e}", 1, e) for e in edge_levels]:
        cam = camera(EffectsSpec(), s, e)
        cam.render(ring_pose(target, 0.0))  # warm-up (first cast builds the BVH)
        times: list[float] = []
        cpu: list[float] = []
        for i in range(frames):
            pose = ring_pose(target, 2.0 * i)
            with Timer(times, cpu):
                cam.render(pose).rgb
        results[f"render_ms_{key}"] = median_ms(times)
        results[f"render_best_ms_{key}"] = 1000.0 * min(times)
        results[f"render_cpu_ms_{key}"] = median_ms(cpu)
        results[f"fps_{key}"] = 1000.0 / median_ms(times)

    base = camera(EffectsSpec())
    base.capture()
    base_times: list[float] = []
    base_cpu: list[float] = []
    for _ in range(frames):
        with Timer(base_times, base_cpu):
            base.capture()
    results["capture_ms_no_effects"] = median_ms(base_times)
    results["capture_best_ms_no_effects"] = 1000.0 * min(base_times)
    results["capture_cpu_ms_no_effects"] = median_ms(base_cpu)
    per_effect: dict[str, dict[str, float]] = {}
    for name in list(CAMERA_EFFECTS) + list(GEOMETRIC_EFFECTS):
        cam = camera(EffectsSpec.model_validate({name: {}}))
        cam.capture()
        totals: list[float] = []
        cpu_totals: list[float] = []
        own: list[float] = []
        for _ in range(frames):
            with Timer(totals, cpu_totals):
                frame = cam.capture()
            own.append(frame.extras["effect_times_s"].get(name, 0.0))
        per_effect[name] = {"effect_ms": median_ms(own), "effect_best_ms": 1000.0 * min(own),
                            "capture_ms": median_ms(totals),
                            "capture_cpu_ms": median_ms(cpu_totals)}
    results["effects"] = per_effect
    results["load_average_after"] = os.getloadavg()[0]
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spec", type=Path, default=None, help="scene spec (default: the demo, else a built-in scene)")
    parser.add_argument("--frames", type=int, default=None, help="frames per measurement (default 20, --quick 5)")
    parser.add_argument("--quick", action="store_true", help="few frames, no supersampling runs")
    parser.add_argument("--json", type=Path, default=None, help="write the results as JSON to this path")
    args = parser.parse_args(argv)
    frames = args.frames or (5 if args.quick else 20)
    levels = [1] if args.quick else [1, 2, 3]
    edge_levels = [] if args.quick else [3]
    with tempfile.TemporaryDirectory() as tmp:
        if args.spec is not None:
            spec = load_scene_spec(args.spec)
        elif DEMO_SPEC.is_file():
            spec = load_scene_spec(DEMO_SPEC)
        else:
            spec = build_fallback_scene(Path(tmp))
        results = run(spec, frames, levels, edge_levels)
    print(f"scene {results['scene']}: {results['triangles']} triangles, {results['textures']} textures, "
          f"{results['width']}x{results['height']}, median of {frames} frames, {results['cpu_count']} CPUs, "
          f"load average {results['load_average_before']:.1f} -> {results['load_average_after']:.1f}")
    for key in [f"supersample_{s}" for s in levels] + [f"edge_supersample_{e}" for e in edge_levels]:
        print(f"  render, {key.replace('_', ' '):<20} {results[f'render_ms_{key}']:7.1f} ms wall "
              f"({results[f'fps_{key}']:.1f} fps, best {results[f'render_best_ms_{key}']:.1f} ms), "
              f"{results[f'render_cpu_ms_{key}']:7.1f} ms CPU")
    print(f"  capture, no effects:   {results['capture_ms_no_effects']:7.1f} ms wall, "
          f"{results['capture_cpu_ms_no_effects']:7.1f} ms CPU")
    for name, row in results["effects"].items():
        print(f"  {name:<16} effect {row['effect_ms']:7.1f} ms (best {row['effect_best_ms']:.1f})   "
              f"capture {row['capture_ms']:7.1f} ms wall, "
              f"{row['capture_cpu_ms']:7.1f} ms CPU")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

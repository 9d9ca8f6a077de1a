"""What the visible fractions' stride costs in accuracy and saves in time (issue #68 item 1).

``VisibilityComputer.compute_many`` at stride 1 (every pixel: exact) and at each ``--strides`` value
(one pixel per ``s x s`` block, small silhouettes exact: :mod:`brave6d.serve.visibility`), on the
synthetic scene with its reference geometry (two 20 mm cubes, the post, the wall, the table) at
``--width`` x ``--height``:

* **time**: CPU ms per view of batches of ``--batch`` views (the vector env's call), the target
  alone (a scored step) and every object (a training step); median of ``--repeats`` batches;
* **error** against stride 1, over ``--views`` seeded views: random starts around either cube (the
  server's start rule) moved by up to 0.25 m, turned by up to 35 degrees (objects at and over the
  image border) and pulled out to 1 m (small objects), every object of each view: ``visib_fract``'s
  absolute error (median, 95th percentile, max), by kind of view (small: under 256 pixels;
  truncated: its whole silhouette leaves the image; occluded: inside the image, partly hidden; not
  visible: hidden or outside the image at stride 1), how
  often a visible object is reported unseen, and the training reward's error (the target's visible
  area gained over a step of up to 3 cm / 0.1 rad, as a fraction of the image) in reward units.

    python benchmarks/visibility_stride.py [--strides 2 4 8] [--views 400] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "src"))


def rotation(axis_angle: np.ndarray) -> np.ndarray:
    """Rodrigues' rotation of an axis-angle vector."""
    angle = float(np.linalg.norm(axis_angle))
    if angle == 0.0:
        return np.eye(3)
    k = axis_angle / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def moved(T: np.ndarray, rng: np.random.Generator, shift: float, turn: float) -> np.ndarray:
    """``T`` moved by up to ``shift`` metres and turned by up to ``turn`` radians, in the camera frame."""
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ rotation(rng.uniform(-turn, turn, 3))
    out[:3, 3] = T[:3, 3] + T[:3, :3] @ rng.uniform(-shift, shift, 3)
    return out


def views(server: Any, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` varied views and, for each, a view one step away (see the module docstring)."""
    rng = np.random.default_rng(seed)
    objs = server.bundle.objects
    poses, steps = [], []
    for k in range(n):
        T = server.random_start(objs[k % len(objs)], rng)
        kind = k % 4
        if kind == 1:  # turned: objects at the border or out of the image
            T = moved(T, rng, 0.02, np.radians(35))
        elif kind == 2:  # pulled back: small objects
            back = T.copy()
            back[:3, 3] = T[:3, 3] - T[:3, 2] * rng.uniform(0.2, 0.6)
            T = moved(back, rng, 0.01, np.radians(5))
        elif kind == 3:  # moved about: occlusion by the other cube, the post
            T = moved(T, rng, 0.25 / 3, np.radians(15))
        poses.append(T)
        steps.append(moved(T, rng, 0.03, 0.1))
    return np.stack(poses), np.stack(steps)


def cpu_ms_per_view(computer: Any, poses: np.ndarray, camera: Any, occluders: Any, stride: int,
                    instances: list[int] | None, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        computer.compute_many(poses, camera, occluder_depths=occluders, instances=instances, stride=stride)
        times.append((time.process_time() - t0) / len(poses) * 1000.0)
    return statistics.median(times)


def error_stats(errors: list[float]) -> dict[str, float | int]:
    if not errors:
        return {"n": 0}
    e = np.asarray(errors)
    return {"n": len(e), "median": float(np.median(e)), "p95": float(np.percentile(e, 95)), "max": float(e.max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--strides", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--views", type=int, default=400)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exact-below", type=int, nargs="+", default=None,
                    help="also price these values of visibility.EXACT_BELOW_SAMPLES (default: its own only)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    from brave6d.serve.bundle import load_bundle
    from brave6d.serve.episodes import SceneServer
    from brave6d.serve.toy_scene import make_synthetic_bundle
    from brave6d.serve import visibility
    from brave6d.serve.visibility import effective_stride

    with tempfile.TemporaryDirectory() as tmp:
        make_synthetic_bundle(Path(tmp) / "scene", n_gaussians=2000, depth=True)
        server = SceneServer(load_bundle(Path(tmp) / "scene" / "bundle"), "cpu")
    camera = server.camera_for(args.width, args.height)
    computer, occluders = server.visibility, server.reference.depth_along_many
    poses, steps = views(server, args.views, args.seed)
    batch = poses[:args.batch]
    area = float(args.width * args.height)

    def all_views(stride: int, of: np.ndarray) -> list[list[Any]]:
        out: list[list[Any]] = []
        for lo in range(0, len(of), args.batch):
            out += computer.compute_many(of[lo:lo + args.batch], camera, occluder_depths=occluders, stride=stride)
        return out

    exact, exact_steps = all_views(1, poses), all_views(1, steps)
    rows: dict[str, Any] = {}
    default_below = visibility.EXACT_BELOW_SAMPLES
    variants = [(1, default_below)] + [(s, b) for s in args.strides for b in (args.exact_below or [default_below])]
    for stride, below in variants:
        visibility.EXACT_BELOW_SAMPLES = below
        s = effective_stride(camera, stride)
        row: dict[str, Any] = {"effective": s,
                               "scored_ms": cpu_ms_per_view(computer, batch, camera, occluders, stride, [0], args.repeats),
                               "training_ms": cpu_ms_per_view(computer, batch, camera, occluders, stride, None,
                                                              args.repeats)}
        got, got_steps = all_views(stride, poses), all_views(stride, steps)
        kinds: dict[str, list[float]] = {"all": [], "small": [], "truncated": [], "occluded": [], "unseen": []}
        unseen = visible = 0
        bad = 0
        for ex_view, st_view in zip(exact, got):
            for e, g in zip(ex_view, st_view):
                if not (np.isfinite(g.visib_fract) and 0.0 <= g.visib_fract <= 1.0):
                    bad += 1
                if e.px_count_all == 0:
                    continue
                err = abs(g.visib_fract - e.visib_fract)
                kinds["all"].append(err)
                if e.bbox_obj is None:  # nothing of it visible: hidden, or outside the image
                    kinds["unseen"].append(err)
                    continue
                x, y, w, h = e.bbox_obj
                if e.px_count_all < 256:
                    kinds["small"].append(err)
                elif x < 0 or y < 0 or x + w >= args.width or y + h >= args.height:
                    kinds["truncated"].append(err)
                elif 0.0 < e.visib_fract < 1.0:
                    kinds["occluded"].append(err)
                if e.px_count_visib > 0:
                    visible += 1
                    unseen += int(g.px_count_visib == 0)
        reward_err, reward_exact = [], []
        for k in range(len(poses)):
            target = k % len(server.bundle.objects)
            r_exact = (exact_steps[k][target].px_count_visib - exact[k][target].px_count_visib) / area
            r_got = (got_steps[k][target].px_count_visib - got[k][target].px_count_visib) / area
            reward_err.append(abs(r_got - r_exact))
            reward_exact.append(abs(r_exact))
        row["visib_fract_error"] = {k: error_stats(v) for k, v in kinds.items()}
        row["visible_reported_unseen"] = f"{unseen} of {visible}"
        row["not_finite_or_outside_0_1"] = bad
        row["reward_error"] = error_stats(reward_err)
        row["reward_exact_abs_median"] = float(np.median(reward_exact))
        rows[f"{stride}" if below == default_below else f"{stride}, exact below {below}"] = row

    print(f"{args.width}x{args.height}, synthetic scene with reference geometry, {args.views} views x "
          f"{len(server.bundle.objects)} objects; CPU ms per view in batches of {args.batch} (median of {args.repeats})")
    print("| stride | scored ms / view | training ms / view | visib_fract error: median / p95 / max (all) | "
          "small | truncated | occluded | not visible at stride 1 | visible reported unseen | reward error median / max |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for stride, row in rows.items():
        cells = []
        for kind in ("all", "small", "truncated", "occluded", "unseen"):
            e = row["visib_fract_error"][kind]
            cells.append(f"{e['median']:.4f} / {e['p95']:.4f} / {e['max']:.4f} (n={e['n']})" if e["n"] else "-")
        r = row["reward_error"]
        print(f"| {stride} | {row['scored_ms']:.3f} | {row['training_ms']:.3f} | "
              + " | ".join(cells) + f" | {row['visible_reported_unseen']} | {r['median']:.2e} / {r['max']:.2e} |")
    print(f"median |reward| at stride 1: {rows['1']['reward_exact_abs_median']:.2e}; values outside [0, 1] or not "
          f"finite: {sum(r['not_finite_or_outside_0_1'] for r in rows.values())}")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

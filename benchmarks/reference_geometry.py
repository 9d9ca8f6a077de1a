"""Benchmark the reference geometry (the mesh scores are measured against): accuracy vs build time.

For each TSDF setting (voxel size; truncation = 4 voxels) it builds the reference of a captured,
calibrated scene (``brave6d.serve.build_scene_reference``: captured depth, calibrated poses) and
compares the reference's depth, ray cast at seeded viewpoints above each annotated object at
10-50 cm (bundle camera), against the TRUE depth of the object's pixels: the annotated object
meshes at their poses (the demo's annotation holds the simulator's true poses), on the pixels
where that object is the first object hit. Reported per distance and setting: median |error|
(mm), shares within 5 and 15 mm, share of the object's pixels without reference depth, and the
build time.

    python benchmarks/reference_geometry.py SCENE_DIR [--voxels 0.001 0.002 0.004] [--views 12] [--json out.json]
    python benchmarks/reference_geometry.py --latency BUNDLE [BUNDLE ...] [--views 12]
    python benchmarks/reference_geometry.py --rescore EPISODE_LOG_DIR --bundle BUNDLE_WITH_REFERENCE

``--latency`` times what the reference costs the server, per bundle (one with a reference, one
without, side by side): the visible fractions of one observation (the reference is cast only on
the objects' pixels) and the full test depth of a view (cast once per episode, at submit), medians
over seeded start views at the bundle's camera.

``--rescore`` scores the same episode logs (the same estimates) twice: on the final depth they were
logged with (a bundle without a reference: the splat's) and on the reference's depth at each final
pose, so that the table shows what the test depth alone changes in each agent's AR.

SCENE_DIR must hold a bundle (``SCENE_DIR/bundle``, for the camera and the objects); copy the demo
scene first, the build writes the undistorted frames into it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))

DISTANCES = (0.10, 0.125, 0.15, 0.20, 0.30, 0.40, 0.50)


def viewpoints(centre: np.ndarray, distance: float, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    from brave6d.core.transforms import look_at

    out = []
    for _ in range(n):
        el = math.radians(rng.uniform(35.0, 80.0))
        az = rng.uniform(-math.pi, math.pi)
        eye = centre + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        out.append(look_at(eye, centre))
    return out


def latency(bundles: list[Path], views: int) -> int:
    import statistics
    import time

    from brave6d.core.progress import format_table
    from brave6d.serve import SceneServer, load_bundle

    rows = []
    for root in bundles:
        bundle = load_bundle(root)
        t = time.perf_counter()
        server = SceneServer(bundle, device="cpu")
        load_s = time.perf_counter() - t
        rng = np.random.default_rng(0)
        vis, test, render = [], [], []
        for k in range(views):
            o = bundle.objects[k % len(bundle.objects)]
            view = server.observe(server.random_start(o, rng), bundle.camera, o.gt_id)
            vis.append(view.timings_ms["visibility"])
            render.append(view.timings_ms["render"])
            t = time.perf_counter()
            _ = view.test_depth
            test.append((time.perf_counter() - t) * 1000.0)
        rows.append([str(root), server.geometry, f"{load_s:.2f}", f"{statistics.median(render):.0f}",
                     f"{statistics.median(vis):.1f}", f"{statistics.median(test):.1f}"])
    print(format_table(["bundle", "geometry", "load s", "render ms", "visibility ms", "test depth ms"], rows))
    return 0


def rescore(logs: Path, bundle_root: Path) -> int:
    import shutil
    import tempfile
    from functools import partial

    from brave6d.core.atomic import depth_m_to_mm_u16, write_png
    from brave6d.core.camera import PinholeCamera
    from brave6d.core.progress import format_table
    from brave6d.evaluation.metrics.episodes import models_from_bundle, read_episodes, score_episodes
    from brave6d.serve import SubmitRecord, load_bundle, read_episode_log, read_reference
    from brave6d.serve.bundle import load_model_m
    from brave6d.serve.visibility import VisibilityComputer

    bundle = load_bundle(bundle_root)
    if bundle.reference_path is None:
        raise SystemExit(f"{bundle_root}: the bundle has no reference geometry")
    ref = read_reference(bundle.reference_path)
    models = models_from_bundle(bundle)
    visibility = VisibilityComputer([load_model_m(bundle.model_path(o)) for o in bundle.objects],
                                    [o.world_T_obj for o in bundle.objects])
    fraction_diffs = []
    boards = {"logged": score_episodes(read_episodes([logs]), models)}
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(shutil.copytree(logs, Path(tmp) / "logs"))
        for path in sorted(copy.glob("*.jsonl")):
            sub = next((r for r in read_episode_log(path) if isinstance(r, SubmitRecord)), None)
            if sub is None or sub.final_view.depth_file is None:
                continue
            v = sub.final_view
            camera = PinholeCamera(v.width, v.height, v.K[0, 0], v.K[1, 1], v.K[0, 2], v.K[1, 2])
            write_png(copy / v.depth_file, depth_m_to_mm_u16(ref.depth(v.world_T_cam, camera)))
            now = visibility.compute(v.world_T_cam, camera, None, partial(ref.depth_along, v.world_T_cam))
            fraction_diffs += [abs(o.visib_fract - now[o.gt_id].visib_fract) for o in sub.objects
                               if o.visib_fract is not None]
        boards["reference"] = score_episodes(read_episodes([copy]), models)
    rows = []
    for a in boards["logged"].agents:
        b = next(x for x in boards["reference"].agents if x.agent == a.agent)
        rows.append([a.agent, a.episodes, f"{a.ar:.3f}", f"{b.ar:.3f}", f"{a.ar_per_metric['vsd']:.3f}",
                     f"{b.ar_per_metric['vsd']:.3f}", f"{a.ar_per_metric['mssd']:.3f}", f"{a.ar_per_metric['mspd']:.3f}"])
    print(format_table(["agent", "episodes", "AR (logged depth)", "AR (reference)", "AR_VSD (logged)",
                        "AR_VSD (reference)", "AR_MSSD", "AR_MSPD"], rows))
    d = np.asarray(fraction_diffs)
    print(f"visible fractions of every object in the final views, logged vs on the reference: {len(d)} objects, "
          f"|difference| median {np.median(d):.3f}, max {d.max():.3f}, share above 0.05 {np.mean(d > 0.05):.3f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from brave6d.annotation import SilhouetteCaster
    from brave6d.core.progress import format_table
    from brave6d.serve import ReferenceGeometry, ReferenceSettings, build_scene_reference, load_bundle
    from brave6d.serve.bundle import load_model_m

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path, nargs="?")
    ap.add_argument("--latency", type=Path, nargs="+", metavar="BUNDLE")
    ap.add_argument("--rescore", type=Path, metavar="EPISODE_LOG_DIR")
    ap.add_argument("--bundle", type=Path, help="with --rescore: the scene's bundle with a reference geometry")
    ap.add_argument("--voxels", type=float, nargs="+", default=[0.001, 0.002, 0.004])
    ap.add_argument("--trunc-voxels", type=float, default=4.0)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.latency:
        return latency(args.latency, args.views)
    if args.rescore:
        if args.bundle is None:
            ap.error("--rescore needs --bundle")
        return rescore(args.rescore, args.bundle)
    if args.scene is None:
        ap.error("SCENE_DIR is required (or --latency BUNDLE ...)")

    bundle = load_bundle(args.scene / "bundle")
    camera = bundle.camera
    models = [load_model_m(bundle.model_path(o)) for o in bundle.objects]
    caster = SilhouetteCaster(dict(enumerate(models)), list(enumerate(o.world_T_obj for o in bundle.objects)))
    rng = np.random.default_rng(args.seed)
    views = []  # (distance, instance, world_T_cam)
    for n, (o, (v, _)) in enumerate(zip(bundle.objects, models)):
        centre = o.world_T_obj[:3, :3] @ (0.5 * (v.min(0) + v.max(0))) + o.world_T_obj[:3, 3]
        for d in DISTANCES:
            views += [(d, n, T) for T in viewpoints(centre, d, args.views, rng)]
    truth = []  # per view: (ys, xs, true depth) of the target's first-hit pixels
    for d, n, T in views:
        sil = next(s for k, s in enumerate(caster.silhouettes(T, camera)) if k == n).within(camera.width, camera.height)
        first = caster.first_instance(T, sil.rays) == n if sil.px_count_all else np.zeros(0, bool)
        truth.append((sil.ys[first], sil.xs[first], sil.depth[first]))

    rows, results = [], []
    for voxel in args.voxels:
        settings = ReferenceSettings(voxel_m=voxel, trunc_m=args.trunc_voxels * voxel)
        mesh = build_scene_reference(args.scene, settings)
        ref = ReferenceGeometry(mesh.vertices, mesh.faces)
        per_d: dict[float, list[np.ndarray]] = {d: [] for d in DISTANCES}
        for (d, _, T), (ys, xs, z) in zip(views, truth):
            if len(z):
                r = ref.depth(T, camera)[ys, xs]
                per_d[d].append(np.where(r > 0, np.abs(r - z) * 1000.0, np.nan))
        for d in DISTANCES:
            err = np.concatenate(per_d[d]) if per_d[d] else np.zeros(0)
            has = err[np.isfinite(err)]
            row = {"voxel_mm": voxel * 1000, "trunc_mm": settings.trunc_m * 1000, "distance_m": d,
                   "pixels": int(len(err)), "median_mm": float(np.median(has)) if len(has) else None,
                   "within_5mm": float(np.mean(has <= 5.0)) if len(has) else None,
                   "within_15mm": float(np.mean(has <= 15.0)) if len(has) else None,
                   "no_depth": float(np.mean(~np.isfinite(err))) if len(err) else None,
                   "build_s": mesh.stats.build_s, "triangles": mesh.stats.triangles}
            results.append(row)
            rows.append([f"{voxel * 1000:g}", f"{d * 100:g}", row["pixels"], row["median_mm"], row["within_5mm"],
                         row["within_15mm"], row["no_depth"], f"{mesh.stats.build_s:.1f}", mesh.stats.triangles])
    print(format_table(["voxel mm", "cm", "pixels", "median mm", "<=5 mm", "<=15 mm", "no depth", "build s",
                        "triangles"], rows))
    if args.json:
        args.json.write_text(json.dumps({"views_per_distance_per_object": args.views, "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

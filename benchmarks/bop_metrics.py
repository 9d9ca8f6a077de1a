"""Timing of the BOP19 evaluation on a synthetic test set (CPU).

Run: ``.venv/bin/python benchmarks/bop_metrics.py [--images 20] [--width 640]``.
Prints the time of the pose errors alone and of a full ``evaluate_bop19`` (all three metrics).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from brave6d.evaluation.metrics.bop_metrics import VSD_TAUS, mspd, mssd, vsd
from brave6d.evaluation.metrics.recall import Estimate, GTInstance, ObjectModel, evaluate_bop19
from brave6d.evaluation.metrics.depth_renderer import DepthRenderer


def make_models() -> dict[int, ObjectModel]:
    meshes = {
        1: (trimesh.creation.cylinder(radius=12.0, height=10.0, sections=6), {"symmetries_discrete": [
            np.vstack([np.hstack([Rotation.from_euler("z", 60 * k, degrees=True).as_matrix(), np.zeros((3, 1))]),
                       [0, 0, 0, 1]]).reshape(-1).tolist() for k in range(1, 6)]}),
        2: (trimesh.creation.cylinder(radius=25.0, height=60.0, sections=128),
            {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}),
        3: (trimesh.creation.icosphere(subdivisions=4, radius=30.0), {}),
        4: (trimesh.creation.box(extents=(50.0, 30.0, 20.0)).subdivide().subdivide().subdivide(), {}),
    }
    out = {}
    for obj_id, (mesh, sym) in meshes.items():
        v = np.asarray(mesh.vertices)
        diameter = float(np.max(np.linalg.norm(v[:, None] - v[None], axis=2))) if len(v) < 4000 else 60.0
        out[obj_id] = ObjectModel.from_models_info(obj_id, v, {"diameter": diameter, **sym}, mesh.faces)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--images", type=int, default=20)
    ap.add_argument("--width", type=int, default=640)
    args = ap.parse_args()
    w = args.width
    h = w * 3 // 4
    f = 600.0 * w / 640.0
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    models = make_models()
    ren = DepthRenderer()
    for obj_id, m in models.items():
        ren.add_object(obj_id, m.points, m.faces)
    print("vertices per model:", {k: len(m.points) for k, m in models.items()},
          "symmetries:", {k: len(m.symmetries()) for k, m in models.items()})

    rng = np.random.default_rng(0)
    gts, ests = [], []
    for im_id in range(args.images):
        poses = []
        for obj_id, x in zip(models, (-90.0, -30.0, 30.0, 90.0)):
            R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
            poses.append((obj_id, R, np.array([x, rng.uniform(-40, 40), rng.uniform(400, 600)])))
        depth = np.full((h, w), np.inf)
        for obj_id, R, t in poses:
            d = ren.render(obj_id, R, t, K, w, h)
            depth = np.where((d > 0) & (d < depth), d, depth)
        depth = np.where(np.isfinite(depth), depth, 900.0)
        for obj_id, R, t in poses:
            gts.append(GTInstance(0, im_id, obj_id, R, t, 1.0, K, (w, h), depth))
            dR = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
            ests.append(Estimate(0, im_id, obj_id, float(rng.uniform()), R @ dR, t + rng.normal(0, 3.0, 3), 0.1))

    t0 = time.perf_counter()
    for g, e in zip(gts, ests):
        m = models[g.obj_id]
        mssd(e.R, e.t, g.R, g.t, m.points, m.symmetries())
    t1 = time.perf_counter()
    for g, e in zip(gts, ests):
        m = models[g.obj_id]
        mspd(e.R, e.t, g.R, g.t, K, m.points, m.symmetries())
    t2 = time.perf_counter()
    for g, e in zip(gts, ests):
        m = models[g.obj_id]
        vsd(e.R, e.t, g.R, g.t, g.depth, K, 15.0, VSD_TAUS, True, m.diameter, ren.render_fn(g.obj_id, K, w, h))
    t3 = time.perf_counter()
    res = evaluate_bop19(gts, ests, models, renderer=ren)
    t4 = time.perf_counter()
    n = len(ests)
    print(f"{n} estimates, {w}x{h}: MSSD {1e3 * (t1 - t0) / n:.2f} ms, MSPD {1e3 * (t2 - t1) / n:.2f} ms, "
          f"VSD {1e3 * (t3 - t2) / n:.2f} ms per estimate; evaluate_bop19 {t4 - t3:.2f} s "
          f"({1e3 * (t4 - t3) / n:.1f} ms per estimate)")
    print(res.table())


if __name__ == "__main__":
    main()

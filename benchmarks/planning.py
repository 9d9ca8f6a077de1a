"""Benchmark the view planner on the demo scene (or a demo-like spec when data/demo is absent).

Reports, for the planner's orders (global tour, ring by ring) against naive orders (sampling
order, and ring by ring sorted by azimuth): estimated travel time (SimRobot moveJ model) and
ratio, planning time, views kept per ring, largest per-joint step between views, dropped
reasons; plus the IK time per pose.

    python benchmarks/planning.py [--spec data/demo/scene.yaml] [--json out.json] [--plot plan.png]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(ROOT / "src"))

from brave6d.core.spec import SceneSpec, load_scene_spec, parse_scene_spec  # noqa: E402
from brave6d.capture.collision import BoxSet  # noqa: E402
from brave6d.capture.kinematics import URKinematics  # noqa: E402
from brave6d.capture.planning import Plan, PlannerOptions, path_travel_time, plan_views, plot_plan  # noqa: E402

DEMO = ROOT / "data" / "demo" / "scene.yaml"


def demo_like_spec() -> SceneSpec:
    """A stand-in for the demo scene: UR5e at the origin, table top at z = 0, 4 rings x 90 views."""
    return parse_scene_spec({
        "name": "demo_like",
        "capture": {"target": [0.45, 0.0, 0.01], "distances_m": [0.2, 0.3, 0.4, 0.5], "views_per_distance": 90,
                    "min_elevation_deg": 30, "max_elevation_deg": 85},
        "workspace": {"min": [0.0, -0.6, 0.02], "max": [0.94, 0.6, 0.9]},
        "collision_boxes": [
            {"name": "table", "center": [0.55, 0.0, -0.375], "size": [0.8, 1.0, 0.75]},
            {"name": "pedestal", "center": [0.0, 0.0, -0.4], "size": [0.2, 0.2, 0.8]},
            {"name": "wall", "center": [0.96, 0.0, 0.4], "size": [0.02, 1.6, 0.8]},
        ],
        "robot": {"model": "ur5e", "tcp_T_camera_guess": {"xyz": [0.0, -0.06, 0.03]}},
    }, check_files=False)


def _steps_deg(plan: Plan) -> tuple[float, float]:
    path = plan.joint_path()[1:]
    if len(path) < 2:
        return 0.0, 0.0
    steps = np.degrees(np.abs(np.diff(path, axis=0)).max(axis=1))
    return float(steps.max()), float(np.median(steps))


def _reason_kind(reason: str) -> str:
    if reason.startswith("collision: "):
        return "collision: " + ", ".join(sorted({h.split(" vs ")[1] for h in reason[11:].split(", ")}))
    return reason.split(" (")[0].split(":")[0]


def run(spec: SceneSpec, repeats: int) -> tuple[dict[str, Any], Plan]:
    results: dict[str, Any] = {"scene": spec.name, "robot": spec.robot.model,
                               "views_sampled": len(spec.capture.distances_m) * spec.capture.views_per_distance}
    plans: dict[str, Plan] = {}
    for order in ("global", "rings"):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            plans[order] = plan_views(spec, options=PlannerOptions(order=order))
            times.append(time.perf_counter() - t0)
        p = plans[order]
        max_step, med_step = _steps_deg(p)
        results[f"order_{order}"] = {
            "travel_time_s": round(p.travel_time_s, 2),
            "estimated_total_s": round(p.estimated_time_s, 2),
            "planning_time_s_median": round(statistics.median(times), 3),
            "max_joint_step_deg": round(max_step, 1),
            "median_joint_step_deg": round(med_step, 1),
            "first_move_deg": round(float(np.degrees(p.meta["first_move_max_joint_step_rad"])), 1),
        }
    p = plans["global"]
    speed, acc = p.joint_speed, p.joint_acceleration
    sampling = path_travel_time(np.vstack([p.start_joints, *[v.joints for v in sorted(p.views, key=lambda v: v.view_id)]]),
                                speed, acc)
    sweep_views = sorted(p.views, key=lambda v: (v.distance_level, v.azimuth))
    sweep = path_travel_time(np.vstack([p.start_joints, *[v.joints for v in sweep_views]]), speed, acc)
    results["naive_sampling_order_travel_s"] = round(sampling, 2)
    results["naive_azimuth_sweep_travel_s"] = round(sweep, 2)
    results["ratio_global_vs_sampling_order"] = round(p.travel_time_s / sampling, 3)
    results["ratio_global_vs_azimuth_sweep"] = round(p.travel_time_s / sweep, 3)
    results["ratio_rings_vs_azimuth_sweep"] = round(plans["rings"].travel_time_s / sweep, 3)
    results["configuration"] = list(p.configuration)
    results["views_planned"] = len(p.views)
    results["views_per_ring"] = {f"{spec.capture.distances_m[k]:.2f} m": n for k, n in p.views_per_ring().items()}
    results["dropped"] = len(p.dropped)
    results["dropped_reasons"] = dict(Counter(_reason_kind(d.reason) for d in p.dropped).most_common())

    kin = URKinematics(spec.robot.model)
    rng = np.random.default_rng(0)
    poses = [kin.fk(q) for q in rng.uniform(-np.pi, np.pi, (300, 6))]
    t0 = time.perf_counter()
    n_sol = [len(kin.ik(T)) for T in poses]
    results["ik_ms_per_pose"] = round(1e3 * (time.perf_counter() - t0) / len(poses), 3)
    results["ik_mean_solutions"] = round(float(np.mean(n_sol)), 2)
    return results, p


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", type=Path, default=None, help=f"scene spec (default: {DEMO} if present)")
    ap.add_argument("--json", type=Path, default=None, help="write the results as JSON here")
    ap.add_argument("--plot", type=Path, default=None, help="write the global plan's PNG plot here")
    ap.add_argument("--repeats", type=int, default=3, help="planning runs per order (median time)")
    args = ap.parse_args(argv)
    spec_path = args.spec or (DEMO if DEMO.is_file() else None)
    spec = load_scene_spec(spec_path, check_files=False) if spec_path else demo_like_spec()
    results, plan = run(spec, max(1, args.repeats))
    results["spec"] = str(spec_path) if spec_path else "built-in demo-like spec"
    print(json.dumps(results, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
    if args.plot:
        plot_plan(plan, args.plot, BoxSet.from_specs(spec.collision_boxes), spec.workspace)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

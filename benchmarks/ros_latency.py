"""Per-step latency of the ROS interfaces vs HTTP on the same bundle and the same poses.

One step = an agent sends a camera pose and waits for the image of that pose:

* ``http``: ``BraveClient.set_pose`` against ``brave6d.serve.ServerThread`` on loopback (PNG RGB and
  float32 depth in the JSON reply, decoded), i.e. the reply the agent waits for;
* ``ros1``: a ``geometry_msgs/PoseStamped`` published on ``/brave6d_sim/set_pose`` until the
  ``sensor_msgs/Image`` (rgb8) with that step's stamp reaches the agent's callback (rosmaster and
  ``brave6d ros1`` on loopback, the agent a separate rospy process; column ``depth``: the 32FC1
  image's arrival);
* ``ros2``: the ``set_pose`` service (``brave6d_msgs/srv/SetPose``) of ``brave6d ros2`` (rclpy on
  Fast DDS, its own process, the node's loopback profile: UDP on 127.0.0.1 and shared memory) called
  by ``brave6d.ros_interface.ros2.agent.Ros2Agent`` (an rclpy node, sensor-data QoS) until the rgb8
  image with the answer's stamp has arrived at the agent (``depth``: the 32FC1 one). The node
  publishes the images before it answers; the answer's arrival is in the JSON
  (``answer_median_ms``). Node and agent run with ROS 2's defaults (every ``ROS_*``, ``RMW_*``,
  ``FASTDDS_*`` / ``FASTRTPS_*`` variable removed) on a random domain id (100..229) given to both,
  so other ROS 2 processes on the machine neither see nor disturb them.

rclpy lives in the layered ROS 2 venv, not in the one that runs this script (docs/ROS.md), so
``ros2`` re-runs this script in ``$BRAVE6D_ROS2_PYTHON`` (default ``<repo>/.venv-ros2/bin/python``)
with an internal flag that measures ros2 only, on the same bundle and poses, and writes its samples
as JSON; the column is skipped, saying why, when that python or its rclpy is missing.

Every transport sees the same ``--steps`` free poses around the target (after ``--warmup`` steps
that are not counted); ``server ms`` is the episode log's own time for the step (render, ground
truth and visible fractions), so ``latency - server`` is the transport's cost. Medians and p90
are printed as a table; ``--json`` writes them.

    python benchmarks/ros_latency.py [--bundle DIR | --gaussians N --width W --height H]
        [--device cpu|cuda|auto] [--steps 30] [--transports http ros1 ros2] [--json out.json]

Without ``--bundle``, a synthetic bundle (``brave6d.serve.make_synthetic_bundle``, ``--gaussians``
at ``--width`` x ``--height``) is built in a temporary folder. ROS 1 needs Debian's packages (see
docs/ROS.md); its column is skipped, saying why, without them. Transports are registered in
``TRANSPORTS`` (name -> function), so a new one is one entry.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
# this folder holds benchmarks/serve.py, which would shadow the serve package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != REPO / "benchmarks"]
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does

from brave6d.core.transforms import look_at  # noqa: E402


def free_views(bundle_dir: Path, n: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` free camera poses on capture-like rings around the bundle's first object (seeded)."""
    from brave6d.serve import load_bundle

    bundle = load_bundle(bundle_dir)
    centre = bundle.objects[0].world_T_obj[:3, 3] if bundle.objects else np.zeros(3)
    dists = bundle.start.get("distances_m") or [0.25, 0.4]
    rng = np.random.default_rng(seed)
    out: list[np.ndarray] = []
    for _ in range(100 * n):
        d = rng.uniform(min(dists), max(dists))
        el, az = math.radians(rng.uniform(30, 80)), rng.uniform(-math.pi, math.pi)
        T = look_at(centre + d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]),
                    centre)
        if bundle.world.check(T) is None:
            out.append(T)
            if len(out) == n:
                return out
    raise SystemExit(f"found only {len(out)} free views around {bundle.objects[0].name}")


def server_step_ms(log_dir: Path) -> list[float]:
    """The ``step`` time of every set_pose in the episode logs of ``log_dir`` (in order)."""
    out: list[float] = []
    for path in sorted(log_dir.glob("*.jsonl")):
        for line in path.read_text(encoding="utf-8").splitlines():
            rec = json.loads(line)
            if rec.get("event") == "set_pose":
                out.append(float(rec["timings_ms"]["step"]))
    return out


def measure_http(bundle_dir: Path, views: list[np.ndarray], args: argparse.Namespace, work: Path) -> dict[str, Any]:
    from brave6d.serve import BraveClient, ServerThread, create_app

    log_dir = work / "http_episodes"
    app = create_app(bundle_dir, device=args.device, log_dir=log_dir)
    lat = []
    with ServerThread(app) as server, BraveClient(server.url, rgb="png", depth="f32") as client:
        client.reset(start=views[0], agent="bench-http")
        for T in views[1:]:
            t0 = time.perf_counter()
            step = client.set_pose(T)
            lat.append(time.perf_counter() - t0)
            assert step.accepted and step.observation.rgb is not None
        client.close()
    return {"image_s": lat, "server_ms": server_step_ms(log_dir)}


def measure_ros1(bundle_dir: Path, views: list[np.ndarray], args: argparse.Namespace, work: Path) -> dict[str, Any]:
    from brave6d.ros_interface.ros1.master import RosMaster, stop_group
    from brave6d.ros_interface.ros1.ros_env import loopback_environment, missing_ros1

    missing = missing_ros1(import_modules=False)
    if missing:
        return {"skipped": "ROS 1 not installed: apt-get install " + " ".join(missing)}
    log_dir = work / "ros1_episodes"
    actions = [{"op": "reset", "start": views[0].tolist()}] + [{"op": "set_pose", "world_T_cam": T.tolist()}
                                                             for T in views[1:]]
    (work / "ros1_actions.json").write_text(json.dumps({"actions": actions, "timeout_s": 300}), encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO / "src"), os.environ.get("PYTHONPATH")]))}
    with RosMaster(log_file=work / "rosmaster.log") as master:
        env.update(loopback_environment(master.uri))
        node = subprocess.Popen(
            [sys.executable, "-c", "import sys; from brave6d.cli import main; sys.exit(main(sys.argv[1:]))", "ros1",
             str(bundle_dir), "--master-uri", master.uri, "--device", args.device, "--log-dir", str(log_dir),
             "--agent", "bench-ros1"], env=env, cwd=REPO, stdout=open(work / "ros1_node.log", "wb"),
            stderr=subprocess.STDOUT, start_new_session=True)
        try:
            agent = subprocess.run([sys.executable, "-m", "brave6d.ros_interface.ros1.client", str(work / "ros1_actions.json"),
                                    str(work / "ros1_out")], env=env, cwd=REPO, capture_output=True, text=True,
                                   timeout=1800)
            if agent.returncode != 0:
                raise SystemExit(f"ROS 1 agent failed:\n{agent.stderr[-2000:]}\n"
                                 f"{(work / 'ros1_node.log').read_text(errors='replace')[-2000:]}")
        finally:
            stop_group(node)
    record = json.loads((work / "ros1_out" / "record.json").read_text(encoding="utf-8"))
    steps = [s for s in record["steps"] if s["op"] == "set_pose"]
    assert all(s["status"]["accepted"] for s in steps)
    return {"image_s": [s["latency_s"]["rgb"] for s in steps], "depth_s": [s["latency_s"]["depth"] for s in steps],
            "server_ms": server_step_ms(log_dir)}


ROS_ENV_PREFIXES = ("ROS_", "RMW_", "FASTDDS_", "FASTRTPS_")
#: The internal flag of the child that measures ros2 in the ROS 2 python (value: its work folder).
ROS2_CHILD_FLAG = "--ros2-child"


def ros2_python() -> Path:
    """The python of the ROS 2 venv: ``$BRAVE6D_ROS2_PYTHON``, else ``<repo>/.venv-ros2/bin/python``."""
    return Path(os.environ.get("BRAVE6D_ROS2_PYTHON") or REPO / ".venv-ros2" / "bin" / "python")


def ros_free_environment() -> dict[str, str]:
    """This process's environment without ROS 2 / DDS settings (ROS 2's defaults), ``src`` first on the path."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(ROS_ENV_PREFIXES)}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO / "src"), os.environ.get("PYTHONPATH")]))
    return env


def measure_ros2(bundle_dir: Path, views: list[np.ndarray], args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """Run :func:`measure_ros2_here` in the ROS 2 python (this script with ``--ros2-child``) and read its samples."""
    python = ros2_python()
    if not python.exists():
        return {"skipped": f"no ROS 2 python at {python} (scripts/setup.sh --with-ros2 makes .venv-ros2; or set "
                           "BRAVE6D_ROS2_PYTHON)"}
    (work / "views.json").write_text(json.dumps([T.tolist() for T in views]), encoding="utf-8")
    cmd = [str(python), str(Path(__file__).resolve()), ROS2_CHILD_FLAG, str(work), "--bundle", str(bundle_dir),
           "--device", args.device]
    child = subprocess.run(cmd, env=ros_free_environment(), cwd=REPO, capture_output=True, text=True, timeout=1800)
    if child.returncode != 0:
        raise SystemExit(f"the ROS 2 measurement failed ({' '.join(cmd)}):\n{child.stdout[-2000:]}\n"
                         f"{child.stderr[-3000:]}")
    return json.loads((work / "samples.json").read_text(encoding="utf-8"))


def measure_ros2_here(bundle_dir: Path, views: list[np.ndarray], args: argparse.Namespace,
                      work: Path) -> dict[str, Any]:
    """The ros2 samples, measured in this (ROS 2) python: node as a process, rclpy agent here."""
    for key in [k for k in os.environ if k.startswith(ROS_ENV_PREFIXES)]:
        del os.environ[key]  # ROS 2's defaults, read by rclpy.init below
    try:
        import rclpy
    except ImportError as exc:
        return {"skipped": f"rclpy not importable in {sys.executable}: {exc} (pip install -e '.[ros2]' there)"}
    import random

    from brave6d.ros_interface.ros2.agent import Ros2Agent
    from brave6d.ros_interface.ros2.interfaces import ensure_interfaces

    class TimedAgent(Ros2Agent):
        """Records when each service answer reached the agent."""

        answered = 0.0

        def call(self, name: str, request: Any) -> Any:
            response = super().call(name, request)
            self.answered = time.perf_counter()
            return response

    ensure_interfaces()  # brave6d_msgs for the agent (the node does the same)
    log_dir = work / "ros2_episodes"
    domain_id = random.randrange(100, 230)
    node_log = work / "ros2_node.log"
    with open(node_log, "wb") as out:
        node = subprocess.Popen(
            [sys.executable, "-m", "brave6d.cli", "ros2", str(bundle_dir), "--domain-id", str(domain_id),
             "--device", args.device, "--log-dir", str(log_dir), "--agent", "bench-ros2"],
            env=ros_free_environment(), cwd=REPO, stdout=out, stderr=subprocess.STDOUT)
    rgb_s, depth_s, answer_s = [], [], []
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        agent = TimedAgent(timeout_s=300, context=context, node_name="brave6d_bench_agent")
        try:
            agent.wait_until_connected(timeout_s=300)
            agent.reset(start=views[0])
            for T in views[1:]:
                t0 = time.perf_counter()
                obs = agent.set_pose(T)
                assert obs.step.accepted, obs.status
                rgb_s.append(obs.received["rgb"] - t0)
                depth_s.append(obs.received["depth"] - t0)
                answer_s.append(agent.answered - t0)
            agent.close()
        finally:
            agent.destroy()
    except Exception as exc:
        raise SystemExit(f"{type(exc).__name__}: {exc}\nnode output:\n"
                         f"{node_log.read_text(errors='replace')[-3000:]}") from exc
    finally:
        rclpy.try_shutdown(context=context)
        node.terminate()
        try:
            node.wait(timeout=30)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait()
    return {"image_s": rgb_s, "depth_s": depth_s, "answer_s": answer_s, "server_ms": server_step_ms(log_dir),
            "domain_id": domain_id}


def ros2_child(work: Path, args: argparse.Namespace) -> int:
    """``--ros2-child WORK``: measure ros2 on ``WORK/views.json``, write ``WORK/samples.json``."""
    views = [np.asarray(T, dtype=np.float64) for T in json.loads((work / "views.json").read_text(encoding="utf-8"))]
    samples = measure_ros2_here(args.bundle, views, args, work)
    (work / "samples.json").write_text(json.dumps(samples), encoding="utf-8")
    return 0


#: name -> function(bundle_dir, views (the first is the reset's start), args, work dir) -> samples.
TRANSPORTS: dict[str, Callable[[Path, list[np.ndarray], argparse.Namespace, Path], dict[str, Any]]] = {
    "http": measure_http,
    "ros1": measure_ros1,
    "ros2": measure_ros2,
}


def summarise(samples: dict[str, Any], warmup: int) -> dict[str, Any]:
    if "skipped" in samples:
        return samples
    ms = np.asarray(samples["image_s"][warmup:]) * 1000.0
    server = np.asarray(samples["server_ms"][warmup:])
    out = {"steps": int(ms.size), "median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90)),
           "server_median_ms": float(np.median(server)) if server.size else None}
    if out["server_median_ms"] is not None:
        out["transport_median_ms"] = float(np.median(ms - server[: ms.size])) if server.size >= ms.size else None
    if "depth_s" in samples:
        depth = np.asarray(samples["depth_s"][warmup:]) * 1000.0
        out["depth_median_ms"], out["depth_p90_ms"] = float(np.median(depth)), float(np.percentile(depth, 90))
    if "answer_s" in samples:
        answer = np.asarray(samples["answer_s"][warmup:]) * 1000.0
        out["answer_median_ms"], out["answer_p90_ms"] = float(np.median(answer)), float(np.percentile(answer, 90))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bundle", type=Path, default=None, help="bundle folder (default: a synthetic one)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu")
    parser.add_argument("--steps", type=int, default=30, help="timed steps per transport (default 30)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps first (default 3)")
    parser.add_argument("--transports", nargs="+", default=list(TRANSPORTS), choices=list(TRANSPORTS))
    parser.add_argument("--gaussians", type=int, default=20_000, help="synthetic bundle: Gaussians (default 20000)")
    parser.add_argument("--width", type=int, default=320, help="synthetic bundle: image width (default 320)")
    parser.add_argument("--height", type=int, default=240, help="synthetic bundle: image height (default 240)")
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    parser.add_argument(ROS2_CHILD_FLAG, type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.ros2_child is not None:
        return ros2_child(args.ros2_child, args)
    from brave6d.core.progress import format_table

    with tempfile.TemporaryDirectory(prefix="brave6d_ros_latency_") as tmp:
        work = Path(tmp)
        bundle_dir = args.bundle
        if bundle_dir is None:
            from brave6d.serve import make_synthetic_bundle

            bundle_dir = make_synthetic_bundle(work / "scene", n_gaussians=args.gaussians, width=args.width,
                                               height=args.height)
        views = free_views(bundle_dir, 1 + args.warmup + args.steps)
        results = {}
        for name in args.transports:
            (work / name).mkdir()
            results[name] = summarise(TRANSPORTS[name](bundle_dir, views, args, work / name), args.warmup)
        from brave6d.serve import load_bundle

        bundle = load_bundle(bundle_dir)
        size = f"{bundle.render.width}x{bundle.render.height}"
    rows = []
    for name, r in results.items():
        if "skipped" in r:
            rows.append([name, "-", "-", "-", "-", r["skipped"]])
            continue
        rows.append([name, r["steps"], f"{r['median_ms']:.1f}", f"{r['p90_ms']:.1f}",
                     f"{r['server_median_ms']:.1f}" if r.get("server_median_ms") is not None else "-",
                     f"{r['transport_median_ms']:.1f}" if r.get("transport_median_ms") is not None else "-"])
    print(f"set_pose -> image received, {bundle.name} ({size}, {args.device}), {platform.node()}:")
    print(format_table(["transport", "steps", "median ms", "p90 ms", "server ms (median)",
                        "transport ms (median)"], rows))
    if args.json is not None:
        args.json.write_text(json.dumps({"bundle": bundle.name, "size": size, "device": args.device,
                                         "host": platform.node(), "python": platform.python_version(),
                                         "results": results}, indent=1), encoding="utf-8")
        print(f"written: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

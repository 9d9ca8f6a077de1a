"""What a view costs through the real UR client, against ``brave6d ur-emulator`` and against SimRobot.

One view is what the capture runner asks of the robot: ``move_joints`` to the next planned joints,
``wait_until_steady(settle)``, ``tcp_pose()`` and ``joints()``. With ``URRobot`` that is ur-rtde 1.6.5
in its worker process talking RTDE to an emulator on a loopback address; the emulator's
``--time-scale`` is set so high that the arm's travel itself is negligible, so the figure is the
client's own cost (commands, async-move polling, the state-stream check). The emulator's CPU share
is read from /proc while the views run. ``SimRobot`` (virtual clock) is the floor.

    python benchmarks/ur_rehearsal.py [--views 60] [--settle 0.0] [--time-scale 1000] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from brave6d.core.spec import RobotSpec
from brave6d.capture.sim_robot import SimRobot
from brave6d.capture.ur_emulator import probe
from brave6d.capture.ur_robot import URRobot

ADDRESS = "127.0.0.61"


def _views(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    base = np.array([0.2, -1.2, 1.5, -1.8, -1.5, 0.3])
    return [base + rng.uniform(-0.3, 0.3, 6) for _ in range(n)]


def _time_views(robot: object, views: list[np.ndarray], settle: float) -> list[float]:
    times = []
    for q in views:
        t0 = time.perf_counter()
        robot.move_joints(q)  # type: ignore[attr-defined]
        robot.wait_until_steady(settle)  # type: ignore[attr-defined]
        robot.tcp_pose()  # type: ignore[attr-defined]
        robot.joints()  # type: ignore[attr-defined]
        times.append(time.perf_counter() - t0)
    return times


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / 100.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--settle", type=float, default=0.0)
    ap.add_argument("--time-scale", type=float, default=1000.0)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    views = _views(args.views)
    sim = _time_views(SimRobot(RobotSpec()), views, args.settle)
    log = Path(tempfile.mkdtemp(prefix="ur-rehearsal-")) / "emulator.log"
    with open(log, "wb") as out:
        emu = subprocess.Popen([sys.executable, "-m", "brave6d.cli", "ur-emulator", "--address", ADDRESS,
                                "--time-scale", str(args.time_scale), "--quiet"], stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while not probe(ADDRESS, timeout_s=0.5):
            if emu.poll() is not None or time.monotonic() > deadline:
                sys.exit(f"the emulator did not start: {log.read_text()[-500:]}")
            time.sleep(0.1)
        t0 = time.perf_counter()
        robot = URRobot(ADDRESS, RobotSpec())
        connect_s = time.perf_counter() - t0
        cpu0, wall0 = _cpu_seconds(emu.pid), time.perf_counter()
        ur = _time_views(robot, views, args.settle)
        emu_share = (_cpu_seconds(emu.pid) - cpu0) / (time.perf_counter() - wall0)
        t0 = time.perf_counter()
        robot.close()
        close_s = time.perf_counter() - t0
    finally:
        emu.terminate()
        emu.wait(timeout=10)
    result = {"views": args.views, "settle_s": args.settle, "time_scale": args.time_scale,
              "sim_view_median_ms": 1e3 * statistics.median(sim), "ur_view_median_ms": 1e3 * statistics.median(ur),
              "ur_view_p90_ms": 1e3 * float(np.percentile(ur, 90)), "ur_connect_s": connect_s, "ur_close_s": close_s,
              "emulator_cpu_share": emu_share}
    print(f"per view ({args.views} views, settle {args.settle:g} s): SimRobot {result['sim_view_median_ms']:.2f} ms, "
          f"URRobot via ur-rtde + emulator {result['ur_view_median_ms']:.1f} ms median "
          f"({result['ur_view_p90_ms']:.1f} p90); connect {connect_s:.2f} s, close {close_s:.2f} s; "
          f"emulator CPU {100 * emu_share:.0f} % of a core")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

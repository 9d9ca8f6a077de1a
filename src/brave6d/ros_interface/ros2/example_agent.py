"""An example ROS 2 agent over DDS: one episode end to end against ``brave6d ros2``.

    brave6d ros2 BUNDLE &                       # the node (loopback, domain 0)
    python -m brave6d.ros_interface.ros2.example_agent  # this agent

It resets, reads the first view (RGB, depth, camera info, tf), steps back along the optical axis
with one ``cmd_twist``, then submits the target's pose taken from the ground-truth tf frame
``gt/<name>_<gt_id>``: an oracle that shows the plumbing, not a pose estimator (a real agent
estimates from the images; the ground truth is in its own ``gt/`` namespace for scoring and
debugging). Prints the scored result as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys

from brave6d.ros_interface.bridge import Estimate
from brave6d.ros_interface.ros2.agent import Ros2Agent
from brave6d.ros_interface.ros2.cli import domain_id_from
from brave6d.ros_interface.ros2.dds import DdsDomain
from brave6d.ros_interface.ros2.defaults import DEFAULT_NAMESPACE


def run_episode(agent: Ros2Agent, seed: int = 0) -> dict:
    """Reset, one twist, submit the target's ground-truth pose; the node's result."""
    first = agent.reset(seed=seed)
    target = first.status["target"]
    print(f"episode {first.status['episode_id']}: target {target['name']} (obj_id {target['obj_id']}), "
          f"image {first.rgb.shape[1]}x{first.rgb.shape[0]}, fx {first.K[0, 0]:.1f}", file=sys.stderr)
    view = agent.twist([0.0, 0.0, -0.05], [0.0, 0.0, 0.0])  # back off 5 cm/s along the optical axis
    print(f"twist: accepted {view.status['accepted']}, adjustments {view.status['adjustments']}", file=sys.stderr)
    estimate = Estimate(target["obj_id"], view.cam_T_gt(target["frame"]), 1.0)
    return agent.submit([estimate])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--domain-id", type=int, default=None, help="DDS domain id (default $ROS_DOMAIN_ID, else 0)")
    parser.add_argument("--namespace", default=DEFAULT_NAMESPACE)
    parser.add_argument("--seed", type=int, default=0, help="seed of the episode's start pose")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for each answer")
    args = parser.parse_args(argv)
    with DdsDomain(domain_id_from(args.domain_id)) as dds:
        agent = Ros2Agent(dds, args.namespace, timeout_s=args.timeout)
        agent.wait_until_connected(timeout_s=args.timeout)
        print(json.dumps(run_episode(agent, args.seed), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

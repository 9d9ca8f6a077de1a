"""The rospy side of tests/test_ros1_learned_agents.py (its own process: ``rospy.init_node`` once per
process): learned-static and learned-active with the Protocol-only estimator of
tests/test_estimator_protocol.py play every object of BUNDLE through
:class:`~brave6d.ros_interface.episode_clients.Ros1EpisodeClient`, seed gt_id, as ``run_baselines`` does;
then the seed-0 start view of gt_id 1 is saved (OUT.npz) and another image size asked for.

    python tests/ros1_learned_player.py BUNDLE WIDTH HEIGHT OUT.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # test_estimator_protocol's stand-ins


def main(bundle_dir: str, width: int, height: int, out: str) -> None:
    from brave6d.ros_interface.ros1.ros_env import require_ros1

    require_ros1()
    import rospy
    from test_estimator_protocol import make_detector, make_pose_estimator

    from brave6d.evaluation.agents import LEARNED_AGENTS, AgentSetup, make_agent, run_episode
    from brave6d.ros_interface import Ros1EpisodeClient
    from brave6d.ros_interface.ros1.client import Ros1Client
    from brave6d.serve import load_bundle

    rospy.init_node("brave6d_learned_player", anonymous=True, disable_signals=True)
    client = Ros1EpisodeClient(Ros1Client(timeout_s=120), bundle_dir)
    setup = AgentSetup(detector=make_detector(), pose_estimator=make_pose_estimator())
    players = [make_agent(name, client, setup) for name in LEARNED_AGENTS]  # RGB-only, then with depth
    outcomes = [run_episode(client, agent, obj.gt_id, seed=obj.gt_id, width=width, height=height)
                for obj in load_bundle(bundle_dir).objects for agent in players]
    record = [{"agent": o.agent, "target": o.target, "adjustments": o.adjustments, "ar": o.submission["ar"],
               "mode": o.submission["mode"], "submitted": o.submission["submitted"],
               "cam_T_obj": [e.cam_T_obj.tolist() for e in o.estimates]} for o in outcomes]
    view = client.reset(target=1, width=width, height=height, seed=0).observation  # the HTTP view's twin
    np.savez(Path(out).with_suffix(".npz"), rgb=view.rgb, depth=view.depth, K=view.K, world_T_cam=view.world_T_cam)
    client.ros.close()
    try:  # a node image size other than the one asked for: one line
        client.reset(target=1, width=width * 2, height=height * 2, seed=0)
        refusal = None
    except Exception as exc:  # noqa: BLE001 - recorded for the test to judge
        refusal = f"{type(exc).__name__}: {exc}"
    Path(out).write_text(json.dumps({"outcomes": record, "size_refusal": refusal}), encoding="utf-8")
    rospy.signal_shutdown("done")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])

"""An example ROS 1 agent node: one episode end to end against ``brave6d ros1``.

    python -m brave6d.ros_interface.ros1.example_agent [--node /brave6d_sim] [--target NAME] [--seed N]

It resets (a seeded random start looking at the target), approaches the target with
``~cmd_twist`` until it is ``--distance`` metres away or a move is refused, reads the images,
camera info and ``/tf``, and submits one estimate: by default a naive one (the target's position
back-projected from the depth at the image centre, identity rotation: a perception stand-in that
shows the plumbing; it runs against a node in its default, scored mode), with ``--oracle`` the
ground truth from the ``gt/`` frames (for testing the pipeline only: it needs a node started with
``--training``, the only mode that publishes ``gt/`` frames). It prints the scored result.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from brave6d.ros_interface.ros1.ros_env import require_ros1


def naive_estimate(obs: object) -> np.ndarray:
    """cam_T_obj from the depth at the image centre (median of a 9x9 patch), identity rotation."""
    depth = obs.depth_array()  # type: ignore[attr-defined]
    K = np.asarray(obs.rgb_info.K, dtype=np.float64).reshape(3, 3)  # type: ignore[attr-defined]
    h, w = depth.shape
    v, u = h // 2, w // 2
    patch = depth[max(0, v - 4): v + 5, max(0, u - 4): u + 5]
    z = float(np.nanmedian(patch)) if np.isfinite(patch).any() else 0.3
    T = np.eye(4)
    T[:3, 3] = [(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z]
    return T


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--node", default="/brave6d_sim")
    parser.add_argument("--target", default="", help="object name or gt_id (default: the bundle's first object)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--distance", type=float, default=0.22, help="stop approaching at this distance (m)")
    parser.add_argument("--max-steps", type=int, default=20)
    parser.add_argument("--speed", type=float, default=0.3, help="approach speed (m/s, camera z)")
    parser.add_argument("--oracle", action="store_true",
                        help="submit the ground truth read from /tf (testing only; needs a node run with --training)")
    args = parser.parse_args(argv)
    require_ros1()
    import rospy

    from brave6d.ros_interface.ros1.client import Ros1Client

    rospy.init_node("brave6d_example_agent", anonymous=True, disable_signals=True)
    client = Ros1Client(args.node)
    obs = client.reset(target=args.target, seed=args.seed)
    status = obs.status_json
    target = status["target"]  # the target's name and ids (its gt/ frame only in training mode)
    print(f"episode {status['episode_id']}: target {target['name']} (obj_id {target['obj_id']}), "
          f"image {obs.rgb.width}x{obs.rgb.height}, fx {obs.rgb_info.K[0]:.1f}, {status.get('mode')} mode")
    if args.oracle and not target.get("frame"):
        print("--oracle reads the target's gt/ frame on /tf, which a node publishes only in training mode: "
              "start it with --training", file=sys.stderr)
        client.close()
        return 1
    for _ in range(args.max_steps):
        z = float(np.nanmedian(obs.depth_array()[obs.rgb.height // 2 - 4: obs.rgb.height // 2 + 5,
                                                 obs.rgb.width // 2 - 4: obs.rgb.width // 2 + 5]))
        if not np.isfinite(z) or z <= args.distance:
            break
        obs = client.move([0.0, 0.0, args.speed])
        s = obs.status
        print(f"  step {s.step}: {'accepted' if s.accepted else 'refused: ' + s.refusal_message}, "
              f"adjustments {s.adjustments}, centre depth was {z:.3f} m")
        if not s.accepted:
            break
    if args.oracle:
        frames = obs.frames()
        cam_T_obj = np.linalg.inv(frames["brave6d_camera_optical_frame"]) @ frames[target["frame"]]
    else:
        cam_T_obj = naive_estimate(obs)
    res = client.submit([(target["obj_id"], cam_T_obj, 1.0)])
    if not res.success:
        print(f"submit failed: {res.message}", file=sys.stderr)
        return 1
    print(f"result: AR {res.ar:.3f} (VSD {res.ar_vsd:.3f}, MSSD {res.ar_mssd:.3f}, MSPD {res.ar_mspd:.3f}), "
          f"adjustments {res.adjustments}, steps {res.steps}, refusals {res.refusals}")
    rospy.signal_shutdown("episode done")
    return 0


if __name__ == "__main__":
    sys.exit(main())

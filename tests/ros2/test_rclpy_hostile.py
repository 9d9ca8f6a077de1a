"""No request stops the node (issue #35): hostile and malformed requests from an rclpy agent get
one refusal each, with the HTTP API's limits and messages, and the node then serves a normal
episode. A burst of requests is answered in full, in order."""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
import pytest
from conftest import NodeProcess

from brave6d.core.transforms import look_at
from brave6d.ros_interface.ros2.agent import AgentError, Ros2Agent

pytestmark = pytest.mark.slow

FREE = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))


def refused(agent: Ros2Agent, name: str, request: Any) -> str:
    """The node's one-line refusal of ``request`` (the test fails if it was accepted)."""
    with pytest.raises(AgentError) as info:
        agent.call(name, request)
    message = str(info.value)
    assert "\n" not in message and len(message) <= 600, message[:200]
    return message


def test_hostile_requests_are_refused_and_the_node_keeps_serving(agent: Ros2Agent, node: NodeProcess) -> None:
    import brave6d_msgs.srv as srv
    from brave6d_msgs.msg import ObjectEstimate
    from geometry_msgs.msg import PoseStamped

    agent.close()  # whatever a previous test left: no open episode
    # commands without an episode
    assert "call reset" in refused(agent, "set_pose", srv.SetPose.Request(
        pose=PoseStamped(pose=_pose(FREE))))
    assert "call reset" in refused(agent, "submit", srv.Submit.Request())
    # reset: the seed HTTP refuses with 422, an 8 MB name, unknown scene and target
    assert refused(agent, "reset", srv.Reset.Request(use_seed=True, seed=-1)).endswith(
        "seed: Input should be greater than or equal to 0")
    big = refused(agent, "reset", srv.Reset.Request(scene="x" * 8_000_000))
    assert "scene: String should have at most 128 characters" in big
    assert "target: at most 128 characters" in refused(agent, "reset", srv.Reset.Request(target="y" * 8_000_000))
    assert "no-such-object" in refused(agent, "reset", srv.Reset.Request(target="no-such-object"))
    # start poses: NaN, huge, non-unit quaternion, the zero quaternion
    for position, q, expect in (((math.nan, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0), "finite number"),
                                ((1e300, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0), "less than or equal to 1000"),
                                ((0.2, 0.0, 0.3), (0.0, 0.0, 0.0, 2.0), "unit quaternion"),
                                ((0.2, 0.0, 0.3), (0.0, 0.0, 0.0, 0.0), "unit quaternion")):
        request = srv.Reset.Request(use_start=True)
        request.start.position.x, request.start.position.y, request.start.position.z = position
        o = request.start.orientation
        o.x, o.y, o.z, o.w = q
        assert expect in refused(agent, "reset", request)

    agent.reset(start=FREE)
    # moves: nothing, NaN, too fast, a wrong frame
    move = srv.Move.Request()
    assert "velocities are both zero" in refused(agent, "move", move)
    move.twist.twist.linear.x = math.nan
    assert "finite number" in refused(agent, "move", move)
    move.twist.twist.linear.x = 1e9
    assert "linear" in refused(agent, "move", move)
    move.twist.twist.linear.x, move.twist.header.frame_id = 0.01, "base_link"
    assert "header.frame_id 'base_link'" in refused(agent, "move", move)
    # set_pose in another frame
    pose = srv.SetPose.Request(pose=PoseStamped(pose=_pose(FREE)))
    pose.pose.header.frame_id = "map"
    assert "header.frame_id 'map'" in refused(agent, "set_pose", pose)
    # submissions: 5,000 estimates (HTTP caps at 100), a NaN pose, a non-unit quaternion
    many = srv.Submit.Request(estimates=[ObjectEstimate(obj_id=1, pose=_pose(np.eye(4)))] * 5000)
    assert "estimates: List should have at most 100 items" in refused(agent, "submit", many)
    nan = ObjectEstimate(obj_id=1, pose=_pose(np.eye(4)))
    nan.pose.position.z = math.nan
    assert "estimates.0.pose.position" in refused(agent, "submit", srv.Submit.Request(estimates=[nan]))
    skew = ObjectEstimate(obj_id=1, pose=_pose(np.eye(4)))
    skew.pose.orientation.w = 3.0
    assert "not a unit quaternion" in refused(agent, "submit", srv.Submit.Request(estimates=[skew]))

    # after all that, a normal episode
    view = agent.set_pose(look_at((0.30, 0.10, 0.35), (0.46, 0.0, 0.01)))
    assert view.step.accepted and view.rgb.shape[2] == 3
    assert agent.submit([])["submitted"] == 0
    assert "Traceback" not in node.output()


def test_a_burst_of_100_set_poses_is_answered_in_full_and_in_order(agent: Ros2Agent) -> None:
    import brave6d_msgs.srv as srv
    from geometry_msgs.msg import PoseStamped

    agent.reset(start=FREE)
    poses = [look_at((0.25 + 0.001 * i, -0.15, 0.30), (0.46, 0.0, 0.01)) for i in range(100)]
    client = agent.clients["set_pose"]
    done = threading.Semaphore(0)
    futures = []
    for T in poses:  # all sent before the first answer comes back
        request = srv.SetPose.Request(pose=PoseStamped(pose=_pose(T)))
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.release())
        futures.append(future)
    for _ in futures:
        assert done.acquire(timeout=300), "a set_pose of the burst was never answered"
    steps = [f.result().step for f in futures]
    assert all(f.result().success for f in futures)
    assert [s.step for s in steps] == list(range(1, 101))
    assert agent.submit([])["steps"] == 100


def _pose(T: Any) -> Any:
    from brave6d.ros_interface.ros2.convert import pose_msg

    return pose_msg(T)

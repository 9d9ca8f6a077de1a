"""The ROS 2 node's pieces without a scene: loopback-only DDS configuration and its guard, domain
ids, the JSON commands' checks (one line naming the topic and field), message conversions (images,
camera info, tf, estimates) and that our brave6d_msgs estimate is ROS 1's definition."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("cyclonedds")
from rosbags.typesys import get_types_from_msg  # noqa: E402

from brave6d.core.errors import BraveError  # noqa: E402
from brave6d.core.transforms import look_at  # noqa: E402
from brave6d.ros_interface import (  # noqa: E402
    FRAME_CAMERA_OPTICAL,
    FRAME_WORLD,
    BridgeStep,
    Estimate,
    GroundTruthObject,
    matrix_to_pose,
)
from brave6d.ros_interface.ros2 import convert  # noqa: E402
from brave6d.ros_interface.ros2 import messages as m  # noqa: E402
from brave6d.ros_interface.ros2.cli import domain_id_from  # noqa: E402
from brave6d.ros_interface.ros2.dds import check_interface, cyclone_config, is_loopback  # noqa: E402
from brave6d.ros_interface.ros2.node import TOPICS, estimates_from_json, parse_json_command, start_pose  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def test_loopback_config_turns_multicast_off_and_discovers_on_127_0_0_1() -> None:
    xml = cyclone_config("127.0.0.1")
    assert '<NetworkInterface address="127.0.0.1"/>' in xml
    assert "<AllowMulticast>false</AllowMulticast>" in xml
    assert '<Peer address="127.0.0.1"/>' in xml
    remote = cyclone_config("eth0", peers=("10.0.0.7",))
    assert '<NetworkInterface name="eth0"/>' in remote and "<AllowMulticast>default</AllowMulticast>" in remote
    assert '<Peer address="10.0.0.7"/>' in remote and "127.0.0.1" not in remote
    with pytest.raises(BraveError, match="--interface"):
        cyclone_config('eth0"/><x')
    with pytest.raises(BraveError, match="--peer"):
        cyclone_config("127.0.0.1", peers=('a"b',))


def test_a_network_interface_needs_allow_remote() -> None:
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("lo") and is_loopback("127.3.2.1")
    assert not is_loopback("eth0") and not is_loopback("192.168.1.5") and not is_loopback("0.0.0.0")
    with pytest.raises(BraveError, match="--allow-remote"):
        check_interface("eth0", allow_remote=False)
    assert check_interface("eth0", allow_remote=True) == "eth0"


def test_domain_id_from_the_flag_or_ros_domain_id() -> None:
    assert domain_id_from(7, {}) == 7
    assert domain_id_from(None, {"ROS_DOMAIN_ID": "42"}) == 42
    assert domain_id_from(None, {}) == 0
    with pytest.raises(BraveError, match="ROS_DOMAIN_ID"):
        domain_id_from(None, {"ROS_DOMAIN_ID": "x"})
    with pytest.raises(BraveError, match="0..232"):
        domain_id_from(300, {})


def test_json_commands_are_checked_naming_the_topic_and_field() -> None:
    assert parse_json_command(m.String(""), "/t") == {}
    with pytest.raises(BraveError, match="/t: data is not JSON"):
        parse_json_command(m.String("{"), "/t")
    with pytest.raises(BraveError, match="/t: data must be a JSON object"):
        parse_json_command(m.String("[1]"), "/t")
    with pytest.raises(BraveError, match=r"/s: 'estimates' must be a list"):
        estimates_from_json({}, "/s")
    with pytest.raises(BraveError, match=r"/s.estimates.0: must be an object"):
        estimates_from_json({"estimates": [3]}, "/s")
    with pytest.raises(BraveError, match=r"/s.estimates.0.orientation: quaternion .* is not unit"):
        estimates_from_json({"estimates": [{"obj_id": 1, "position": [0, 0, 0.3], "orientation": [0, 0, 0, 0]}]},
                            "/s")
    (e,) = estimates_from_json({"estimates": [{"obj_id": 2, "position": [0.1, 0, 0.3],
                                               "orientation": [0, 0, 0, 1], "score": 0.5}]}, "/s")
    assert e.obj_id == 2 and e.score == 0.5 and np.allclose(e.cam_T_obj[:3, 3], [0.1, 0, 0.3])


def test_reset_start_forms() -> None:
    T = look_at((0.25, -0.15, 0.30), (0.46, 0.0, 0.01))
    assert start_pose(None, "/r") is None
    assert start_pose(T.tolist(), "/r") == T.tolist()
    pos, q = matrix_to_pose(T)
    np.testing.assert_allclose(start_pose({"position": pos.tolist(), "orientation": q.tolist()}, "/r"), T, atol=1e-12)
    with pytest.raises(BraveError, match="/r.start"):
        start_pose({"position": [0, 0, 0]}, "/r")


def test_topic_table_uses_sensor_qos_for_images_and_reliable_for_commands() -> None:
    by_name = {t.suffix: t for t in TOPICS}
    for name in ("rgb/image_raw", "depth/image_raw", "rgb/camera_info", "depth/camera_info"):
        assert (by_name[name].qos.reliable, by_name[name].qos.depth) == (False, 5)
    for name in ("reset", "set_pose", "cmd_twist", "submit", "submit_json", "close", "status", "result"):
        assert (by_name[name].qos.reliable, by_name[name].qos.depth) == (True, 10)


def _step(rgb: np.ndarray, depth: np.ndarray, T: np.ndarray) -> BridgeStep:
    K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    obj = GroundTruthObject("cube_red", 1, 0, True, np.eye(4), np.linalg.inv(T), 0.8)
    return BridgeStep(episode_id="e", step=0, accepted=True, collided=False, refusal=None, adjustments=0,
                      stamp_ns=1_700_000_000_000_000_123, rgb=rgb, depth_m=depth, K=K, width=rgb.shape[1],
                      height=rgb.shape[0], world_T_cam=T, objects=(obj,))


@settings(max_examples=20)
@given(h=st.integers(1, 7), w=st.integers(1, 9), seed=st.integers(0, 2**32 - 1))
def test_images_round_trip_through_messages(h: int, w: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    depth = rng.uniform(0.1, 2.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.3] = 0.0  # the server's "no data"
    step = _step(rgb, depth, look_at((0.3, 0.0, 0.3), (0.46, 0.0, 0.0)))
    rgb_msg, depth_msg = convert.rgb_image(step), convert.depth_image(step)
    assert (rgb_msg.encoding, rgb_msg.step, depth_msg.encoding, depth_msg.step) == ("rgb8", 3 * w, "32FC1", 4 * w)
    np.testing.assert_array_equal(convert.image_to_array(m.Image.deserialize(rgb_msg.serialize())), rgb)
    back = convert.image_to_array(m.Image.deserialize(depth_msg.serialize()))
    np.testing.assert_array_equal(np.isnan(back), depth == 0)  # REP 118: no data is NaN
    np.testing.assert_array_equal(back[depth > 0], depth[depth > 0])


def test_camera_info_and_tf_of_a_step() -> None:
    T = look_at((0.3, 0.0, 0.3), (0.46, 0.0, 0.0))
    step = _step(np.zeros((120, 160, 3), np.uint8), np.ones((120, 160), np.float32), T)
    info = convert.camera_info(step)
    assert (info.width, info.height, info.distortion_model, info.header.frame_id) == (
        160, 120, "plumb_bob", FRAME_CAMERA_OPTICAL)
    assert info.k == step.K.reshape(-1).tolist() and info.p[:3] == [100.0, 0.0, 80.0] and info.d == [0.0] * 5
    assert m.stamp_to_ns(info.header.stamp) == step.stamp_ns
    tf = convert.tf_message(step)
    assert [(t.header.frame_id, t.child_frame_id) for t in tf.transforms] == [
        (FRAME_WORLD, FRAME_CAMERA_OPTICAL), (FRAME_WORLD, "gt/cube_red_0")]
    np.testing.assert_allclose(convert.transform_to_matrix(tf.transforms[0]), T, atol=1e-12)


def test_estimates_round_trip_and_frames_are_checked() -> None:
    T = look_at((0.1, 0.2, 0.5), (0.0, 0.0, 0.0))
    msg = convert.estimates_to_msg([Estimate(3, T, 0.7)], stamp_ns=5)
    (e,) = convert.estimates_from_msg(m.ObjectEstimateArray.deserialize(msg.serialize()), "/s")
    assert e.obj_id == 3 and e.score == 0.7
    np.testing.assert_allclose(e.cam_T_obj, T, atol=1e-12)
    msg.header.frame_id = "world"
    with pytest.raises(BraveError, match="/s: header.frame_id 'world'"):
        convert.estimates_from_msg(msg, "/s")
    pose = m.PoseStamped(header=m.Header(frame_id="map"), pose=convert.pose_to_msg(T))
    with pytest.raises(BraveError, match="/p: header.frame_id 'map'"):
        convert.camera_pose_from_msg(pose, "/p")
    twist = m.TwistStamped(header=m.Header(frame_id="base_link"))
    with pytest.raises(BraveError, match="/c: header.frame_id 'base_link'"):
        convert.twist_from_msg(twist, "/c")
    assert convert.twist_from_msg(m.TwistStamped(header=m.Header(frame_id="world")), "/c")[2] == "world"


def test_our_object_estimate_is_ros1s_definition() -> None:
    """One definition for both generations: the ROS 2 brave6d_msgs/ObjectEstimate has the fields
    of the ROS 1 one (src/brave6d/ros_interface/ros1/msg)."""
    name = "brave6d_msgs/msg/ObjectEstimate"
    ros1 = get_types_from_msg((REPO / "src/brave6d/ros_interface/ros1/msg/ObjectEstimate.msg").read_text(), name)
    ros2 = get_types_from_msg(m.CUSTOM_MSG_FILES[name].read_text(), name)
    assert ros1 == ros2
    assert list(m.ObjectEstimate.__dataclass_fields__) == ["obj_id", "pose", "score"]

"""Where ``brave6d ros2`` can be reached, without ROS: the variables and the Fast DDS profile it
starts rclpy with (loopback unless --allow-remote), and domain ids. The node itself is tested with
rclpy in tests/ros2 (run by test_ros2_suite.py)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from brave6d.core.errors import BraveError
from brave6d.ros_interface.ros2.cli import domain_id_from
from brave6d.ros_interface.ros2.transport import SHM_SEGMENT_BYTES, fastdds_profile, node_environment

NS = {"d": "http://www.eprosima.com"}


def _profile(env: dict[str, str]) -> ET.Element:
    return ET.fromstring(Path(env["FASTDDS_DEFAULT_PROFILES_FILE"]).read_text())


def test_by_default_the_node_is_loopback_only(tmp_path: Path) -> None:
    env = node_environment(False, environ={}, profile_dir=tmp_path)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    root = _profile(env)
    udp = root.find(".//d:transport_descriptor[d:type='UDPv4']", NS)
    assert udp is not None and [a.text for a in udp.findall(".//d:interfaceWhiteList/d:address", NS)] == ["127.0.0.1"]
    participant = root.find(".//d:participant", NS)
    assert participant is not None and participant.get("is_default_profile") == "true"
    assert participant.findtext(".//d:useBuiltinTransports", namespaces=NS) == "false"  # nothing else listens
    shm = root.find(".//d:transport_descriptor[d:type='SHM']", NS)
    assert shm is not None and int(shm.findtext("d:segment_size", namespaces=NS) or 0) == SHM_SEGMENT_BYTES
    assert SHM_SEGMENT_BYTES >= 4 * 640 * 480 * 4  # several depth images of 640x480 in flight


def test_allow_remote_keeps_ros2s_defaults_and_only_widens_shared_memory(tmp_path: Path) -> None:
    env = node_environment(True, environ={}, profile_dir=tmp_path)
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in env
    assert _profile(env).find(".//d:interfaceWhiteList", NS) is None
    assert "127.0.0.1" not in fastdds_profile(loopback=False)


def test_a_wider_discovery_range_needs_allow_remote(tmp_path: Path) -> None:
    for value in ("SUBNET", "system_default"):
        with pytest.raises(BraveError, match="--allow-remote"):
            node_environment(False, environ={"ROS_AUTOMATIC_DISCOVERY_RANGE": value}, profile_dir=tmp_path)
    assert node_environment(True, environ={"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"},
                            profile_dir=tmp_path)["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    assert node_environment(False, environ={"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"},
                            profile_dir=tmp_path)["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "OFF"
    with pytest.raises(BraveError, match="must be one of"):
        node_environment(False, environ={"ROS_AUTOMATIC_DISCOVERY_RANGE": "LAN"}, profile_dir=tmp_path)


def test_peers_and_a_users_own_profile(tmp_path: Path) -> None:
    env = node_environment(False, ("127.0.0.1",), environ={}, profile_dir=tmp_path)
    assert env["ROS_STATIC_PEERS"] == "127.0.0.1"
    with pytest.raises(BraveError, match="needs --allow-remote"):
        node_environment(False, ("10.0.0.7",), environ={}, profile_dir=tmp_path)
    env = node_environment(True, ("10.0.0.7",), environ={"ROS_STATIC_PEERS": "10.0.0.5"}, profile_dir=tmp_path)
    assert env["ROS_STATIC_PEERS"] == "10.0.0.5;10.0.0.7"
    own = node_environment(False, environ={"FASTDDS_DEFAULT_PROFILES_FILE": "/etc/lab.xml"}, profile_dir=tmp_path)
    assert own["FASTDDS_DEFAULT_PROFILES_FILE"] == "/etc/lab.xml"


def test_domain_id_from_the_flag_or_ros_domain_id() -> None:
    assert domain_id_from(7, {}) == 7
    assert domain_id_from(None, {"ROS_DOMAIN_ID": "42"}) == 42
    assert domain_id_from(None, {}) == 0
    with pytest.raises(BraveError, match=r"\$ROS_DOMAIN_ID 'x': not an integer"):
        domain_id_from(None, {"ROS_DOMAIN_ID": "x"})
    with pytest.raises(BraveError, match="--domain-id 300: must be in 0..232"):
        domain_id_from(300, {})

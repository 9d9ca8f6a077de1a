"""Incoming ROS 1 messages -> bridge values (brave6d.ros_interface.ros1.convert): frame_ids, quaternions and
twists are checked with one-line errors naming the topic and field. Plain stand-ins for the
messages (the converters read attributes only), so no ROS install is needed."""

from __future__ import annotations

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from brave6d.core.errors import BraveError
from brave6d.ros_interface.ros1 import convert


def _pose(x: float = 0.3, q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)) -> NS:
    return NS(position=NS(x=x, y=0.1, z=0.35), orientation=NS(x=q[0], y=q[1], z=q[2], w=q[3]))


def _pose_stamped(frame: str, **kw: object) -> NS:
    return NS(header=NS(frame_id=frame), pose=_pose(**kw))  # type: ignore[arg-type]


def test_set_pose_needs_the_world_frame_and_a_unit_quaternion() -> None:
    T = convert.world_T_cam_from(_pose_stamped("world"), "/brave6d_sim/set_pose")
    np.testing.assert_allclose(T[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)  # pi about x: looking down
    np.testing.assert_allclose(T[:3, 3], [0.3, 0.1, 0.35])
    with pytest.raises(BraveError, match=r"^/brave6d_sim/set_pose: header.frame_id must be 'world'.*'map'"):
        convert.world_T_cam_from(_pose_stamped("map"), "/brave6d_sim/set_pose")
    with pytest.raises(BraveError, match=r"^/brave6d_sim/set_pose: pose.orientation: .*not a unit quaternion"):
        convert.world_T_cam_from(_pose_stamped("world", q=(0.0, 0.0, 0.0, 0.0)), "/brave6d_sim/set_pose")


def test_twist_frames() -> None:
    def twist(frame: str, vz: float = 0.05) -> NS:
        return NS(header=NS(frame_id=frame), twist=NS(linear=NS(x=0.0, y=0.0, z=vz), angular=NS(x=0.0, y=0.1, z=0.0)))

    assert convert.twist_from(twist(""), "t") == ([0.0, 0.0, 0.05], [0.0, 0.1, 0.0], "camera")
    assert convert.twist_from(twist("brave6d_camera_optical_frame"), "t")[2] == "camera"
    assert convert.twist_from(twist("world"), "t")[2] == "world"
    with pytest.raises(BraveError, match=r"^/x/cmd_twist: header.frame_id must be .*'base_link'"):
        convert.twist_from(twist("base_link"), "/x/cmd_twist")
    with pytest.raises(BraveError, match="twist must be finite"):
        convert.twist_from(twist("", vz=math.nan), "t")


def test_estimates_are_in_the_camera_frame() -> None:
    req = NS(header=NS(frame_id=""), estimates=[NS(obj_id=2, pose=_pose(q=(0.0, 0.0, 0.0, 1.0)), score=0.7)])
    (e,) = convert.estimates_from(req, "/s/submit")
    assert e.obj_id == 2 and e.score == 0.7
    np.testing.assert_allclose(e.cam_T_obj, [[1, 0, 0, 0.3], [0, 1, 0, 0.1], [0, 0, 1, 0.35], [0, 0, 0, 1]])
    req.header.frame_id = "world"
    with pytest.raises(BraveError, match=r"^/s/submit: header.frame_id must be 'brave6d_camera_optical_frame'"):
        convert.estimates_from(req, "/s/submit")
    req.header.frame_id = "brave6d_camera_optical_frame"
    req.estimates[0].pose.orientation.w = 2.0
    with pytest.raises(BraveError, match=r"estimates\[0\]\.pose\.orientation"):
        convert.estimates_from(req, "/s/submit")


def test_image_arrays_honour_row_padding() -> None:
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    padded = np.zeros((2, 12), dtype=np.uint8)
    padded[:, :9] = rgb.reshape(2, 9)
    msg = NS(encoding="rgb8", height=2, width=3, step=12, data=padded.tobytes(), is_bigendian=0)
    np.testing.assert_array_equal(convert.image_array(msg), rgb)
    depth = np.array([[0.5, np.nan], [1.0, 2.0]], dtype=">f4")
    msg = NS(encoding="32FC1", height=2, width=2, step=8, data=depth.tobytes(), is_bigendian=1)
    np.testing.assert_array_equal(convert.image_array(msg), depth.astype(np.float32))
    with pytest.raises(BraveError, match="bgr8"):
        convert.image_array(NS(encoding="bgr8"))

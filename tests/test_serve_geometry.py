"""Collision checks and twist integration of the render server (brave6d.serve.geometry)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.linalg import expm

from brave6d.core.transforms import check_rigid, look_at, make_transform, rpy_deg_to_matrix
from brave6d.serve.geometry import (
    CollisionWorld,
    OrientedBox,
    Workspace,
    integrate_twist,
    pose_after,
    se3_exp,
    substep_count,
)

WS = Workspace((0.0, -0.6, 0.02), (0.94, 0.6, 0.9))
TABLE = OrientedBox("table", make_transform(np.eye(3), (0.55, 0.0, -0.375)), (0.8, 1.0, 0.75))
POST = OrientedBox("post", make_transform(rpy_deg_to_matrix((0, 0, 45)), (0.45, 0.22, 0.15)), (0.06, 0.06, 0.3))
WORLD = CollisionWorld((TABLE, POST), WS, camera_radius=0.02)


def at(x: float, y: float, z: float) -> np.ndarray:
    return look_at((x, y, z), (0.45, 0.0, 0.0))


def test_oriented_box_distance() -> None:
    assert POST.distance((0.45, 0.22, 0.15)) == 0.0
    # along the rotated box's local x axis (world diagonal): 0.03 half size, point at 0.05
    d = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0])
    assert POST.distance(np.array((0.45, 0.22, 0.15)) + 0.05 * d) == pytest.approx(0.02, abs=1e-12)
    # above the top face
    assert POST.distance((0.45, 0.22, 0.35)) == pytest.approx(0.05, abs=1e-12)


def test_check_reports_workspace_and_collision() -> None:
    assert WORLD.check(at(0.3, 0.0, 0.3)) is None
    r = WORLD.check(at(0.3, 0.0, 0.01))
    assert r is not None and r.reason == "workspace" and "z=" in r.message
    r = WORLD.check(at(0.45, 0.22, 0.2))
    assert r is not None and r.reason == "collision" and r.box == "post"
    # the sphere radius matters: 1.5 cm above the post's top is a collision, 2.5 cm is not
    assert WORLD.check(at(0.45, 0.22, 0.315)) is not None
    assert WORLD.check(at(0.45, 0.22, 0.325)) is None


def hat6(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    X = np.zeros((4, 4))
    X[:3, :3] = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    X[:3, 3] = v
    return X


@given(st.lists(st.floats(-2, 2), min_size=6, max_size=6))
def test_se3_exp_matches_matrix_exponential(xi: list[float]) -> None:
    v, w = np.array(xi[:3]), np.array(xi[3:])
    np.testing.assert_allclose(se3_exp(v, w), expm(hat6(v, w)), atol=1e-9)
    check_rigid(se3_exp(v, w))


def test_camera_frame_twist_is_body_motion() -> None:
    T0 = at(0.3, -0.1, 0.3)
    # pure forward motion along the optical axis
    T = pose_after(T0, (0, 0, 0.1), (0, 0, 0), 1.0, "camera")
    np.testing.assert_allclose(T[:3, 3], T0[:3, 3] + 0.1 * T0[:3, 2], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], T0[:3, :3], atol=1e-12)
    # a yaw in place about the camera's y axis keeps the centre
    T = pose_after(T0, (0, 0, 0), (0, 0.5, 0), 1.0, "camera")
    np.testing.assert_allclose(T[:3, 3], T0[:3, 3], atol=1e-12)
    # world frame: straight line in the world, rotation about the centre
    T = pose_after(T0, (0, 0, 0.1), (0, 0, 1.0), 0.5, "world")
    np.testing.assert_allclose(T[:3, 3], T0[:3, 3] + (0, 0, 0.05), atol=1e-12)
    # exact: integrating in pieces equals integrating at once
    a = pose_after(pose_after(T0, (0.1, 0, 0.2), (0.3, -0.2, 0.1), 0.4, "camera"), (0.1, 0, 0.2), (0.3, -0.2, 0.1),
                   0.6, "camera")
    np.testing.assert_allclose(a, pose_after(T0, (0.1, 0, 0.2), (0.3, -0.2, 0.1), 1.0, "camera"), atol=1e-12)


def test_free_move_runs_the_whole_duration() -> None:
    T0 = at(0.3, -0.1, 0.3)
    res = integrate_twist(WORLD, T0, (0.0, 0.0, 0.05), (0, 0, 0), 1.0)
    assert res.refusal is None and res.fraction == 1.0 and res.path_m == pytest.approx(0.05)
    assert res.substeps == substep_count((0, 0, 0.05), (0, 0, 0), 1.0) == 10


def test_move_stops_at_the_first_collision() -> None:
    # straight down towards the table top (z = 0): the workspace floor (z = 0.02) stops it
    T0 = make_transform(rpy_deg_to_matrix((180, 0, 0)), (0.45, -0.2, 0.2))  # looking down
    res = integrate_twist(WORLD, T0, (0.0, 0.0, 0.1), (0, 0, 0), 5.0, keep_trajectory=True)
    assert res.refusal is not None and res.refusal.reason == "workspace"
    assert 0.0 < res.fraction < 1.0
    z = res.world_T_cam[2, 3]
    assert 0.02 <= z < 0.02 + 0.005 + 1e-12  # within one 5 mm substep of the floor
    assert WORLD.check(res.world_T_cam) is None
    assert all(WORLD.check(T) is None for T in res.trajectory)
    # sideways into the post: stops before the sphere touches it
    T0 = make_transform(np.eye(3), (0.45, 0.0, 0.15))
    res = integrate_twist(WORLD, T0, (0.0, 0.2, 0.0), (0, 0, 0), 2.0, frame="world")
    assert res.refusal is not None and res.refusal.box == "post"
    assert POST.distance(res.world_T_cam[:3, 3]) >= 0.02
    assert POST.distance(res.world_T_cam[:3, 3]) < 0.02 + 0.005 + 1e-9


def test_move_blocked_at_the_first_substep_goes_nowhere() -> None:
    T0 = make_transform(np.eye(3), (0.45, 0.22 - 0.03 - 0.0201, 0.15))  # 0.1 mm from touching the post
    res = integrate_twist(WORLD, T0, (0.0, 0.1, 0.0), (0, 0, 0), 1.0, frame="world")
    assert not res.moved and res.fraction == 0.0
    np.testing.assert_array_equal(res.world_T_cam, T0)


def test_thin_walls_are_not_tunnelled() -> None:
    wall = OrientedBox("thin", make_transform(np.eye(3), (0.5, 0.0, 0.3)), (0.002, 1.0, 1.0))
    world = CollisionWorld((wall,), WS, camera_radius=0.0)
    T0 = make_transform(np.eye(3), (0.3, 0.0, 0.3))
    res = integrate_twist(world, T0, (1.0, 0.0, 0.0), (0, 0, 0), 0.4, frame="world")
    assert res.collided and res.world_T_cam[0, 3] < 0.499


def test_invalid_moves_raise() -> None:
    T0 = at(0.3, 0.0, 0.3)
    with pytest.raises(ValueError, match="duration"):
        integrate_twist(WORLD, T0, (0, 0, 0.1), (0, 0, 0), float("nan"))
    with pytest.raises(ValueError, match="frame"):
        integrate_twist(WORLD, T0, (0, 0, 0.1), (0, 0, 0), 1.0, frame="tool")
    with pytest.raises(ValueError, match="too long"):
        integrate_twist(WORLD, T0, (0, 0, 1000.0), (0, 0, 0), 10.0)

"""SimRobot (virtual clock, motion model, effects), and URRobot with nothing listening (the rest of URRobot: the
real client against the emulator, test_ur_emulator.py)."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.spec import EffectsSpec, RobotPoseError, RobotSpec, SensorNoise, TimeOffset, parse_scene_spec
from brave6d.core.transforms import make_transform, rotation_distance
from brave6d.capture.kinematics import URKinematics
from brave6d.capture.protocols import Robot, RobotError
from brave6d.capture.sim_robot import SimRobot, joint_move_time, trapezoid_fraction, trapezoid_time
from brave6d.capture.ur_robot import URRobot

HOME = np.deg2rad([0, -90, 90, -90, -90, 0])
Q_A = np.array([0.2, -1.2, 1.5, -1.8, -1.5, 0.3])
Q_B = np.array([-0.4, -1.6, 1.1, -1.2, -1.7, -0.5])
POSE_ERR = RobotPoseError(translation_sigma_m=0.002, rotation_sigma_deg=0.2)


def spec_robot(**kw: Any) -> RobotSpec:
    return RobotSpec(**kw)


# ============================================================================ motion model
@settings(max_examples=80, deadline=None)
@given(d1=st.floats(0.0, 10.0), d2=st.floats(0.0, 10.0),
       v=st.floats(0.1, 3.0), a=st.floats(0.1, 20.0))
def test_trapezoid_time_monotone_and_bounded(d1: float, d2: float, v: float, a: float) -> None:
    lo, hi = sorted((d1, d2))
    t_lo, t_hi = trapezoid_time(lo, v, a), trapezoid_time(hi, v, a)
    assert t_lo <= t_hi + 1e-12
    if hi <= 1e-12:  # null move
        assert t_hi == 0.0 and trapezoid_fraction(0.0, hi, v, a) == 1.0
        return
    assert t_hi >= hi / v - 1e-12  # never faster than full speed all the way
    assert t_hi >= 2 * math.sqrt(hi / a) - 1e-9  # never faster than the acceleration allows
    # the profile covers the whole distance exactly at the end, and is monotone
    ts = np.linspace(0, t_hi, 50)
    s = [trapezoid_fraction(t, hi, v, a) for t in ts]
    assert s[-1] == pytest.approx(1.0)
    assert all(x <= y + 1e-12 for x, y in zip(s[:-1], s[1:]))


def test_joint_motion_respects_speed_and_acceleration_limits() -> None:
    spec = spec_robot(joint_speed=0.8, joint_acceleration=1.5)
    robot = SimRobot(spec, start_joints=Q_A)
    t0 = robot.now()
    robot.move_joints(Q_B)
    t1 = robot.now()
    delta = np.max(np.abs(Q_B - Q_A))
    assert t1 - t0 == pytest.approx(trapezoid_time(delta, 0.8, 1.5))
    assert t1 - t0 == pytest.approx(joint_move_time(Q_A, Q_B, 0.8, 1.5))
    dt = 1e-3
    ts = np.arange(t0, t1 + dt, dt)
    qs = np.array([robot.joints_at(t) for t in ts])
    vel = np.diff(qs, axis=0) / dt
    acc = np.diff(vel, axis=0) / dt
    assert np.max(np.abs(vel)) <= 0.8 * (1 + 1e-6)
    assert np.max(np.abs(acc)) <= 1.5 * 1.05
    # synchronised: all joints reach the target at the same time, along a straight joint line
    frac = (qs - Q_A) / (Q_B - Q_A)
    assert np.allclose(frac, frac[:, :1], atol=1e-9)
    np.testing.assert_allclose(robot.joints_at(t1), Q_B, atol=1e-12)
    np.testing.assert_allclose(robot.joints_at(t0 - 5.0), Q_A, atol=1e-12)


def test_clock_is_monotone_and_virtual() -> None:
    robot = SimRobot(spec_robot(), start_joints=Q_A)
    wall = time.perf_counter()
    times = [robot.now()]
    for q in (Q_B, Q_A, Q_B):
        robot.move_joints(q)
        times.append(robot.now())
        robot.wait_until_steady(0.3)
        times.append(robot.now())
    assert all(b > a for a, b in zip(times[:-1], times[1:]))
    assert times[2] - times[1] == pytest.approx(0.3)
    assert time.perf_counter() - wall < 1.0  # no real sleeping (virtual time is several seconds)
    assert times[-1] > 3.0


def test_longer_moves_take_longer() -> None:
    robot = SimRobot(spec_robot(), start_joints=Q_A)
    durations = []
    for scale in (0.1, 0.3, 1.0):
        start = robot.now()
        robot.move_joints(Q_A + scale * (Q_B - Q_A))
        durations.append(robot.now() - start)
        robot.move_joints(Q_A)
    assert durations[0] < durations[1] < durations[2]


def test_true_pose_follows_the_trajectory_without_effects() -> None:
    robot = SimRobot(spec_robot(), start_joints=Q_A)
    kin = URKinematics("ur5e")
    robot.move_joints(Q_B)
    mid = 0.5 * robot.now()
    np.testing.assert_allclose(robot.true_base_T_tcp(mid), kin.fk(robot.joints_at(mid)), atol=1e-12)
    np.testing.assert_allclose(robot.true_base_T_tcp(), kin.fk(Q_B), atol=1e-12)
    np.testing.assert_allclose(robot.tcp_pose(), kin.fk(Q_B), atol=1e-12)
    assert robot.is_moving(mid) and not robot.is_moving()


def test_move_to_reaches_pose_and_linear_path_is_straight() -> None:
    spec = spec_robot(linear_speed=0.2, linear_acceleration=1.0)
    robot = SimRobot(spec, start_joints=Q_A)
    T0 = robot.tcp_pose()
    T1 = T0.copy()
    T1[:3, 3] += [0.08, -0.05, 0.04]
    robot.move_to(T1)
    np.testing.assert_allclose(robot.tcp_pose(), T1, atol=1e-9)
    t_start = robot.now()
    T2 = T1.copy()
    T2[:3, 3] += [-0.12, 0.0, 0.0]
    robot.move_to(T2, linear=True)
    assert robot.now() - t_start == pytest.approx(trapezoid_time(0.12, 0.2, 1.0))
    for t in np.linspace(t_start, robot.now(), 7):
        p = robot.true_base_T_tcp(t)[:3, 3]
        # on the segment T1 -> T2 and the orientation unchanged
        assert abs(p[1] - T1[1, 3]) < 1e-12 and abs(p[2] - T1[2, 3]) < 1e-12
        assert rotation_distance(robot.true_base_T_tcp(t), T1) < 1e-9
        np.testing.assert_allclose(URKinematics("ur5e").fk(robot.joints_at(t))[:3, 3], p, atol=2e-3)
    np.testing.assert_allclose(robot.tcp_pose(), T2, atol=1e-9)


def test_unreachable_target_is_refused_naming_the_pose() -> None:
    robot = SimRobot(spec_robot())
    before = robot.now()
    T = make_transform(np.eye(3), [1.5, 0.2, 0.3])
    with pytest.raises(RobotError, match=r"\[1\.5000, 0\.2000, 0\.3000.*unreachable"):
        robot.move_to(T)
    with pytest.raises(RobotError, match="1.5000"):
        robot.move_to(T, linear=True)
    with pytest.raises(RobotError, match="joint limits"):
        robot.move_joints(np.full(6, 7.0))
    assert robot.now() == before and robot.move_count == 0


def test_protocol_fault_and_close() -> None:
    robot = SimRobot(spec_robot())
    assert isinstance(robot, Robot)
    robot.inject_fault("protective stop")
    with pytest.raises(RobotError, match="protective stop"):
        robot.move_joints(Q_A)
    robot.clear_fault()
    robot.move_joints(Q_A)
    robot.stop()
    robot.close()
    with pytest.raises(RobotError, match="closed"):
        robot.move_joints(Q_B)
    assert robot.inverse_kinematics(robot.tcp_pose(), Q_A) is not None
    np.testing.assert_allclose(robot.inverse_kinematics(robot.tcp_pose(), Q_A), Q_A, atol=1e-8)
    assert robot.inverse_kinematics(make_transform(np.eye(3), [3.0, 0, 0])) is None


# ============================================================================ effects
def _run(robot: SimRobot) -> list[np.ndarray]:
    out = []
    for q in (Q_A, Q_B, Q_A, Q_B):
        robot.move_joints(q)
        robot.wait_until_steady(0.2)
        out += [robot.tcp_pose(), robot.true_base_T_tcp(), robot.joints()]
    return out


def test_unlisted_effects_change_nothing_and_draw_nothing() -> None:
    plain = SimRobot(spec_robot(), start_joints=HOME)
    camera_only = SimRobot(spec_robot(), start_joints=HOME, seed=7,
                           effects=EffectsSpec(sensor_noise=SensorNoise(sigma=3.0)))
    a, b = _run(plain), _run(camera_only)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert plain.random_draws == 0 and camera_only.random_draws == 0
    for i in range(0, len(a), 3):  # reported == true without pose error
        np.testing.assert_array_equal(a[i], a[i + 1])


def test_robot_pose_error_moves_the_true_pose_only() -> None:
    robot = SimRobot(spec_robot(), start_joints=HOME, seed=3, effects=EffectsSpec(robot_pose_error=POSE_ERR))
    kin = URKinematics("ur5e")
    trans, rots = [], []
    q_targets = [Q_A + 0.05 * k * (Q_B - Q_A) for k in range(1, 41)]
    for q in q_targets:
        robot.move_joints(q)
        reported, actual = robot.tcp_pose(), robot.true_base_T_tcp()
        np.testing.assert_allclose(reported, kin.fk(q), atol=1e-12)  # reports the commanded pose
        d = np.linalg.inv(reported) @ actual
        trans.append(d[:3, 3])
        rots.append(math.degrees(rotation_distance(d, np.eye(4))))
    trans = np.array(trans)
    assert robot.random_draws == 6 * len(q_targets)
    # per-axis spread matches the sigma (120 samples: within 35 %), rotation angle ~ sigma * chi(3)
    assert 0.65 * 0.002 < trans.std() < 1.35 * 0.002
    assert 0.5 * 0.2 * 1.6 < np.mean(rots) < 1.5 * 0.2 * 1.6
    # seeded: the same seed gives the same actual poses, another seed different ones
    same = SimRobot(spec_robot(), start_joints=HOME, seed=3, effects=EffectsSpec(robot_pose_error=POSE_ERR))
    other = SimRobot(spec_robot(), start_joints=HOME, seed=4, effects=EffectsSpec(robot_pose_error=POSE_ERR))
    for r in (same, other):
        for q in q_targets:
            r.move_joints(q)
    np.testing.assert_array_equal(same.true_base_T_tcp(), robot.true_base_T_tcp())
    assert not np.allclose(other.true_base_T_tcp(), robot.true_base_T_tcp())


def test_pose_error_blends_during_a_move() -> None:
    robot = SimRobot(spec_robot(), start_joints=Q_A, seed=1, effects=EffectsSpec(robot_pose_error=POSE_ERR))
    robot.move_joints(Q_B)
    E1 = np.linalg.inv(robot.commanded_base_T_tcp()) @ robot.true_base_T_tcp()
    t_mid_start = robot.now()
    robot.move_joints(Q_A)
    E2 = np.linalg.inv(robot.commanded_base_T_tcp()) @ robot.true_base_T_tcp()
    t_half = 0.5 * (t_mid_start + robot.now())
    Em = np.linalg.inv(robot.commanded_base_T_tcp(t_half)) @ robot.true_base_T_tcp(t_half)
    np.testing.assert_allclose(Em[:3, 3], 0.5 * (E1[:3, 3] + E2[:3, 3]), atol=1e-12)


def test_time_offset_reports_a_stale_pose_while_moving() -> None:
    off = 0.05
    robot = SimRobot(spec_robot(), start_joints=Q_A, effects=EffectsSpec(time_offset=TimeOffset(offset_s=off)))
    robot.move_joints(Q_B)
    now = robot.now()
    np.testing.assert_allclose(robot.joints(), robot.joints_at(now - off), atol=1e-12)
    np.testing.assert_allclose(robot.tcp_pose(), robot.commanded_base_T_tcp(now - off), atol=1e-12)
    assert np.max(np.abs(robot.joints() - Q_B)) > 1e-6  # still behind the arm
    np.testing.assert_allclose(robot.true_base_T_tcp(), robot.commanded_base_T_tcp(), atol=1e-12)
    robot.wait_until_steady(off)  # once still, the stale pose is the final pose
    np.testing.assert_allclose(robot.joints(), Q_B, atol=1e-12)
    assert robot.random_draws == 0
    plain = SimRobot(spec_robot(), start_joints=Q_A)
    plain.move_joints(Q_B)
    np.testing.assert_allclose(plain.joints(), Q_B, atol=1e-12)


def test_effect_streams_are_independent() -> None:
    a = SimRobot(spec_robot(), start_joints=HOME, seed=5, effects=EffectsSpec(robot_pose_error=POSE_ERR))
    b = SimRobot(spec_robot(), start_joints=HOME, seed=5,
                 effects=EffectsSpec(robot_pose_error=POSE_ERR, time_offset=TimeOffset(offset_s=0.02)))
    for r in (a, b):
        for q in (Q_A, Q_B):
            r.move_joints(q)
    np.testing.assert_array_equal(a.true_base_T_tcp(), b.true_base_T_tcp())


def test_from_spec_uses_seed_and_effects() -> None:
    data = {
        "name": "t", "capture": {"target": [0.45, 0.0, 0.02]},
        "workspace": {"min": [-1, -1, 0], "max": [1, 1, 1]},
        "simulation": {"true_tcp_T_camera": {"xyz": [0, 0, 0.05]}, "seed": 11,
                       "effects": {"robot_pose_error": {"translation_sigma_m": 0.001}}},
    }
    spec = parse_scene_spec(data, check_files=False)
    r = SimRobot.from_spec(spec)
    assert r.seed == 11 and r.effects.robot_pose_error is not None
    calib = SimRobot.from_spec(spec, effects=EffectsSpec())
    assert calib.effects.robot_pose_error is None
    r.move_joints(Q_A)
    calib.move_joints(Q_A)
    assert r.random_draws == 6 and calib.random_draws == 0


# ============================================================================ URRobot
# URRobot is tested with the real ur-rtde client against brave6d ur-emulator in test_ur_emulator.py.
def test_real_ur_rtde_fails_fast_with_our_error() -> None:
    """ur-rtde against 127.0.0.1 with nothing listening: our RobotError, quickly."""
    pytest.importorskip("rtde_control")
    result: dict[str, Any] = {}

    def attempt() -> None:
        t0 = time.perf_counter()
        try:
            URRobot("127.0.0.1", RobotSpec(), connect_tries=2, retry_pause_s=0.05)
        except BaseException as exc:  # noqa: BLE001
            result["exc"] = exc
        result["elapsed"] = time.perf_counter() - t0

    worker = threading.Thread(target=attempt, daemon=True)
    worker.start()
    worker.join(10.0)
    if worker.is_alive() or result.get("elapsed", 0.0) > 10.0:
        pytest.skip("ur-rtde took more than 10 s to fail on 127.0.0.1 here")
    exc = result.get("exc")
    assert isinstance(exc, RobotError), repr(exc)
    assert str(exc).startswith("Could not connect to UR robot at 127.0.0.1 after 2 tries: ")
    assert "Could not connect" in str(exc).split("tries: ", 1)[1]

"""UR forward/inverse kinematics: hand-derived poses, FK(IK(T)) == T, solution counts against an
independent numerical solver, singularities, unreachable poses, joint limits and normalisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq, least_squares
from scipy.spatial.transform import Rotation

from brave6d.core.errors import NonRigidTransformError
from brave6d.core.transforms import make_transform
from brave6d.capture.kinematics import (
    UR_DH,
    URKinematics,
    closest_solution,
    joint_distance,
    max_joint_step,
    nearest_representative,
    wrap_to_pi,
)

MODELS = sorted(UR_DH)
KIN = {m: URKinematics(m) for m in MODELS}
TOL = 1e-9


def fk_error(kin: URKinematics, q: np.ndarray, T: np.ndarray) -> float:
    return float(np.max(np.abs(kin.fk(q) - T)))


def assert_all_solutions_exact(kin: URKinematics, T: np.ndarray, res) -> None:
    assert np.all(np.isfinite(res.solutions))
    for q in res.solutions:
        assert fk_error(kin, q, T) < TOL
        assert kin.within_limits(q)


# ----------------------------------------------------------------------------- forward kinematics
@pytest.mark.parametrize("model", MODELS)
def test_fk_zero_and_home_match_hand_derivation(model: str) -> None:
    """All zeros: arm stretched along -x; home (0,-90,90,-90,-90,0): forearm horizontal, tool down."""
    kin, dh = KIN[model], UR_DH[model]
    T0 = kin.fk(np.zeros(6))
    np.testing.assert_allclose(T0[:3, 3], [dh.a2 + dh.a3, -(dh.d4 + dh.d6), dh.d1 - dh.d5], atol=1e-12)
    np.testing.assert_allclose(T0[:3, 2], [0.0, -1.0, 0.0], atol=1e-12)  # tool axis along -y
    home = np.deg2rad([0, -90, 90, -90, -90, 0])
    Th = kin.fk(home)
    np.testing.assert_allclose(Th[:3, 3], [dh.a3 - dh.d5, -dh.d4, dh.d1 - dh.a2 - dh.d6], atol=1e-12)
    np.testing.assert_allclose(Th[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)  # tool points down


def test_fk_joint1_rotates_about_base_z() -> None:
    kin = KIN["ur5e"]
    q = np.array([0.0, -1.0, 1.2, -0.5, 0.7, 0.3])
    for a in (0.4, -2.0):
        q2 = q.copy()
        q2[0] += a
        Rz = make_transform(Rotation.from_euler("z", a).as_matrix(), np.zeros(3))
        np.testing.assert_allclose(kin.fk(q2), Rz @ kin.fk(q), atol=1e-12)


def test_tool_offset_applies_on_the_right() -> None:
    off = make_transform(Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix(), [0.01, -0.02, 0.15])
    kin = URKinematics("ur5e", flange_T_tcp=off)
    q = np.array([0.3, -1.1, 1.4, -0.8, 1.2, 0.5])
    np.testing.assert_allclose(kin.fk(q), kin.fk_flange(q) @ off, atol=1e-14)
    res = kin.ik(kin.fk(q), q)
    assert res.reachable
    np.testing.assert_allclose(res.solutions[0], q, atol=1e-8)
    assert_all_solutions_exact(kin, kin.fk(q), res)


# ----------------------------------------------------------------------------- IK round trips
joint_vectors = st.lists(st.floats(-math.pi, math.pi, allow_nan=False), min_size=6, max_size=6).map(np.array)


@settings(max_examples=150, deadline=None)
@given(model=st.sampled_from(MODELS), q=joint_vectors)
def test_ik_round_trip_random_poses(model: str, q: np.ndarray) -> None:
    kin = KIN[model]
    T = kin.fk(q)
    res = kin.ik(T, q_near=q)
    assert res.reachable, res.reason
    assert 1 <= len(res) <= 8
    assert_all_solutions_exact(kin, T, res)
    # the generating joints come back as the first solution (closest to q_near) when the pose is
    # well conditioned; near a singularity joint space is ill-posed and only the pose must match
    if not res.singular and abs(math.sin(q[2])) > 1e-3 and abs(math.sin(q[4])) > 1e-3:
        np.testing.assert_allclose(res.solutions[0], q, atol=1e-6)
    # branch labels are distinct
    assert len({tuple(b) for b in res.branches}) == len(res)


@settings(max_examples=60, deadline=None)
@given(model=st.sampled_from(MODELS), q=joint_vectors,
       q5=st.sampled_from([0.0, 1e-13, -1e-11, 1e-9, math.pi, math.pi - 1e-12]))
def test_ik_near_wrist_singularity(model: str, q: np.ndarray, q5: float) -> None:
    kin = KIN[model]
    q = q.copy()
    q[4] = q5
    T = kin.fk(q)
    res = kin.ik(T, q_near=q)
    assert res.reachable, res.reason
    assert_all_solutions_exact(kin, T, res)
    if abs(math.sin(q5)) < 1e-10:
        assert "wrist" in res.singular
        # q6 is free: the solver takes it from q_near, so the given joints come back exactly
        np.testing.assert_allclose(res.solutions[0], q, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(model=st.sampled_from(MODELS), q=joint_vectors,
       q3=st.sampled_from([0.0, 1e-12, -1e-9, 1e-6, math.pi, -math.pi + 1e-10]))
def test_ik_near_elbow_singularity(model: str, q: np.ndarray, q3: float) -> None:
    kin = KIN[model]
    q = q.copy()
    q[2] = q3
    T = kin.fk(q)
    res = kin.ik(T, q_near=q)
    assert res.reachable, res.reason
    assert_all_solutions_exact(kin, T, res)


def _shoulder_singular_q2(model: str, q3: float, q4: float) -> float:
    """q2 that puts the wrist centre exactly at the shoulder-offset distance d4 from the base axis."""
    dh = UR_DH[model]

    def planar(q2: float) -> float:
        return dh.a2 * math.cos(q2) + dh.a3 * math.cos(q2 + q3) + dh.d5 * math.sin(q2 + q3 + q4)

    xs = np.linspace(-math.pi, math.pi, 721)
    vals = [planar(x) for x in xs]
    for a, b, fa, fb in zip(xs[:-1], xs[1:], vals[:-1], vals[1:]):
        if fa * fb < 0:
            return float(brentq(planar, a, b, xtol=1e-15))
    raise AssertionError("no shoulder-singular configuration found")


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("eps", [0.0, 1e-12, -1e-10, 1e-8])
@pytest.mark.parametrize("q5", [1.0, 0.0])
def test_ik_near_shoulder_singularity(model: str, eps: float, q5: float) -> None:
    kin = KIN[model]
    q2 = _shoulder_singular_q2(model, 1.3, 0.4)
    q = np.array([0.7, q2 + eps, 1.3, 0.4, q5, -0.6])
    T = kin.fk(q)
    p05 = T[:3, 3] - UR_DH[model].d6 * T[:3, 2]
    assert math.hypot(p05[0], p05[1]) == pytest.approx(UR_DH[model].d4, abs=1e-6)
    res = kin.ik(T, q_near=q)
    assert res.reachable, res.reason
    assert_all_solutions_exact(kin, T, res)
    if eps == 0.0:
        assert "shoulder" in res.singular


# ----------------------------------------------------------------------------- solution counts
def _numeric_solutions(kin: URKinematics, T: np.ndarray, starts: int = 40) -> list[np.ndarray]:
    """Distinct IK solutions found by least squares from many random starts (independent check)."""
    rng = np.random.default_rng(0)
    found: list[np.ndarray] = []

    def residual(q: np.ndarray) -> np.ndarray:
        F = kin.fk(q)
        return np.concatenate([F[:3, 3] - T[:3, 3], 0.3 * (F[:3, :3] - T[:3, :3]).ravel()])

    for _ in range(starts):
        sol = least_squares(residual, rng.uniform(-math.pi, math.pi, 6), xtol=1e-14, ftol=1e-14, gtol=1e-14)
        if np.max(np.abs(residual(sol.x))) < 1e-8:
            w = wrap_to_pi(sol.x)
            if not any(np.max(np.abs(wrap_to_pi(w - f))) < 1e-4 for f in found):
                found.append(w)
    return found


@pytest.mark.slow
@pytest.mark.parametrize("model", MODELS)
def test_solution_count_matches_numerical_search(model: str) -> None:
    kin = KIN[model]
    rng = np.random.default_rng(5)
    poses = [kin.fk(np.deg2rad([0, -90, 90, -90, -90, 0])), kin.fk(rng.uniform(-math.pi, math.pi, 6)),
             kin.fk(np.array([0.3, -1.0, 1.4, -0.9, 1.1, 0.2]))]
    counts = []
    for T in poses:
        res = kin.ik(T)
        numeric = _numeric_solutions(kin, T)
        assert len(res) == len(numeric)
        for qn in numeric:  # every numerically found solution is among the analytic ones
            assert min(np.max(np.abs(wrap_to_pi(qn - qa))) for qa in res.solutions) < 1e-6
        counts.append(len(res))
    assert counts[0] == 8 and counts[2] == 8  # generic poses in the middle of the workspace


@pytest.mark.parametrize("model", MODELS)
def test_generic_compact_pose_has_eight_distinct_branches(model: str) -> None:
    kin = KIN[model]
    q = np.array([0.3, -1.0, 1.4, -0.9, 1.1, 0.2])
    res = kin.ik(kin.fk(q))
    assert len(res) == 8
    assert {tuple(b) for b in res.branches} == {(s, e, w) for s in (1, -1) for e in (1, -1) for w in (1, -1)}
    assert not res.singular


# ----------------------------------------------------------------------------- unreachable
def test_far_pose_is_unreachable_with_reason() -> None:
    kin = KIN["ur5e"]
    res = kin.ik(make_transform(np.eye(3), [2.0, 0.0, 0.3]))
    assert not res.reachable
    assert res.solutions.shape == (0, 6)
    assert "out of reach" in res.reason


@pytest.mark.parametrize("model", MODELS)
def test_reach_boundary_is_sharp(model: str) -> None:
    """Along a ray from the shoulder (tool pointing outwards), find the reach boundary D* by
    bisection: 0.1 um beyond it the answer is 'out of reach' naming the elbow, 0.1 um inside it
    all solutions are exact."""
    kin = KIN[model]
    direction = np.array([0.6, 0.3, 0.2]) / np.linalg.norm([0.6, 0.3, 0.2])
    R = Rotation.align_vectors([direction], [[0.0, 0.0, 1.0]])[0].as_matrix()

    def pose(D: float) -> np.ndarray:
        return make_transform(R, np.array([0.0, 0.0, UR_DH[model].d1]) + D * direction)

    lo, hi = 0.6 * (abs(UR_DH[model].a2) + abs(UR_DH[model].a3)), 3.0
    assert kin.ik(pose(lo)).reachable and not kin.ik(pose(hi)).reachable
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if kin.ik(pose(mid)).reachable else (lo, mid)
    outside = kin.ik(pose(hi + 1e-7))
    assert not outside.reachable
    assert "out of reach" in outside.reason and "elbow" in outside.reason
    inside = kin.ik(pose(lo - 1e-7))
    assert inside.reachable
    assert_all_solutions_exact(kin, pose(lo - 1e-7), inside)


@pytest.mark.parametrize("r", [0.0, 0.05, 0.1332])
def test_wrist_centre_inside_shoulder_cylinder_is_unreachable(r: float) -> None:
    kin = KIN["ur5e"]
    d6 = UR_DH["ur5e"].d6
    # tool pointing down, wrist centre at distance r < d4 from the base z axis
    T = make_transform(np.diag([1.0, -1.0, -1.0]), [r, 0.0, 0.5 - d6])
    res = kin.ik(T)
    assert not res.reachable
    assert "base z axis" in res.reason
    assert not np.any(np.isnan(res.solutions))


@settings(max_examples=60, deadline=None)
@given(xyz=st.tuples(*[st.floats(-1.5, 1.5, allow_nan=False)] * 3),
       rv=st.tuples(*[st.floats(-3.0, 3.0, allow_nan=False)] * 3))
def test_arbitrary_poses_give_exact_solutions_or_a_reason(xyz, rv) -> None:
    kin = KIN["ur5e"]
    T = make_transform(Rotation.from_rotvec(rv).as_matrix(), xyz)
    res = kin.ik(T)
    if res.reachable:
        assert_all_solutions_exact(kin, T, res)
        assert res.reason == ""
    else:
        assert res.reason
        assert res.solutions.shape == (0, 6)


def test_non_finite_or_non_rigid_target_raises() -> None:
    kin = KIN["ur5e"]
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(NonRigidTransformError):
        kin.ik(T)
    with pytest.raises(NonRigidTransformError):
        kin.ik(np.diag([2.0, 1.0, 1.0, 1.0]))


# ----------------------------------------------------------------------------- limits and normalisation
def test_solutions_respect_custom_joint_limits() -> None:
    limits = np.tile([-math.pi / 2, math.pi / 2], (6, 1))
    limits[1] = [-math.pi, 0.0]
    kin = URKinematics("ur5e", joint_limits=limits)
    q = np.array([0.3, -1.0, 1.2, -0.5, 0.8, 0.2])
    res = kin.ik(kin.fk(q))
    assert res.reachable
    assert np.all(res.solutions >= limits[:, 0]) and np.all(res.solutions <= limits[:, 1])
    assert len(res) < len(KIN["ur5e"].ik(kin.fk(q)))
    narrow = URKinematics("ur5e", joint_limits=np.tile([-0.01, 0.01], (6, 1)))
    res2 = narrow.ik(kin.fk(q))
    assert not res2.reachable and "joint limits" in res2.reason


def test_representatives_follow_q_near() -> None:
    kin = KIN["ur5e"]
    q = np.array([-3.0, -1.0, 1.2, -0.5, 0.8, -3.0])
    near = q.copy()
    near[0] += 2 * math.pi
    near[5] += 2 * math.pi
    res = kin.ik(kin.fk(q), q_near=near)
    np.testing.assert_allclose(res.solutions[0], near, atol=1e-8)  # same angles, the other turn
    res0 = kin.ik(kin.fk(q))  # without q_near: principal values, q itself among them
    assert np.all(np.abs(res0.solutions) <= math.pi + 1e-12)
    assert min(np.max(np.abs(s - q)) for s in res0.solutions) < 1e-8


def test_ik_closest_branch_and_max_step() -> None:
    kin = KIN["ur5e"]
    q = np.array([0.3, -1.0, 1.4, -0.9, 1.1, 0.2])
    T = kin.fk(q)
    np.testing.assert_allclose(kin.ik_closest(T, q + 0.05), q, atol=1e-8)
    assert kin.ik_closest(T, q + 0.5, max_step=0.1) is None
    br = kin.branch_of(q)
    other = (-br[0], br[1], br[2])
    sol = kin.ik_closest(T, q, branch=other)
    assert sol is not None and kin.branch_of(sol) == other
    assert max_joint_step(sol, q) > 0.5  # another configuration is far away in joint space


def test_joint_space_helpers() -> None:
    a = np.zeros(6)
    b = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 2 * math.pi - 0.1])
    assert joint_distance(a, b) == pytest.approx(2 * math.pi - 0.1)
    assert joint_distance(a, b, wrapped=True) == pytest.approx(0.1)
    assert joint_distance(a, np.ones(6), weights=[1, 0, 0, 0, 0, 0]) == pytest.approx(1.0)
    sols = np.array([[0.0] * 6, [0.5] * 6, [3.0] * 6])
    assert closest_solution(sols, np.full(6, 0.4)) == 1
    assert closest_solution(sols, np.full(6, 2.0), max_step=0.5) is None
    assert closest_solution(np.zeros((0, 6)), np.zeros(6)) is None
    rep = nearest_representative([3.0] * 6, [-3.0] * 6)
    np.testing.assert_allclose(rep, 3.0 - 2 * math.pi)
    assert nearest_representative([3.0] * 6, None, np.tile([-1.0, 1.0], (6, 1))) is None
    np.testing.assert_allclose(wrap_to_pi([math.pi, -math.pi, 3 * math.pi]), [math.pi] * 3)

"""Rigid transforms: round trips, hard cases (angle 0, near pi, exactly pi, sign flips,
degenerate look-at) and rejection of non-rigid input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.core.errors import NonRigidTransformError
from brave6d.core.transforms import (
    ROTATION_TOLERANCE,
    check_rigid,
    format_tum_line,
    invert,
    look_at,
    make_transform,
    matrix_to_quat_wxyz,
    matrix_to_rpy_deg,
    matrix_to_tum,
    matrix_to_ur_pose,
    nearest_rigid,
    QUATERNION_TOLERANCE,
    nearest_rotation,
    unit_quaternion,
    orthonormalize,
    ring_orbit,
    parse_tum_line,
    pose_distance,
    quat_wxyz_to_matrix,
    rotation_angle,
    rotation_distance,
    rpy_deg_to_matrix,
    transform_points,
    tum_to_matrix,
    ur_pose_to_matrix,
)

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite)
unit_quats = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(
    lambda q: np.linalg.norm(q) > 1e-3).map(lambda q: np.asarray(q) / np.linalg.norm(q))
poses = st.tuples(vec3, unit_quats).map(
    lambda tq: make_transform(Rotation.from_quat(tq[1]).as_matrix(), tq[0]))


def assert_same_transform(A: np.ndarray, B: np.ndarray, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(A, B, atol=atol, rtol=0)


# ----------------------------------------------------------------------------- round trips
@given(poses)
def test_ur_pose_round_trip(T: np.ndarray) -> None:
    pose = matrix_to_ur_pose(T)
    assert len(pose) == 6 and all(math.isfinite(v) for v in pose)
    assert np.linalg.norm(pose[3:]) <= math.pi + 1e-12
    assert_same_transform(ur_pose_to_matrix(pose), T)


@given(poses)
def test_tum_round_trip_and_text(T: np.ndarray) -> None:
    values = matrix_to_tum(T)
    assert values[6] >= 0.0  # canonical sign: qw >= 0
    assert_same_transform(tum_to_matrix(values), T)
    frame_id, parsed = parse_tum_line(format_tum_line(17, T))
    assert frame_id == "17"
    assert_same_transform(parsed, T)


@given(poses)
def test_inverse_is_exact(T: np.ndarray) -> None:
    assert_same_transform(invert(T) @ T, np.eye(4), atol=1e-12 * max(1.0, np.abs(T).max()) * 10)
    assert_same_transform(invert(invert(T)), T)


@given(poses, st.lists(vec3, min_size=1, max_size=5))
def test_transform_points_matches_homogeneous(T: np.ndarray, pts: list) -> None:
    P = np.asarray(pts)
    homog = (T @ np.c_[P, np.ones(len(P))].T).T[:, :3]
    np.testing.assert_allclose(transform_points(T, P), homog, atol=1e-12)


@given(unit_quats)
def test_quaternion_wxyz_round_trip_and_sign_flip(q_xyzw: np.ndarray) -> None:
    q_wxyz = q_xyzw[[3, 0, 1, 2]]
    R = quat_wxyz_to_matrix(q_wxyz)
    np.testing.assert_allclose(quat_wxyz_to_matrix(-q_wxyz), R, atol=1e-12)  # q and -q: same rotation
    back = matrix_to_quat_wxyz(R)
    assert back[0] >= 0.0
    np.testing.assert_allclose(abs(back @ q_wxyz), 1.0, atol=1e-9)


@given(st.tuples(st.floats(-179, 179), st.floats(-89, 89), st.floats(-179, 179)))
def test_rpy_round_trip(rpy: tuple) -> None:
    np.testing.assert_allclose(matrix_to_rpy_deg(rpy_deg_to_matrix(rpy)), rpy, atol=1e-7)


# ----------------------------------------------------------------------------- hard cases
@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, math.pi - 1e-9, math.pi - 1e-6, math.pi])
@pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1), (-0.3, 0.2, 0.9)])
def test_rotation_vector_edge_angles(angle: float, axis: tuple) -> None:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    pose = [0.1, -0.2, 0.3, *(a * angle)]
    T = ur_pose_to_matrix(pose)
    back = matrix_to_ur_pose(T)
    assert all(math.isfinite(v) for v in back)
    assert_same_transform(ur_pose_to_matrix(back), T)
    assert abs(np.linalg.norm(back[3:]) - angle) < 1e-7
    assert abs(rotation_angle(T[:3, :3]) - angle) < 1e-7


def test_rotation_distance_is_accurate_near_zero_and_pi() -> None:
    R0 = rpy_deg_to_matrix((10, 20, 30))
    tiny = Rotation.from_rotvec([1e-9, 0, 0]).as_matrix()
    assert abs(rotation_distance(R0, R0 @ tiny) - 1e-9) < 1e-12  # arccos-based formulas fail here
    flip = Rotation.from_rotvec([0, math.pi, 0]).as_matrix()
    assert abs(rotation_distance(R0, R0 @ flip) - math.pi) < 1e-9
    T1, T2 = make_transform(R0, [0, 0, 0]), make_transform(R0 @ flip, [3, 4, 0])
    rot, trans = pose_distance(T1, T2)
    assert abs(rot - math.pi) < 1e-9 and abs(trans - 5.0) < 1e-12


@given(vec3, vec3)
def test_look_at_points_optical_axis_at_target(eye: tuple, target: tuple) -> None:
    e, t = np.asarray(eye), np.asarray(target)
    assume(np.linalg.norm(t - e) > 1e-3)
    T = look_at(e, t)
    check_rigid(T)
    z = T[:3, 2]
    np.testing.assert_allclose(z, (t - e) / np.linalg.norm(t - e), atol=1e-9)
    cam_target = transform_points(invert(T), t[None])[0]
    np.testing.assert_allclose(cam_target[:2], 0.0, atol=1e-9 * max(1.0, np.abs(t - e).max()))
    assert cam_target[2] > 0


def test_look_at_roll_convention_image_up_is_world_up() -> None:
    T = look_at([0.0, -1.0, 0.5], [0.0, 0.0, 0.0])
    # camera -y (image up) must have a positive world z component
    assert (-T[:3, 1])[2] > 0.0
    assert abs(T[:3, 0][2]) < 1e-12  # x axis horizontal: no roll


@pytest.mark.parametrize("direction", [(0, 0, -1), (0, 0, 1), (1e-9, 0, -1), (0, 1e-8, 1)])
def test_look_at_parallel_to_up_is_finite_and_deterministic(direction: tuple) -> None:
    eye = np.array([0.4, 0.1, 0.5])
    target = eye + np.asarray(direction, float)
    T1 = look_at(eye, target)
    T2 = look_at(eye, target)
    assert np.all(np.isfinite(T1))
    check_rigid(T1)
    np.testing.assert_array_equal(T1, T2)
    np.testing.assert_allclose(T1[:3, 2], np.asarray(direction) / np.linalg.norm(direction), atol=1e-9)


@given(vec3, st.lists(st.floats(1e-3, 10.0), min_size=1, max_size=3), st.integers(1, 12), st.floats(-90.0, 90.0))
def test_ring_orbit_cameras_sit_on_their_rings_looking_at_the_target(target: tuple, distances: list, per_ring: int,
                                                                     elevation: float) -> None:
    poses = ring_orbit(target, distances, per_ring, elevation)
    assert [(ring, d) for ring, d, _ in poses] == [(r, d) for r, d in enumerate(distances) for _ in range(per_ring)]
    t = np.asarray(target, float)
    for _, d, T in poses:
        check_rigid(T)
        eye = T[:3, 3]
        np.testing.assert_allclose(np.linalg.norm(eye - t), d, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(t).max()))
        np.testing.assert_allclose(eye[2] - t[2], d * math.sin(math.radians(elevation)), atol=1e-9 * max(1.0, np.abs(t).max()))
        cam_target = transform_points(invert(T), t[None])[0]
        assert cam_target[2] > 0 and np.abs(cam_target[:2]).max() <= 1e-7 * max(1.0, np.abs(t).max())
    # one ring's cameras spread evenly: neighbours a full turn / per_ring apart in azimuth
    if per_ring >= 2 and abs(elevation) < 89.0:
        eyes = np.array([T[:3, 3] - t for ring, _, T in poses if ring == 0])
        az = np.arctan2(eyes[:, 1], eyes[:, 0])
        step_error = np.angle(np.exp(1j * (np.diff(az) - 2 * math.pi / per_ring)))  # wrapped to (-pi, pi]
        np.testing.assert_allclose(step_error, 0.0, atol=1e-6)


def test_look_at_rejects_coincident_eye_and_target() -> None:
    with pytest.raises(NonRigidTransformError, match="coincide"):
        look_at([1, 2, 3], [1, 2, 3])


# ----------------------------------------------------------------------------- rejection
@pytest.mark.parametrize(
    ("matrix", "message"),
    [
        (np.diag([2.0, 1.0, 1.0, 1.0]), "not orthonormal"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
        (np.eye(3), "expected a 4x4"),
        (np.r_[np.eye(4)[:3], [[0.0, 0.0, 0.1, 1.0]]], "bottom row"),
        (np.full((4, 4), np.nan), "NaN"),
        (make_transform(np.eye(3) + np.array([[0, 1e-3, 0], [0, 0, 0], [0, 0, 0]]), [0, 0, 0]), "sheared"),
    ],
)
def test_check_rigid_rejects_non_rigid(matrix: np.ndarray, message: str) -> None:
    with pytest.raises(NonRigidTransformError, match=message):
        check_rigid(matrix, "cam_T_x")


def test_error_names_the_transform() -> None:
    with pytest.raises(NonRigidTransformError, match="^frame 12 base_T_tcp"):
        check_rigid(np.diag([1.0, 1.0, 1.0, 2.0]), "frame 12 base_T_tcp")


@given(poses, st.floats(1e-4, 0.5))
def test_orthonormalize_projects_perturbed_rotation_back(T: np.ndarray, eps: float) -> None:
    noisy = T[:3, :3] + eps * np.array([[0.3, -0.1, 0.2], [0.05, 0.1, -0.2], [0.1, 0.2, 0.0]])
    R = orthonormalize(noisy)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0


# ----------------------------------------------------------------------------- the one rule for poses made elsewhere
noise = st.lists(st.floats(-1.0, 1.0), min_size=9, max_size=9).map(lambda v: np.reshape(v, (3, 3)))


@given(poses, noise, st.floats(1e-9, 1e-4))
def test_rotations_off_by_rounding_are_projected_and_the_correction_reported(T: np.ndarray, E: np.ndarray,
                                                                             eps: float) -> None:
    noisy = T[:3, :3] + eps * E  # |R^T R - I| <= 6 eps + 9 eps^2 < ROTATION_TOLERANCE
    R, correction = nearest_rotation(noisy, "frame 3")
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    assert math.isfinite(correction) and correction == np.abs(R - noisy).max()
    assert correction <= 3 * eps + 1e-15  # no farther than the rotation it was rounded from
    np.testing.assert_allclose(R, T[:3, :3], atol=6 * eps + 1e-12)
    rigid, same = nearest_rigid(np.c_[noisy, T[:3, 3]], "frame 3")  # 3x4 as transforms.json may hold
    assert same == correction and rigid[3].tolist() == [0.0, 0.0, 0.0, 1.0]
    np.testing.assert_array_equal(rigid[:3, :3], R)


@given(poses, st.sampled_from(["scaled", "sheared", "reflected", "nan"]), st.floats(2e-3, 1.0))
def test_sheared_scaled_reflected_or_nan_matrices_are_refused_naming_the_frame(T: np.ndarray, kind: str,
                                                                               size: float) -> None:
    R = T[:3, :3].copy()
    if kind == "scaled":
        R[:, 1] *= 1.0 + size
    elif kind == "sheared":
        R[:, 2] += size * R[:, 0]
    elif kind == "reflected":
        R = -R
    else:
        R[1, 1] = np.nan
    with pytest.raises(NonRigidTransformError) as info:
        nearest_rotation(R, "frames[7] (f007.png)")
    message = str(info.value)
    assert message.startswith("frames[7] (f007.png): ") and "\n" not in message
    expected = {"scaled": "not orthonormal", "sheared": "not orthonormal", "reflected": "reflection",
                "nan": "NaN"}[kind]
    assert expected in message
    if kind in ("scaled", "sheared"):
        measured = float(message.split("max |R^T R - I| = ")[1].split(",")[0])
        assert measured > ROTATION_TOLERANCE


@pytest.mark.parametrize("bad", [[0, 0, 0, 0, 0], [0, 0, 0, np.nan, 0, 0], [0, 0, 0, 0, 0, np.inf]])
def test_ur_pose_rejects_malformed(bad: list) -> None:
    with pytest.raises(NonRigidTransformError):
        ur_pose_to_matrix(bad)


@pytest.mark.parametrize("line", ["1 0 0 0 0 0 0", "1 a 0 0 0 0 0 1", "1 0 0 0 0 0 0 0"])
def test_tum_line_rejects_malformed(line: str) -> None:
    with pytest.raises(NonRigidTransformError):
        parse_tum_line(line)


def test_tum_line_accepts_commas() -> None:
    frame, T = parse_tum_line("3, 0.1, 0.2, 0.3, 0, 0, 0, 1")
    assert frame == "3"
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, 0.3])


@given(q=st.tuples(*[st.floats(allow_nan=True, allow_infinity=True, width=64)] * 4))
def test_unit_quaternion_normalises_near_unit_and_names_the_rest(q: tuple) -> None:
    """The one quaternion rule: within QUATERNION_TOLERANCE of norm 1 -> exactly unit, finite; any
    other four numbers (zero, NaN, inf, far off) -> one line naming where, the order and the norm."""
    arr = np.asarray(q)
    with np.errstate(over="ignore", invalid="ignore"):
        norm = float(np.linalg.norm(arr))
    if np.all(np.isfinite(arr)) and abs(norm - 1.0) <= QUATERNION_TOLERANCE:
        unit = unit_quaternion(arr, "pose.orientation")
        assert np.all(np.isfinite(unit)) and np.linalg.norm(unit) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(unit, arr / norm)
    else:
        with pytest.raises(NonRigidTransformError) as info:
            unit_quaternion(arr, "pose.orientation", "w, x, y, z")
        message = str(info.value)
        assert message.startswith("pose.orientation: ") and "(w, x, y, z)" in message and "\n" not in message


@pytest.mark.parametrize("scale, accepted", [(1.0 + 0.9e-3, True), (1.0 - 0.9e-3, True), (1.0011, False), (0.0, False)])
def test_unit_quaternion_tolerance_edges(scale: float, accepted: bool) -> None:
    q = scale * np.array([0.5, 0.5, 0.5, 0.5])
    if accepted:
        np.testing.assert_allclose(unit_quaternion(q, "q"), [0.5] * 4, atol=1e-15)
    else:
        with pytest.raises(NonRigidTransformError, match="not a unit quaternion"):
            unit_quaternion(q, "q")

"""Rigid transforms as 4x4 float64 matrices named ``a_T_b`` (maps points from frame b to a).

All rotation conversions go through :class:`scipy.spatial.transform.Rotation`; this module
adds the project's conventions on top (UR rotation-vector poses, TUM lines with scalar-last
quaternions, OpenCV look-at) and a strict rigidity check, because scipy silently
orthonormalises whatever matrix it is given.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from brave6d.core.errors import NonRigidTransformError

Matrix4 = NDArray[np.float64]
Matrix3 = NDArray[np.float64]

#: Default tolerance of :func:`check_rigid` on ``R^T R - I`` and ``det(R) - 1``.
RIGID_ATOL = 1e-6


def check_rigid(T: ArrayLike, name: str = "transform", atol: float = RIGID_ATOL) -> Matrix4:
    """Return ``T`` as a float64 4x4 array, or raise naming ``name`` and what is wrong.

    Rejects wrong shapes, NaN/inf, a bottom row other than ``0 0 0 1``, reflections and
    rotation blocks that are scaled or sheared (``|R^T R - I| > atol``).
    """
    arr = np.asarray(T, dtype=np.float64)
    problem = _frame_problem(arr, atol)
    if problem:
        raise NonRigidTransformError(f"{name}: {problem}")
    check_rotation(arr[:3, :3], name=name, atol=atol)
    return arr


def _frame_problem(arr: NDArray[np.float64], atol: float) -> str | None:
    """What keeps ``arr`` from being a finite 4x4 with bottom row ``0 0 0 1`` (one line), or None."""
    if arr.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {arr.shape}"
    if not np.all(np.isfinite(arr)):
        return "contains NaN or inf"
    if not np.allclose(arr[3], (0.0, 0.0, 0.0, 1.0), atol=atol, rtol=0.0):
        return f"bottom row is {arr[3].tolist()}, expected [0, 0, 0, 1]"
    return None


def check_rotation(R: ArrayLike, name: str = "rotation", atol: float = RIGID_ATOL) -> Matrix3:
    """Return ``R`` as a float64 3x3 rotation matrix, or raise naming ``name`` and the defect."""
    rot = np.asarray(R, dtype=np.float64)
    problem = _rotation_problem(rot, atol)
    if problem:
        raise NonRigidTransformError(f"{name}: {problem}")
    return rot


def _rotation_problem(rot: NDArray[np.float64], atol: float) -> str | None:
    """What keeps ``rot`` from being a rotation within ``atol`` on ``max |R^T R - I|`` (one line), or None."""
    if rot.shape != (3, 3):
        return f"expected a 3x3 rotation, got shape {rot.shape}"
    if not np.all(np.isfinite(rot)):
        return "rotation contains NaN or inf"
    orth_err = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
    if orth_err > atol:
        scales = np.linalg.norm(rot, axis=0)
        return (f"rotation block is not orthonormal (max |R^T R - I| = {orth_err:.3g}, more than the {atol:g} "
                f"accepted; column norms {np.round(scales, 6).tolist()}): scaled or sheared matrix, not a rotation")
    det = float(np.linalg.det(rot))
    if det <= 0:
        return f"rotation block is a reflection (det = {det:.6f}), not a rotation"
    return None


#: Largest ``max |R^T R - I|`` of a rotation that enters from outside (an imported capture, a pose
#: file, a 3D-DAT pose, a server request) accepted as rounding and projected onto the nearest
#: rotation (:func:`nearest_rotation`). Real files need about 1e-6 (instant-ngp's transforms.json
#: prints six digits: 1.09e-6 on its fox), float32 files about 1e-7, and a matrix printed with four
#: decimals up to about 2e-4; nerfstudio's and COLMAP's quaternions normalise to exact rotations.
#: 1e-3 takes all of these, and moves a rotation by at most about 0.03 degrees, while a scale
#: of 0.1 % or a shear of 0.1 (what a wrong matrix looks like) is well above it and refused.
ROTATION_TOLERANCE = 1e-3


def nearest_rotation(R: ArrayLike, where: str, atol: float = ROTATION_TOLERANCE) -> tuple[Matrix3, float]:
    """The rotation nearest to ``R`` (SVD projection onto SO(3), det +1) and the correction made
    (``max |R_projected - R|`` over the entries), when ``R`` is a rotation up to rounding
    (``max |R^T R - I| <= atol``, det > 0, finite; see :data:`ROTATION_TOLERANCE`); else
    :class:`NonRigidTransformError` in one line naming ``where`` and the measured deviation.

    The one rule for rotations that come from outside: every reader of poses made elsewhere uses it.
    """
    rot = np.asarray(R, dtype=np.float64)
    problem = _rotation_problem(rot, atol)
    if problem:
        raise NonRigidTransformError(f"{where}: {problem}")
    projected = orthonormalize(rot)
    return projected, float(np.max(np.abs(projected - rot)))


def nearest_rigid(T: ArrayLike, where: str, atol: float = ROTATION_TOLERANCE) -> tuple[Matrix4, float]:
    """A 4x4 (or 3x4) pose made elsewhere -> the rigid 4x4 with its rotation projected by
    :func:`nearest_rotation` and the bottom row set to ``0 0 0 1``, and the rotation's correction;
    else :class:`NonRigidTransformError` naming ``where``."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape == (3, 4):
        arr = np.vstack([arr, [0.0, 0.0, 0.0, 1.0]])
    problem = _frame_problem(arr, atol)
    if problem:
        raise NonRigidTransformError(f"{where}: {problem}")
    R, correction = nearest_rotation(arr[:3, :3], where, atol)
    return make_transform(R, arr[:3, 3]), correction


#: A quaternion made elsewhere whose norm is off 1 by at most this is normalised; further off, it is
#: refused: printed quaternions carry rounding far below it, while a zero quaternion (ROS's
#: uninitialised default) or a vector that is not a rotation is far above it.
QUATERNION_TOLERANCE = 1e-3


def unit_quaternion(q: ArrayLike, where: str, order: str = "x, y, z, w",
                    atol: float = QUATERNION_TOLERANCE) -> NDArray[np.float64]:
    """``q`` normalised, when it is four finite numbers of norm 1 within ``atol``
    (:data:`QUATERNION_TOLERANCE`); else :class:`NonRigidTransformError` in one line naming ``where``,
    the order the numbers were read in, and the norm. The one rule for quaternions from outside."""
    arr = np.asarray(q, dtype=np.float64).reshape(-1)
    if arr.size != 4 or not np.all(np.isfinite(arr)):
        raise NonRigidTransformError(f"{where}: a quaternion ({order}) must be 4 finite numbers, got {arr.tolist()}")
    norm = float(np.linalg.norm(arr))
    if not abs(norm - 1.0) <= atol:
        raise NonRigidTransformError(f"{where}: quaternion {np.round(arr, 6).tolist()} ({order}) has norm {norm:.6g}: "
                                     f"not a unit quaternion (within {atol:g})")
    return arr / norm


def make_transform(R: ArrayLike, t: ArrayLike) -> Matrix4:
    """Assemble ``[[R, t], [0, 1]]`` as float64 (no rigidity check; see :func:`check_rigid`)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: ArrayLike) -> Matrix4:
    """Inverse of a rigid transform, computed as ``[R^T, -R^T t]`` (exact, no matrix inverse)."""
    arr = np.asarray(T, dtype=np.float64)
    R = arr[:3, :3]
    return make_transform(R.T, -R.T @ arr[:3, 3])


def transform_points(a_T_b: ArrayLike, points_b: ArrayLike) -> NDArray[np.float64]:
    """Map ``(N, 3)`` points from frame b to frame a."""
    T = np.asarray(a_T_b, dtype=np.float64)
    pts = np.asarray(points_b, dtype=np.float64).reshape(-1, 3)
    return pts @ T[:3, :3].T + T[:3, 3]


def orthonormalize(R: ArrayLike) -> Matrix3:
    """Closest rotation matrix to ``R`` in the Frobenius norm (SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


# ----------------------------------------------------------------------------- UR poses
def ur_pose_to_matrix(pose: Sequence[float] | ArrayLike) -> Matrix4:
    """UR pose ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in radians) -> 4x4."""
    p = np.asarray(pose, dtype=np.float64).reshape(-1)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise NonRigidTransformError(f"UR pose must be 6 finite numbers [x,y,z,rx,ry,rz], got {p.tolist()}")
    return make_transform(Rotation.from_rotvec(p[3:]).as_matrix(), p[:3])


def matrix_to_ur_pose(T: ArrayLike) -> list[float]:
    """4x4 -> UR pose ``[x, y, z, rx, ry, rz]``; the rotation-vector angle lies in [0, pi]."""
    arr = check_rigid(T, "UR target pose")
    rotvec = Rotation.from_matrix(arr[:3, :3]).as_rotvec()
    return [*arr[:3, 3].tolist(), *rotvec.tolist()]


# ----------------------------------------------------------------------------- quaternions
def quat_wxyz_to_matrix(q_wxyz: ArrayLike) -> Matrix3:
    """Unit quaternion (w, x, y, z) -> 3x3 rotation. A zero quaternion is an error."""
    q = np.asarray(q_wxyz, dtype=np.float64).reshape(4)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-12:
        raise NonRigidTransformError(f"quaternion {q.tolist()} has zero or non-finite norm")
    return Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()


def matrix_to_quat_wxyz(R: ArrayLike) -> NDArray[np.float64]:
    """3x3 rotation -> unit quaternion (w, x, y, z) with ``w >= 0`` (canonical sign)."""
    xyzw = Rotation.from_matrix(check_rotation(R)).as_quat(canonical=True)
    return xyzw[[3, 0, 1, 2]]


# ----------------------------------------------------------------------------- TUM lines
def tum_to_matrix(values: Sequence[float] | ArrayLike) -> Matrix4:
    """TUM pose ``tx ty tz qx qy qz qw`` (scalar-last quaternion) -> 4x4."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.shape != (7,) or not np.all(np.isfinite(v)):
        raise NonRigidTransformError(f"TUM pose must be 7 finite numbers tx ty tz qx qy qz qw, got {v.tolist()}")
    q = v[3:]
    if np.linalg.norm(q) < 1e-12:
        raise NonRigidTransformError(f"TUM pose has a zero quaternion: {v.tolist()}")
    return make_transform(Rotation.from_quat(q).as_matrix(), v[:3])


def matrix_to_tum(T: ArrayLike) -> list[float]:
    """4x4 -> TUM ``[tx, ty, tz, qx, qy, qz, qw]`` with ``qw >= 0``."""
    arr = check_rigid(T)
    q = Rotation.from_matrix(arr[:3, :3]).as_quat(canonical=True)
    return [*arr[:3, 3].tolist(), *q.tolist()]


def parse_tum_line(line: str) -> tuple[str, Matrix4]:
    """Parse ``id tx ty tz qx qy qz qw`` (whitespace or comma separated) into (id, 4x4)."""
    parts = line.replace(",", " ").split()
    if len(parts) != 8:
        raise NonRigidTransformError(f"expected 'id tx ty tz qx qy qz qw' (8 fields), got {len(parts)}: {line!r}")
    try:
        values = [float(p) for p in parts[1:]]
    except ValueError as exc:
        raise NonRigidTransformError(f"non-numeric field in {line!r}: {exc}") from None
    return parts[0], tum_to_matrix(values)


def format_tum_line(frame_id: str | int, T: ArrayLike) -> str:
    """Format ``id tx ty tz qx qy qz qw`` with enough digits to round-trip float64."""
    return " ".join([str(frame_id), *(repr(float(x)) for x in matrix_to_tum(T))])


# ----------------------------------------------------------------------------- Euler / rotvec helpers
def rpy_deg_to_matrix(rpy_deg: Sequence[float] | ArrayLike) -> Matrix3:
    """Extrinsic roll-pitch-yaw about x, y, z (degrees) -> 3x3, as scipy's ``'xyz'`` sequence."""
    return Rotation.from_euler("xyz", np.asarray(rpy_deg, dtype=np.float64), degrees=True).as_matrix()


def matrix_to_rpy_deg(R: ArrayLike) -> NDArray[np.float64]:
    """3x3 -> extrinsic roll-pitch-yaw (degrees), inverse of :func:`rpy_deg_to_matrix`."""
    return Rotation.from_matrix(check_rotation(R)).as_euler("xyz", degrees=True)


# ----------------------------------------------------------------------------- look-at
def look_at(
    eye: ArrayLike,
    target: ArrayLike,
    up: ArrayLike = (0.0, 0.0, 1.0),
    min_sine: float = 1e-6,
) -> Matrix4:
    """``world_T_cam`` of an OpenCV camera at ``eye`` whose optical axis (+z) points at ``target``.

    The image "up" (-y of the camera) is the projection of ``up`` onto the image plane, so the
    camera's x axis is ``forward x up`` normalised. When the view direction is parallel to ``up``
    (sine of the angle below ``min_sine``) that axis is undefined; the rule then is to use the
    world axis least aligned with the view direction (preferring -x, then y, then z of the world
    frame in that order of ties) as ``up``. This keeps the result finite, rigid and deterministic.
    Raises when ``eye`` equals ``target`` or any input is not finite.
    """
    e = np.asarray(eye, dtype=np.float64).reshape(3)
    t = np.asarray(target, dtype=np.float64).reshape(3)
    u = np.asarray(up, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(t)) and np.all(np.isfinite(u))):
        raise NonRigidTransformError("look_at: eye, target and up must be finite")
    forward = t - e
    dist = float(np.linalg.norm(forward))
    if dist < 1e-12:
        raise NonRigidTransformError(f"look_at: eye and target coincide at {e.tolist()}")
    z = forward / dist
    u_norm = float(np.linalg.norm(u))
    if u_norm < 1e-12:
        raise NonRigidTransformError("look_at: 'up' vector has zero length")
    u = u / u_norm
    x = np.cross(z, u)
    if np.linalg.norm(x) < min_sine:
        candidates = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        u = candidates[int(np.argmin(np.abs(candidates @ z)))]
        x = np.cross(z, u)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.stack([x, y, z], axis=1), e)


def ring_orbit(target: ArrayLike, distances: Sequence[float], per_ring: int, elevation_deg: float
               ) -> list[tuple[int, float, Matrix4]]:
    """``(ring, distance, world_T_cam)`` of ``per_ring`` cameras on a ring per distance around ``target``,
    all at ``elevation_deg`` above its horizontal plane and looking at it, spread evenly in azimuth
    (each ring turned by half a step against the previous one, so rings do not line up)."""
    centre = np.asarray(target, dtype=np.float64).reshape(3)
    el = math.radians(elevation_deg)
    poses = []
    for ring, distance in enumerate(distances):
        for i in range(per_ring):
            az = 2.0 * math.pi * (i + 0.5 * ring) / per_ring
            direction = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
            poses.append((ring, float(distance), look_at(centre + distance * direction, centre)))
    return poses


# ----------------------------------------------------------------------------- distances
def rotation_angle(R: ArrayLike) -> float:
    """Rotation angle of ``R`` in radians, in [0, pi] (accurate near 0 and near pi)."""
    return float(Rotation.from_matrix(check_rotation(R)).magnitude())


def rotation_distance(Ra: ArrayLike, Rb: ArrayLike) -> float:
    """Geodesic angle between two rotations (radians, [0, pi])."""
    A = np.asarray(Ra, dtype=np.float64)
    B = np.asarray(Rb, dtype=np.float64)
    if A.shape == (4, 4):
        A = A[:3, :3]
    if B.shape == (4, 4):
        B = B[:3, :3]
    return rotation_angle(check_rotation(A).T @ check_rotation(B))


def translation_distance(Ta: ArrayLike, Tb: ArrayLike) -> float:
    """Euclidean distance between the translations of two transforms (metres)."""
    return float(np.linalg.norm(np.asarray(Ta, dtype=np.float64)[:3, 3] - np.asarray(Tb, dtype=np.float64)[:3, 3]))


def pose_distance(Ta: ArrayLike, Tb: ArrayLike) -> tuple[float, float]:
    """``(rotation angle in radians, translation distance in metres)`` between two poses."""
    return rotation_distance(Ta, Tb), translation_distance(Ta, Tb)

"""Do the cameras see the scene? The pose sanity check run at import and at the start of training.

Every camera of a capture must look at the scene: the scene's reference points (an imported
capture's sparse points, else the spec's capture target, else the point nearest to every optical
axis) must lie in front of it and inside its image. A camera that sees less than ``min_share`` of
them fails, and the check names each failing frame. The classic cause is a pose written with
OpenGL's camera axes (x right, y up, z backwards: nerfstudio, instant-ngp, Blender) and read as
OpenCV's (x right, y down, z forward): every camera then faces away from the scene, and training
runs to a blur without a word. The check also tries each failing pose with its y and z axes
flipped and says so when that makes it see the scene.

Pure NumPy (no torch): the importer and the trainer call it before anything heavy starts.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError

#: Default least share of the reference points a camera must see (in front, inside the image).
MIN_VISIBLE_SHARE = 0.02
#: OpenGL camera axes -> OpenCV camera axes (and back): y and z flipped.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
#: How many failing frames a message names before "and N more".
_NAMED = 8


class PoseCheckError(DataError):
    """Cameras that do not see the scene; ``failing`` lists their names."""

    def __init__(self, message: str, failing: list[str]) -> None:
        super().__init__(message)
        self.failing = failing


@dataclass(frozen=True)
class FrameVisibility:
    """What one camera sees of the reference points: shares in [0, 1]."""

    name: str
    visible: float  # in front and inside the image (with the margin)
    in_front: float  # in front of the camera, anywhere
    visible_flipped: float  # ``visible`` with the pose's y and z axes flipped (OpenGL read as OpenCV)


@dataclass(frozen=True)
class PoseCheck:
    """The check's result: one :class:`FrameVisibility` per frame and what it was measured against."""

    frames: tuple[FrameVisibility, ...]
    reference: str  # e.g. "5123 sparse points" or "the capture target (0, 0, 0.05)"
    min_share: float

    @property
    def failing(self) -> list[FrameVisibility]:
        return [f for f in self.frames if f.visible < self.min_share]

    def summary(self) -> str:
        """One line: how many frames passed, the least share seen and the reference."""
        shares = [f.visible for f in self.frames]
        least = min(shares) if shares else float("nan")
        return (f"pose check: {len(self.frames) - len(self.failing)} of {len(self.frames)} cameras see at least "
                f"{self.min_share:.0%} of {self.reference} (least {least:.0%})")


def visible_shares(camera: PinholeCamera, world_T_cam: ArrayLike, points: ArrayLike,
                   margin: float = 0.1) -> tuple[float, float]:
    """``(visible, in_front)`` shares of ``points`` (N, 3, world) for one OpenCV camera pose.

    Visible: in front (z > 0) and projecting inside the image grown by ``margin`` of its size on
    each side (pinhole projection without distortion, so a wild distortion polynomial never sends
    a far point into the image). Non-finite points count as not seen.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return 0.0, 0.0
    inside, front = _visibility(camera, world_T_cam, pts, margin)
    n = float(len(pts))
    return float(inside.sum()) / n, float(front.sum()) / n


def visible_mask(camera: PinholeCamera, world_T_cam: ArrayLike, points: ArrayLike,
                 margin: float = 0.0) -> NDArray[np.bool_]:
    """Which of ``points`` (N, 3, world) are in front of the camera and inside its image (+ ``margin``)."""
    return _visibility(camera, world_T_cam, np.asarray(points, dtype=np.float64).reshape(-1, 3), margin)[0]


def _visibility(camera: PinholeCamera, world_T_cam: ArrayLike, pts: NDArray[np.float64],
                margin: float) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    T = np.asarray(world_T_cam, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    with np.errstate(invalid="ignore", over="ignore"):
        cam = (pts - t) @ R  # R^T (p - t), row-wise
        finite = np.isfinite(cam).all(axis=1)
        z = np.where(finite, cam[:, 2], -1.0)
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        u = camera.fx * cam[:, 0] / zs + camera.cx
        v = camera.fy * cam[:, 1] / zs + camera.cy
    mu, mv = margin * camera.width, margin * camera.height
    inside = front & (u >= -0.5 - mu) & (u <= camera.width - 0.5 + mu) & (v >= -0.5 - mv) & (v <= camera.height - 0.5 + mv)
    return inside, front


def check_camera_poses(camera: PinholeCamera, poses: Sequence[tuple[str, ArrayLike]], points: ArrayLike,
                       reference: str, min_share: float = MIN_VISIBLE_SHARE, *, raise_on_failure: bool = True,
                       how_to_skip: str = "") -> PoseCheck:
    """Check that every camera in ``poses`` (``(name, world_T_cam)``, OpenCV axes) sees at least
    ``min_share`` of ``points``; raises :class:`PoseCheckError` naming the frames that do not.

    ``reference`` says what the points are (for messages); ``how_to_skip`` is appended to the
    error (e.g. "pass --skip-pose-check to train anyway").
    """
    if not 0.0 <= min_share <= 1.0 or not np.isfinite(min_share):
        raise ValueError(f"min_share must be in [0, 1], got {min_share}")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    frames = []
    for name, pose in poses:
        T = np.asarray(pose, dtype=np.float64)
        visible, front = visible_shares(camera, T, pts)
        flipped = visible_shares(camera, T @ GL_TO_CV, pts)[0] if visible < min_share else visible
        frames.append(FrameVisibility(str(name), visible, front, flipped))
    result = PoseCheck(tuple(frames), reference, float(min_share))
    if raise_on_failure and result.failing:
        raise PoseCheckError(failure_message(result, how_to_skip), [f.name for f in result.failing])
    return result


def failure_message(result: PoseCheck, how_to_skip: str = "") -> str:
    """The one-line error of a failed check: the frames, what they see, and the likely cause."""
    failing = result.failing
    named = ", ".join(f"{f.name} ({f.visible:.0%})" for f in failing[:_NAMED])
    more = f" and {len(failing) - _NAMED} more" if len(failing) > _NAMED else ""
    message = (f"pose check failed: {len(failing)} of {len(result.frames)} cameras see less than "
               f"{result.min_share:.0%} of {result.reference} in front of them and inside their image: {named}{more}")
    behind = sum(1 for f in failing if f.in_front < 0.5)
    fixed_by_flip = sum(1 for f in failing if f.visible_flipped >= result.min_share)
    if failing and fixed_by_flip >= max(1, len(failing) // 2):
        message += (f"; with y and z flipped, {fixed_by_flip} of them would see it: the poses look like OpenGL camera "
                    "axes (x right, y up, z backwards, as nerfstudio / instant-ngp / Blender write them) read as "
                    "OpenCV's (x right, y down, z forward)")
    elif behind:
        message += f"; the reference lies behind {behind} of them: check the pose convention (camera-to-world, axes)"
    else:
        message += "; the scene is outside their view: check the poses, the intrinsics and the scale"
    return message + (f" ({how_to_skip})" if how_to_skip else "")


def axes_meeting_point(poses: Sequence[ArrayLike], min_condition: float = 1e-3) -> NDArray[np.float64] | None:
    """The point nearest (least squares) to every camera's optical axis, or None when the axes are
    too close to parallel (the smallest eigenvalue of the normal matrix, per camera, below
    ``min_condition``) or not finite.

    For a capture around an object this is the object; the axes are lines, so the point is the same
    whichever way the cameras face, and a flipped camera finds it behind itself.
    """
    A = np.zeros((3, 3))
    b = np.zeros(3)
    n = 0
    for pose in poses:
        T = np.asarray(pose, dtype=np.float64)
        c, d = T[:3, 3], T[:3, 2]
        norm = np.linalg.norm(d)
        if not (np.isfinite(c).all() and np.isfinite(d).all()) or norm < 1e-12:
            return None
        d = d / norm
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
        n += 1
    if n < 2:
        return None
    eig = np.linalg.eigvalsh(A / n)
    if eig[0] < min_condition:
        return None
    point = np.linalg.solve(A, b)
    return point if np.isfinite(point).all() else None

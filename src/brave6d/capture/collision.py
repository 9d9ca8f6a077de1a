"""Collision checks of the camera, the flange and the arm's links against the scene's boxes.

Pure NumPy, vectorised over the scene's boxes. Shapes:

- oriented boxes (the spec's collision boxes, the camera body, the flange): exact
  separating-axis test (15 axes). With a ``margin`` a pair counts as colliding unless some axis
  separates it by more than ``margin``: never misses a pair closer than ``margin``; it may flag a
  pair whose closest features are corner-to-corner slightly farther than ``margin`` (conservative).
- link capsules (a segment with a radius): the segment is clipped against the box inflated by
  ``radius + margin`` (slab test). Exact for the segment, conservative near box edges and corners.

The arm's links are approximated by the DH skeleton (segments between consecutive frame origins),
which ignores the lateral shoulder/elbow offsets of the real link housings: the radii should cover
them (see :class:`ToolModel`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.spec import BoxSpec


@dataclass(frozen=True)
class BoxSet:
    """M oriented boxes: centres (M, 3), rotations (M, 3, 3) (columns = box axes in the world),
    half edge lengths (M, 3), names."""

    centers: NDArray[np.float64]
    rotations: NDArray[np.float64]
    half_sizes: NDArray[np.float64]
    names: tuple[str, ...]

    @classmethod
    def from_specs(cls, boxes: Sequence[BoxSpec]) -> BoxSet:
        """The spec's collision boxes."""
        if not boxes:
            return cls.empty()
        mats = np.stack([b.matrix() for b in boxes])
        return cls(mats[:, :3, 3].copy(), mats[:, :3, :3].copy(),
                   0.5 * np.array([b.size for b in boxes], dtype=np.float64), tuple(b.name for b in boxes))

    @classmethod
    def from_arrays(
        cls, world_T_box: ArrayLike, size: ArrayLike, names: Sequence[str] | None = None
    ) -> BoxSet:
        """Boxes from (M, 4, 4) poses and (M, 3) full edge lengths."""
        mats = np.asarray(world_T_box, dtype=np.float64).reshape(-1, 4, 4)
        sz = np.asarray(size, dtype=np.float64).reshape(-1, 3)
        if len(sz) != len(mats) or np.any(sz <= 0):
            raise ValueError("need one positive size triple per box pose")
        nm = tuple(names) if names is not None else tuple(f"box{i}" for i in range(len(mats)))
        return cls(mats[:, :3, 3].copy(), mats[:, :3, :3].copy(), 0.5 * sz, nm)

    @classmethod
    def empty(cls) -> BoxSet:
        return cls(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), ())

    def __len__(self) -> int:
        return len(self.names)

    def concat(self, other: BoxSet) -> BoxSet:
        """Both sets of boxes in one."""
        if len(other) == 0:
            return self
        if len(self) == 0:
            return other
        return BoxSet(np.concatenate([self.centers, other.centers]), np.concatenate([self.rotations, other.rotations]),
                      np.concatenate([self.half_sizes, other.half_sizes]), self.names + other.names)

    def corners(self) -> NDArray[np.float64]:
        """(M, 8, 3) corner points in the world frame."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        local = signs[None, :, :] * self.half_sizes[:, None, :]
        return np.einsum("mij,mkj->mki", self.rotations, local) + self.centers[:, None, :]


# ----------------------------------------------------------------------------- primitive tests
def obb_overlaps(
    world_T_box: ArrayLike, half_size: ArrayLike, boxes: BoxSet, margin: float = 0.0
) -> NDArray[np.bool_]:
    """For one oriented box (pose, half edge lengths), which of ``boxes`` it overlaps (or comes
    within ``margin`` of, see the module docstring). Boolean array of length M."""
    if len(boxes) == 0:
        return np.zeros(0, dtype=bool)
    T = np.asarray(world_T_box, dtype=np.float64)
    A = T[:3, :3]
    ha = np.asarray(half_size, dtype=np.float64).reshape(3)
    B = boxes.rotations  # (M, 3, 3)
    hb = boxes.half_sizes  # (M, 3)
    d = boxes.centers - T[:3, 3]  # (M, 3)
    M = len(boxes)
    axes_a = np.broadcast_to(A.T, (M, 3, 3))  # rows = A's axes
    axes_b = np.transpose(B, (0, 2, 1))  # rows = B's axes
    cross = np.cross(axes_a[:, :, None, :], axes_b[:, None, :, :]).reshape(M, 9, 3)
    axes = np.concatenate([axes_a, axes_b, cross], axis=1)  # (M, 15, 3)
    norms = np.linalg.norm(axes, axis=2)
    valid = norms > 1e-9  # parallel edges give no new axis (face axes cover them)
    L = axes / np.where(valid, norms, 1.0)[..., None]
    dist = np.abs(np.einsum("mkj,mj->mk", L, d))
    ra = np.abs(L @ A) @ ha  # projection radius of the query box: sum_i ha_i |L . a_i|
    rb = np.einsum("mki,mi->mk", np.abs(np.einsum("mkj,mji->mki", L, B)), hb)
    separated = valid & (dist - ra - rb > margin)
    return ~np.any(separated, axis=1)


def segment_hits(
    p0: ArrayLike, p1: ArrayLike, boxes: BoxSet, radius: float = 0.0, margin: float = 0.0
) -> NDArray[np.bool_]:
    """Which boxes the segment p0-p1 (a capsule of ``radius``) hits, within ``margin``.

    Slab clipping of the segment against each box inflated by ``radius + margin``.
    """
    if len(boxes) == 0:
        return np.zeros(0, dtype=bool)
    a = np.asarray(p0, dtype=np.float64).reshape(3)
    b = np.asarray(p1, dtype=np.float64).reshape(3)
    R = boxes.rotations
    la = np.einsum("mji,mj->mi", R, a - boxes.centers)  # endpoints in box frames
    lb = np.einsum("mji,mj->mi", R, b - boxes.centers)
    h = boxes.half_sizes + (radius + margin)
    dvec = lb - la
    t_lo = np.zeros(len(boxes))
    t_hi = np.ones(len(boxes))
    hit = np.ones(len(boxes), dtype=bool)
    for k in range(3):
        dk = dvec[:, k]
        pk = la[:, k]
        still = np.abs(dk) < 1e-15
        hit &= ~(still & (np.abs(pk) > h[:, k]))
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h[:, k] - pk) / dk
            t2 = (h[:, k] - pk) / dk
        tmin = np.where(still, -np.inf, np.minimum(t1, t2))
        tmax = np.where(still, np.inf, np.maximum(t1, t2))
        t_lo = np.maximum(t_lo, tmin)
        t_hi = np.minimum(t_hi, tmax)
    return hit & (t_lo <= t_hi)


def points_in_boxes(points: ArrayLike, boxes: BoxSet, margin: float = 0.0) -> NDArray[np.bool_]:
    """(N, M) booleans: point n lies inside box m grown by ``margin``."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(boxes) == 0:
        return np.zeros((len(pts), 0), dtype=bool)
    local = np.einsum("mji,nmj->nmi", boxes.rotations, pts[:, None, :] - boxes.centers[None])
    return np.all(np.abs(local) <= boxes.half_sizes[None] + margin, axis=2)


# ----------------------------------------------------------------------------- the robot's end
@dataclass(frozen=True)
class ToolModel:
    """Collision geometry of what the arm carries, and the arm's link radii (metres).

    ``camera_size``/``camera_center``: the camera body as a box in the camera (OpenCV) frame; the
    default is an OAK-D-like body (0.11 wide, 0.03 tall, 0.04 deep) just behind the optical centre.
    ``flange_size``/``flange_center``: a box around the flange in the TCP frame (TCP = flange).
    ``wrist_radius``: capsule of the last link, wrist 3 -> flange. ``link_radii``: capsules of the
    DH skeleton segments frame1->2 (upper arm), 2->3 (forearm), 3->4, 4->5 (wrists 1, 2).
    ``base_half_width``/``base_height``: the robot's own base and shoulder as a box about the base
    z axis (from z = 0 up to ``base_height``), checked against the camera and flange; 0 disables.
    ``margin``: safety distance added to every test.
    """

    camera_size: tuple[float, float, float] = (0.11, 0.03, 0.04)
    camera_center: tuple[float, float, float] = (0.0, 0.0, -0.02)
    flange_size: tuple[float, float, float] = (0.08, 0.08, 0.03)
    flange_center: tuple[float, float, float] = (0.0, 0.0, -0.015)
    wrist_radius: float = 0.045
    link_radii: tuple[float, float, float, float] = (0.06, 0.05, 0.045, 0.045)
    base_half_width: float = 0.09
    base_height: float = 0.25
    margin: float = 0.01

    def robot_base_box(self) -> BoxSet:
        """The robot's base + shoulder keep-out box (empty when disabled)."""
        if self.base_half_width <= 0 or self.base_height <= 0:
            return BoxSet.empty()
        T = np.eye(4)
        T[2, 3] = 0.5 * self.base_height
        w = 2.0 * self.base_half_width
        return BoxSet.from_arrays(T[None], [[w, w, self.base_height]], ["robot base (self)"])


def _offset_box(world_T_frame: NDArray[np.float64], center: Sequence[float]) -> NDArray[np.float64]:
    T = world_T_frame.copy()
    T[:3, 3] = world_T_frame[:3, :3] @ np.asarray(center, dtype=np.float64) + world_T_frame[:3, 3]
    return T


def tool_collisions(
    base_T_flange: ArrayLike,
    base_T_cam: ArrayLike,
    boxes: BoxSet,
    tool: ToolModel = ToolModel(),
    wrist_length: float | None = None,
) -> list[str]:
    """What of the robot's end hits which box: e.g. ``["camera body vs 'table'"]`` (empty = free).

    Checks the camera body, the flange box and (with ``wrist_length`` = DH d6) the last link
    from the wrist-3 axis to the flange against ``boxes`` and the robot's own base box
    (:meth:`ToolModel.robot_base_box`). All depend only on the flange and camera poses.
    """
    boxes = boxes.concat(tool.robot_base_box())
    if len(boxes) == 0:
        return []
    F = np.asarray(base_T_flange, dtype=np.float64)
    C = np.asarray(base_T_cam, dtype=np.float64)
    hits: list[str] = []
    cam = obb_overlaps(_offset_box(C, tool.camera_center), 0.5 * np.asarray(tool.camera_size), boxes, tool.margin)
    hits += [f"camera body vs '{n}'" for n in np.asarray(boxes.names, dtype=object)[cam]]
    fl = obb_overlaps(_offset_box(F, tool.flange_center), 0.5 * np.asarray(tool.flange_size), boxes, tool.margin)
    hits += [f"flange vs '{n}'" for n in np.asarray(boxes.names, dtype=object)[fl]]
    if wrist_length is not None:
        p6 = F[:3, 3]
        p5 = p6 - wrist_length * F[:3, 2]
        wr = segment_hits(p5, p6, boxes, tool.wrist_radius, tool.margin)
        hits += [f"wrist 3 link vs '{n}'" for n in np.asarray(boxes.names, dtype=object)[wr]]
    return hits


_LINK_NAMES = ("upper arm", "forearm", "wrist 1 link", "wrist 2 link")


def arm_collisions(link_frames: ArrayLike, boxes: BoxSet, tool: ToolModel = ToolModel()) -> list[str]:
    """Which DH-skeleton link capsules (frames 1->2 ... 4->5) hit which box; ``link_frames`` is the
    (7, 4, 4) output of :meth:`brave6d.capture.kinematics.URKinematics.link_frames`."""
    if len(boxes) == 0:
        return []
    frames = np.asarray(link_frames, dtype=np.float64)
    hits: list[str] = []
    names = np.asarray(boxes.names, dtype=object)
    for k, (name, radius) in enumerate(zip(_LINK_NAMES, tool.link_radii)):
        p0 = frames[k + 1, :3, 3]
        p1 = frames[k + 2, :3, 3]
        hit = segment_hits(p0, p1, boxes, radius, tool.margin)
        hits += [f"{name} vs '{n}'" for n in names[hit]]
    return hits

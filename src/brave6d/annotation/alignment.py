"""Rigid alignment of two sets of camera poses of the same views (3D-DAT world -> robot base).

3D-DAT annotates objects in the frame of the camera poses it was given. When those poses are
expressed in another frame than the capture's robot base, the aligning transform
``target_T_source`` is estimated from the matching views by a joint least squares over camera
centres and orientations::

    min_{R, t}  sum_i |R c_i + t - d_i|^2  +  w sum_i |R A_i - B_i|_F^2

(``c_i, A_i``: source centre and rotation; ``d_i, B_i``: target). Both terms are linear in ``R``
after removing the centroids, so the optimum is one SVD (Kabsch/Umeyama without scale); the
orientation term keeps it well posed when the centres are nearly collinear. Residuals are
reported per view in mm and degrees; a large RMS residual is refused, naming the worst views.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import BraveError, DegenerateGeometryError
from brave6d.core.transforms import check_rigid, make_transform, rotation_distance

Matrix4 = NDArray[np.float64]


class AlignmentError(BraveError):
    """The two sets of camera poses do not agree up to a rigid transform (or too few views)."""


@dataclass(frozen=True)
class AlignmentOptions:
    """Thresholds: refuse above ``max_rms_mm``/``max_rms_deg``; skip (identity) when every view
    already agrees within ``skip_mm``/``skip_deg``; estimating needs ``min_frames`` views."""

    max_rms_mm: float = 3.0
    max_rms_deg: float = 0.5
    skip_mm: float = 0.05
    skip_deg: float = 0.005
    min_frames: int = 3


@dataclass(frozen=True)
class FrameResidual:
    """How far one view's aligned source pose is from its target pose."""

    frame_id: str
    translation_mm: float
    rotation_deg: float


@dataclass(frozen=True)
class AlignmentReport:
    """The transform applied (``target_T_source``), whether it was estimated, and the residuals."""

    target_T_source: Matrix4
    applied: bool
    residuals: tuple[FrameResidual, ...]
    options: AlignmentOptions = field(default_factory=AlignmentOptions)

    @property
    def frames(self) -> int:
        return len(self.residuals)

    @property
    def rms_mm(self) -> float:
        return _rms([r.translation_mm for r in self.residuals])

    @property
    def rms_deg(self) -> float:
        return _rms([r.rotation_deg for r in self.residuals])

    @property
    def max_mm(self) -> float:
        return max((r.translation_mm for r in self.residuals), default=0.0)

    @property
    def max_deg(self) -> float:
        return max((r.rotation_deg for r in self.residuals), default=0.0)

    def worst(self, n: int = 3) -> list[FrameResidual]:
        """The ``n`` views with the largest residual (translation, then rotation)."""
        return sorted(self.residuals, key=lambda r: (r.translation_mm, r.rotation_deg), reverse=True)[:n]

    def to_json(self) -> dict[str, Any]:
        return {
            "target_T_source": self.target_T_source.tolist(),
            "applied": self.applied,
            "frames": self.frames,
            "rms_mm": self.rms_mm, "max_mm": self.max_mm,
            "rms_deg": self.rms_deg, "max_deg": self.max_deg,
            "thresholds": {"max_rms_mm": self.options.max_rms_mm, "max_rms_deg": self.options.max_rms_deg,
                           "skip_mm": self.options.skip_mm, "skip_deg": self.options.skip_deg},
            "residuals": [{"frame_id": r.frame_id, "translation_mm": r.translation_mm,
                           "rotation_deg": r.rotation_deg} for r in self.residuals],
        }

    def summary(self) -> str:
        what = "estimated and applied" if self.applied else "not needed (frames agree)"
        return (f"alignment {what}: {self.frames} views, residual RMS {self.rms_mm:.3f} mm / {self.rms_deg:.4f} deg, "
                f"max {self.max_mm:.3f} mm / {self.max_deg:.4f} deg")


def _rms(values: Sequence[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values)) if values else 0.0


def _stack(poses: Sequence[ArrayLike], name: str) -> NDArray[np.float64]:
    return np.stack([check_rigid(T, f"{name}[{i}]") for i, T in enumerate(poses)])


def rigid_alignment(target: Sequence[ArrayLike], source: Sequence[ArrayLike],
                    rotation_weight_m2: float | None = None) -> Matrix4:
    """``target_T_source`` minimising the joint centre + orientation least squares (module doc).

    ``rotation_weight_m2`` (w, in m^2) balances the two terms; by default the mean squared spread
    of the source centres, at least (0.1 m)^2.
    """
    B_all = _stack(target, "target")
    A_all = _stack(source, "source")
    if len(A_all) != len(B_all) or len(A_all) == 0:
        raise DegenerateGeometryError(f"alignment needs matching, non-empty pose lists "
                                      f"(got {len(B_all)} target and {len(A_all)} source poses)")
    c, d = A_all[:, :3, 3], B_all[:, :3, 3]
    c_mean, d_mean = c.mean(axis=0), d.mean(axis=0)
    cc, dd = c - c_mean, d - d_mean
    w = rotation_weight_m2
    if w is None:
        w = max(float(np.mean(np.sum(cc * cc, axis=1))), 0.01)
    M = dd.T @ cc + w * np.einsum("nij,nkj->ik", B_all[:, :3, :3], A_all[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt))) or 1.0])
    R = U @ D @ Vt
    return make_transform(R, d_mean - R @ c_mean)


def pose_residuals(target: Sequence[ArrayLike], source: Sequence[ArrayLike], target_T_source: ArrayLike,
                   frame_ids: Sequence[str]) -> list[FrameResidual]:
    """Per view: |aligned source centre - target centre| (mm) and the rotation angle between them (deg)."""
    T = np.asarray(target_T_source, dtype=np.float64)
    out = []
    for fid, B, A in zip(frame_ids, target, source):
        aligned = T @ np.asarray(A, dtype=np.float64)
        B = np.asarray(B, dtype=np.float64)
        out.append(FrameResidual(
            frame_id=str(fid),
            translation_mm=float(np.linalg.norm(aligned[:3, 3] - B[:3, 3]) * 1000.0),
            rotation_deg=math.degrees(rotation_distance(aligned[:3, :3], B[:3, :3])),
        ))
    return out


def estimate_alignment(target: Sequence[ArrayLike], source: Sequence[ArrayLike], frame_ids: Sequence[str],
                       options: AlignmentOptions = AlignmentOptions()) -> AlignmentReport:
    """The report :func:`align_camera_poses` checks, without refusing: the identity (not applied)
    when every view agrees within the skip tolerances or when there are fewer than ``min_frames``
    views, else the estimated transform (applied) with its residuals."""
    if not (len(target) == len(source) == len(frame_ids)):
        raise ValueError("target, source and frame_ids must have the same length")
    if not frame_ids:
        raise AlignmentError("no camera pose of the 3D-DAT folder matches a captured view")
    identity = pose_residuals(target, source, np.eye(4), frame_ids)
    agree = all(r.translation_mm <= options.skip_mm and r.rotation_deg <= options.skip_deg for r in identity)
    if agree or len(frame_ids) < options.min_frames:
        return AlignmentReport(np.eye(4), applied=False, residuals=tuple(identity), options=options)
    T = rigid_alignment(target, source)
    return AlignmentReport(T, applied=True, residuals=tuple(pose_residuals(target, source, T, frame_ids)),
                           options=options)


def alignment_problem(report: AlignmentReport) -> str | None:
    """Why ``report`` is refused (one line), or None when it is accepted."""
    options = report.options
    if not report.applied:
        worst = max(report.residuals, key=lambda r: r.translation_mm)
        if all(r.translation_mm <= options.skip_mm and r.rotation_deg <= options.skip_deg for r in report.residuals):
            return None
        return (f"the 3D-DAT camera poses differ from the captured ones (up to {worst.translation_mm:.2f} mm at "
                f"frame {worst.frame_id!r}) but only {report.frames} views match; at least {options.min_frames} "
                "are needed to estimate and check the aligning transform")
    if report.rms_mm > options.max_rms_mm or report.rms_deg > options.max_rms_deg:
        worst_views = ", ".join(f"{r.frame_id!r} ({r.translation_mm:.2f} mm, {r.rotation_deg:.3f} deg)"
                                for r in report.worst(3))
        return (f"the 3D-DAT camera poses do not match the captured ones up to a rigid transform: residual RMS "
                f"{report.rms_mm:.2f} mm / {report.rms_deg:.3f} deg over {report.frames} views exceeds "
                f"{options.max_rms_mm} mm / {options.max_rms_deg} deg; worst frames: {worst_views}")
    return None


def align_camera_poses(target: Sequence[ArrayLike], source: Sequence[ArrayLike], frame_ids: Sequence[str],
                       options: AlignmentOptions = AlignmentOptions()) -> AlignmentReport:
    """Align ``source`` camera poses (3D-DAT world) to ``target`` (robot base) of the same views.

    Returns an identity report when the views already agree within the skip tolerances;
    otherwise estimates the transform and raises :class:`AlignmentError` when the RMS residual
    exceeds the thresholds (or there are fewer than ``min_frames`` views to estimate from).
    """
    report = estimate_alignment(target, source, frame_ids, options)
    problem = alignment_problem(report)
    if problem is not None:
        raise AlignmentError(problem)
    return report


def apply_alignment(target_T_source: ArrayLike, poses: Sequence[ArrayLike]) -> list[Matrix4]:
    """Express source-frame poses in the target frame (``target_T_source @ pose``), kept rigid."""
    T = check_rigid(target_T_source, "alignment")
    return [check_rigid(T @ np.asarray(P, dtype=np.float64), "aligned pose") for P in poses]


__all__ = ["AlignmentError", "AlignmentOptions", "AlignmentReport", "FrameResidual", "align_camera_poses",
           "alignment_problem", "apply_alignment", "estimate_alignment", "pose_residuals", "rigid_alignment"]

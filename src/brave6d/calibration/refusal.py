"""Why a hand-eye result is too uncertain to accept: the dominant cause and each cause's share.

A result is refused when its 1-sigma (norm over the axes) exceeds ``max_sigma_mm`` or
``max_sigma_deg`` (:class:`~brave6d.calibration.handeye.HandEyeOptions`). The variance of the
refused quantity (translation or rotation, whichever exceeds its limit by more) is split in two
additive parts, as :class:`~brave6d.calibration.handeye_result.Uncertainty` sums them:

* **intrinsics uncertainty**: the part the intrinsics' own uncertainty adds;
* the **poses** part (what the views give with the intrinsics held), which to first order is
  ``pixel noise^2 x geometry / corners``. It is shared among three causes in proportion to the
  logarithm of how far each factor is worse than a good capture's (factors at or better than
  the reference get no share):

  - **reprojection error**: ``(pixel noise / 0.5 px)^2`` (the corner noise that the per-view PnP
    fits show; a sharp ChArUco image gives 0.05-0.3 px);
  - **detection count**: ``recommended views x board corners / corners used`` (too few views, or
    boards seen only in part);
  - **pose conditioning**: ``(recommended weakest rotation / weakest rotation)^2`` (the RMS rotation
    about the direction the motions turn least, :func:`~brave6d.calibration.conditioning.weakest_rotation`).

  When none is worse than its reference, the poses part goes to the factor closest to it and the
  message says that the limits are tighter than this capture can reach.

The refusal (:class:`HandEyeRefusedError`) names the dominant cause with its share, every share,
the figures behind them and advice for that cause.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from brave6d.core.errors import DegenerateGeometryError
from brave6d.calibration.handeye_result import Uncertainty

__all__ = ["CAUSES", "PIXEL_SIGMA_OK_PX", "HandEyeRefusedError", "UncertaintyBreakdown", "explain_uncertainty"]

INTRINSICS, CONDITIONING, COUNT, REPROJECTION = ("intrinsics uncertainty", "pose conditioning", "detection count",
                                                 "reprojection error")
#: The causes a refusal names, in the order of its messages.
CAUSES = (INTRINSICS, CONDITIONING, COUNT, REPROJECTION)
#: Corner noise of a good capture (px); more counts against the reprojection.
PIXEL_SIGMA_OK_PX = 0.5


@dataclass(frozen=True)
class UncertaintyBreakdown:
    """The figures of a too-uncertain result and the share of each cause (see the module docstring).

    ``judged``: ``"translation"`` or ``"rotation"``, the quantity furthest beyond its limit;
    ``shares``: cause -> fraction of its variance (sums to 1); ``intrinsics_*``/``poses_*``: the
    1-sigma from each part; ``factors``: cause -> how much worse than a good capture (> 1: worse).
    """

    sigma_mm: float
    sigma_deg: float
    limit_mm: float | None
    limit_deg: float | None
    judged: str
    intrinsics_mm: float
    intrinsics_deg: float
    poses_mm: float
    poses_deg: float
    shares: dict[str, float]
    factors: dict[str, float]
    pixel_sigma_px: float
    n_corners: int
    n_views: int
    n_input_views: int
    board_corners: int
    weakest_rotation_deg: float
    recommended_views: int
    recommended_weakest_deg: float

    @property
    def dominant(self) -> str:
        """The cause with the largest share."""
        return max(CAUSES, key=lambda c: self.shares[c])

    @property
    def exceeded(self) -> bool:
        """True when a limit is exceeded."""
        return (self.limit_mm is not None and self.sigma_mm > self.limit_mm) or (
            self.limit_deg is not None and self.sigma_deg > self.limit_deg)

    def advice(self) -> str:
        """What to change for the dominant cause."""
        cause = self.dominant
        if cause == INTRINSICS:
            return ("the intrinsics' own uncertainty dominates: refine them jointly with the hand-eye transform "
                    "(HandEyeOptions.refine_intrinsics; 'brave6d calibrate folder' does unless --no-refine-intrinsics), "
                    "calibrate them from "
                    "more board views that fill the image with the board tilted 30-45 deg, or give better intrinsics")
        if cause == CONDITIONING:
            return (f"add poses with larger rotations about different axes (the motions turn their weakest direction "
                    f"by {self.weakest_rotation_deg:.1f} deg RMS; {self.recommended_weakest_deg:g} deg or more "
                    "recommended)")
        if cause == COUNT:
            return (f"add views, or keep more of the board in view in each ({self.n_corners} corners in {self.n_views} "
                    f"usable views of {self.n_input_views}; about {self.recommended_views} views showing the whole "
                    f"board, {self.recommended_views * self.board_corners} corners, recommended)")
        return (f"the corners fit with {self.pixel_sigma_px:.2f} px noise (a sharp ChArUco image gives under "
                f"{PIXEL_SIGMA_OK_PX:g} px): check focus, motion blur and lighting, the distortion model, and that "
                "the board geometry (squares, square and marker size, dictionary) matches the printed board")

    def message(self) -> str:
        """One line: the figures, the limits, the dominant cause with its share, every share, advice."""
        limits = f"{_limit(self.limit_mm)} mm / {_limit(self.limit_deg)} deg"
        dominant = self.dominant
        shares = ", ".join(f"{c} {self.shares[c]:.0%}" for c in CAUSES)
        worse = [c for c in (CONDITIONING, COUNT, REPROJECTION) if self.factors[c] > 1.0]
        tight = "" if dominant == INTRINSICS or dominant in worse else (
            " (no figure of the poses is worse than a good capture's: the limits are tighter than this capture "
            "can reach)")
        return (
            f"hand-eye result refused, it is poorly determined: 1-sigma {self.sigma_mm:.2f} mm / {self.sigma_deg:.3f} "
            f"deg exceeds the limits {limits} (max_sigma_mm / max_sigma_deg; on the command line --max-sigma-mm / "
            f"--max-sigma-deg). Dominant cause: {dominant}, {self.shares[dominant]:.0%} of the {self.judged} "
            f"variance{tight}; the intrinsics' uncertainty gives {self.intrinsics_mm:.2f} mm / "
            f"{self.intrinsics_deg:.3f} deg, the poses alone {self.poses_mm:.2f} mm / {self.poses_deg:.3f} deg "
            f"(pixel noise {self.pixel_sigma_px:.2f} px, {self.n_corners} corners in {self.n_views} of "
            f"{self.n_input_views} views, weakest rotation {self.weakest_rotation_deg:.1f} deg). Shares: {shares}. "
            f"Advice: {self.advice()}"
        )


def _limit(v: float | None) -> str:
    return "none" if v is None else f"{v:g}"


class HandEyeRefusedError(DegenerateGeometryError):
    """A hand-eye result whose uncertainty exceeds the limits; ``breakdown`` says why."""

    def __init__(self, breakdown: UncertaintyBreakdown) -> None:
        super().__init__(breakdown.message())
        self.breakdown = breakdown


def _parts(unc: Uncertainty) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis variances ``(poses, intrinsics)`` in (rad^2 x 3, m^2 x 3), as the uncertainty sums them."""
    poses = np.maximum(np.diag(unc.covariance_model), np.diag(unc.covariance_clustered))
    intrinsics = np.maximum(np.diag(unc.covariance_intrinsics), 0.0)
    return np.maximum(poses, 0.0), intrinsics


def explain_uncertainty(
    unc: Uncertainty,
    *,
    limit_mm: float | None,
    limit_deg: float | None,
    pixel_sigma_px: float,
    n_corners: int,
    n_views: int,
    n_input_views: int,
    board_corners: int,
    weakest_rotation_deg: float,
    recommended_views: int = 10,
    recommended_weakest_deg: float = 10.0,
) -> UncertaintyBreakdown:
    """The breakdown of ``unc`` (see the module docstring); ``board_corners``: corners of the
    whole board; the recommendations are :class:`~brave6d.calibration.conditioning.ConditioningThresholds`'."""
    poses, intr = _parts(unc)
    t_ratio = unc.translation_sigma_norm_mm / limit_mm if limit_mm else 0.0
    r_ratio = unc.rotation_sigma_norm_deg / limit_deg if limit_deg else 0.0
    judged = "translation" if t_ratio >= r_ratio else "rotation"
    axes = slice(3, 6) if judged == "translation" else slice(0, 3)
    var_p, var_i = float(poses[axes].sum()), float(intr[axes].sum())
    total = var_p + var_i
    share_i = var_i / total if total > 0 else 0.0
    factors = {
        REPROJECTION: (pixel_sigma_px / PIXEL_SIGMA_OK_PX) ** 2,
        COUNT: recommended_views * board_corners / max(n_corners, 1),
        CONDITIONING: (recommended_weakest_deg / max(weakest_rotation_deg, 1e-6)) ** 2,
    }
    logs = {c: max(math.log(max(f, 1e-12)), 0.0) for c, f in factors.items()}
    if sum(logs.values()) > 0:
        weights = {c: v / sum(logs.values()) for c, v in logs.items()}
    else:  # nothing worse than a good capture: the factor closest to its reference takes the poses part
        closest = max(factors, key=lambda c: factors[c])
        weights = {c: float(c == closest) for c in factors}
    shares = {INTRINSICS: share_i, **{c: (1.0 - share_i) * weights[c] for c in (CONDITIONING, COUNT, REPROJECTION)}}
    return UncertaintyBreakdown(
        sigma_mm=unc.translation_sigma_norm_mm, sigma_deg=unc.rotation_sigma_norm_deg, limit_mm=limit_mm,
        limit_deg=limit_deg, judged=judged,
        intrinsics_mm=1000.0 * math.sqrt(float(intr[3:].sum())), intrinsics_deg=math.degrees(math.sqrt(float(intr[:3].sum()))),
        poses_mm=1000.0 * math.sqrt(float(poses[3:].sum())), poses_deg=math.degrees(math.sqrt(float(poses[:3].sum()))),
        shares=shares, factors=factors, pixel_sigma_px=pixel_sigma_px, n_corners=n_corners, n_views=n_views,
        n_input_views=n_input_views, board_corners=board_corners, weakest_rotation_deg=weakest_rotation_deg,
        recommended_views=recommended_views, recommended_weakest_deg=recommended_weakest_deg,
    )

"""Typed hand-eye results and their JSON form (``calibration/handeye.json``).

Schema ``brave6d.handeye/1`` (all lengths in metres unless the key says mm, angles in degrees
where the key says deg):

* ``method``: how the result was obtained; ``tcp_T_cam``, ``base_T_board``: 4x4 row-major;
* ``residuals``: :class:`Residuals` of the result (px, mm, deg);
* ``fit``: the refinement's own figures (:class:`FitSummary`): reprojection RMS with the
  estimated robot pose corrections, estimated pixel noise, robot error model;
* ``uncertainty``: :class:`Uncertainty` (1-sigma, mm and deg, with the 6x6 covariances);
* ``methods``: one :class:`MethodResult` per closed-form method and one for ``refined``;
* ``views`` / ``skipped_views``: per input view, used or skipped with the reason;
* ``conditioning``, ``intrinsics`` (K, dist used; with ``std``, their 1-sigma, when they were refined
  jointly with the hand-eye transform), ``loss``, ``f_scale_px``, ``warnings``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.atomic import read_json_as
from brave6d.core.calibration_io import write_handeye_file
from brave6d.core.errors import DataError
from brave6d.core.transforms import check_rigid, rotation_distance, translation_distance
from brave6d.calibration.conditioning import ConditioningReport

__all__ = ["SCHEMA", "FitSummary", "HandEyeResult", "MethodResult", "Residuals", "Uncertainty", "ViewReport"]

SCHEMA = "brave6d.handeye/1"
Array = NDArray[np.float64]


def _opt_float(v: Any) -> float | None:
    return None if v is None else float(v)


@dataclass(frozen=True)
class Residuals:
    """Fit quality of one ``tcp_T_cam`` with its ``base_T_board`` on the used views, with the
    robot poses as reported (so every method is judged the same way).

    ``reprojection_*_px``: per-corner reprojection error (Euclidean, px); ``reprojection_rms_mm``:
    the same error scaled to the board (px * depth / f); ``axxb_*``: ``A X = X B`` consistency
    over all view pairs (angle and translation of ``inv(A X) X B``); ``board_*``: spread of the
    board pose ``base_T_tcp_i X cam_T_board_i`` implied by each view around ``base_T_board``.
    """

    reprojection_rms_px: float
    reprojection_median_px: float
    reprojection_max_px: float
    reprojection_rms_mm: float
    axxb_rotation_rms_deg: float
    axxb_translation_rms_mm: float
    axxb_rotation_max_deg: float
    axxb_translation_max_mm: float
    board_rotation_rms_deg: float
    board_translation_rms_mm: float
    n_views: int
    n_corners: int

    def to_json(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @staticmethod
    def from_json(d: dict[str, Any]) -> Residuals:
        return Residuals(**{f.name: (int if f.name.startswith("n_") else float)(d[f.name]) for f in fields(Residuals)})


@dataclass(frozen=True)
class Uncertainty:
    """1-sigma uncertainty of ``tcp_T_cam`` about / along the TCP frame's axes.

    Covariances are 6x6 in (rad, m), order ``[rx, ry, rz, tx, ty, tz]``, for a perturbation
    ``R = exp([r]x) R_hat``, ``t = t_hat + dt``: ``covariance_model`` is the Gauss-Newton
    estimate ``s^2 (J^T W J)^-1``, ``covariance_clustered`` a sandwich estimate clustered by
    view (robust to errors shared by a view's corners), ``covariance_intrinsics`` the part
    propagated from the intrinsics' uncertainty (zeros when it was not given). Variances are
    the larger of the first two plus the third.
    """

    translation_sigma_mm: tuple[float, float, float]
    rotation_sigma_deg: tuple[float, float, float]
    translation_sigma_norm_mm: float
    rotation_sigma_norm_deg: float
    covariance_model: Array
    covariance_clustered: Array
    covariance_intrinsics: Array

    @staticmethod
    def from_covariances(cov_model: Array, cov_clustered: Array, cov_intrinsics: Array | None = None) -> Uncertainty:
        cov_i = np.zeros((6, 6)) if cov_intrinsics is None else np.asarray(cov_intrinsics, dtype=np.float64)
        var = np.maximum(np.diag(cov_model), np.diag(cov_clustered)) + np.maximum(np.diag(cov_i), 0.0)
        sig = np.sqrt(np.maximum(var, 0.0))
        rot = np.degrees(sig[:3])
        trans = 1000.0 * sig[3:]
        return Uncertainty(
            (float(trans[0]), float(trans[1]), float(trans[2])), (float(rot[0]), float(rot[1]), float(rot[2])),
            float(np.linalg.norm(trans)), float(np.linalg.norm(rot)), cov_model, cov_clustered, cov_i,
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "translation_sigma_mm": list(self.translation_sigma_mm),
            "rotation_sigma_deg": list(self.rotation_sigma_deg),
            "translation_sigma_norm_mm": self.translation_sigma_norm_mm,
            "rotation_sigma_norm_deg": self.rotation_sigma_norm_deg,
            "covariance_model": self.covariance_model.tolist(),
            "covariance_clustered": self.covariance_clustered.tolist(),
            "covariance_intrinsics": self.covariance_intrinsics.tolist(),
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> Uncertainty:
        t = [float(v) for v in d["translation_sigma_mm"]]
        r = [float(v) for v in d["rotation_sigma_deg"]]
        return Uncertainty(
            (t[0], t[1], t[2]), (r[0], r[1], r[2]),
            float(d["translation_sigma_norm_mm"]), float(d["rotation_sigma_norm_deg"]),
            np.asarray(d["covariance_model"], dtype=np.float64), np.asarray(d["covariance_clustered"], dtype=np.float64),
            np.asarray(d.get("covariance_intrinsics", np.zeros((6, 6))), dtype=np.float64),
        )


@dataclass(frozen=True)
class FitSummary:
    """The joint refinement's own figures.

    ``fit_rms_px``: reprojection RMS of the refinement's model (with the estimated robot pose
    corrections when ``robot_sigma_mm``/``robot_sigma_deg`` are set); ``pixel_sigma_px``: corner
    noise used to weight pixels against the robot error model (estimated from the residuals
    unless given); ``robot_sigma_mm``/``_deg``: the robot error model of the final fit (estimated
    from the corrections when ``robot_sigma_configured_mm``/``_deg``, the configured starting
    values, are set); ``robot_correction_rms_mm``/``_deg``: RMS of the estimated per-view robot
    pose corrections; ``iterations``: function evaluations of ``least_squares``.
    """

    fit_rms_px: float
    pixel_sigma_px: float
    robot_sigma_mm: float | None
    robot_sigma_deg: float | None
    robot_correction_rms_mm: float | None
    robot_correction_rms_deg: float | None
    iterations: int
    robot_sigma_configured_mm: float | None = None
    robot_sigma_configured_deg: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @staticmethod
    def from_json(d: dict[str, Any]) -> FitSummary:
        return FitSummary(
            float(d["fit_rms_px"]), float(d["pixel_sigma_px"]), _opt_float(d.get("robot_sigma_mm")),
            _opt_float(d.get("robot_sigma_deg")), _opt_float(d.get("robot_correction_rms_mm")),
            _opt_float(d.get("robot_correction_rms_deg")), int(d["iterations"]),
            _opt_float(d.get("robot_sigma_configured_mm")), _opt_float(d.get("robot_sigma_configured_deg")),
        )


@dataclass(frozen=True)
class MethodResult:
    """One row of the method table: a closed-form solution or the refined one.

    ``error`` is set (and the matrices are None) when the method failed on this data.
    ``time_s``: the solver's own time; for ``refined``, everything after PnP (all closed-form
    solvers, their board fits and the refinement), i.e. the cost of the final answer.
    """

    method: str
    tcp_T_cam: Array | None
    base_T_board: Array | None
    residuals: Residuals | None
    time_s: float
    error: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "tcp_T_cam": None if self.tcp_T_cam is None else self.tcp_T_cam.tolist(),
            "base_T_board": None if self.base_T_board is None else self.base_T_board.tolist(),
            "residuals": None if self.residuals is None else self.residuals.to_json(),
            "time_s": self.time_s,
            "error": self.error,
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> MethodResult:
        return MethodResult(
            str(d["method"]),
            None if d.get("tcp_T_cam") is None else np.asarray(d["tcp_T_cam"], dtype=np.float64),
            None if d.get("base_T_board") is None else np.asarray(d["base_T_board"], dtype=np.float64),
            None if d.get("residuals") is None else Residuals.from_json(d["residuals"]),
            float(d["time_s"]), d.get("error"),
        )


@dataclass(frozen=True)
class ViewReport:
    """What happened to one input view: used (with its residuals) or skipped (with a reason).

    For used views: ``rms_px`` and ``corner_errors_px`` are the final model's reprojection
    errors; ``mean_weight`` the mean robust-loss weight of its corners (1 = full weight);
    ``robot_correction_mm``/``_deg`` the size of the estimated robot pose correction.
    """

    index: int
    name: str
    used: bool
    reason: str
    n_corners: int
    rms_px: float | None = None
    mean_weight: float | None = None
    robot_correction_mm: float | None = None
    robot_correction_deg: float | None = None
    corner_errors_px: tuple[float, ...] = ()

    def to_json(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["corner_errors_px"] = [float(e) for e in self.corner_errors_px]
        return d

    @staticmethod
    def from_json(d: dict[str, Any]) -> ViewReport:
        return ViewReport(
            int(d["index"]), str(d["name"]), bool(d["used"]), str(d["reason"]), int(d["n_corners"]),
            _opt_float(d.get("rms_px")), _opt_float(d.get("mean_weight")), _opt_float(d.get("robot_correction_mm")),
            _opt_float(d.get("robot_correction_deg")), tuple(float(e) for e in d.get("corner_errors_px", ())),
        )


@dataclass(frozen=True)
class HandEyeResult:
    """Result of :func:`~brave6d.calibration.handeye.calibrate_handeye` (see the module docstring).

    ``K``, ``dist``: the intrinsics of the result (refined jointly when ``intrinsics_std`` is set,
    their 1-sigma from that solve; else as given)."""

    method: str
    tcp_T_cam: Array
    base_T_board: Array
    residuals: Residuals
    fit: FitSummary | None
    uncertainty: Uncertainty | None
    methods: tuple[MethodResult, ...]
    views: tuple[ViewReport, ...]
    conditioning: ConditioningReport
    K: Array
    dist: Array
    loss: str
    f_scale_px: float
    warnings: tuple[str, ...] = ()
    intrinsics_std: dict[str, float] | None = None

    @property
    def skipped_views(self) -> list[ViewReport]:
        """Views that were not used, each with its reason."""
        return [v for v in self.views if not v.used]

    def camera_pose(self, base_T_tcp: ArrayLike) -> Array:
        """``base_T_cam = base_T_tcp @ tcp_T_cam``."""
        return np.asarray(base_T_tcp, dtype=np.float64) @ self.tcp_T_cam

    def method_result(self, method: str) -> MethodResult:
        """The table row of ``method`` (``"tsai"``, ``"park"``, ``"daniilidis"``, ``"refined"``)."""
        for m in self.methods:
            if m.method == method:
                return m
        raise KeyError(f"no method {method!r} in this result ({[m.method for m in self.methods]})")

    def errors_against(self, tcp_T_cam_true: ArrayLike) -> dict[str, tuple[float, float]]:
        """``{method: (translation error mm, rotation error deg)}`` against a known truth."""
        truth = np.asarray(tcp_T_cam_true, dtype=np.float64)
        return {
            m.method: (1000.0 * translation_distance(m.tcp_T_cam, truth), math.degrees(rotation_distance(m.tcp_T_cam, truth)))
            for m in self.methods if m.tcp_T_cam is not None
        }

    def to_json(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA,
            "method": self.method,
            "tcp_T_cam": self.tcp_T_cam.tolist(),
            "base_T_board": self.base_T_board.tolist(),
            "residuals": self.residuals.to_json(),
            "fit": None if self.fit is None else self.fit.to_json(),
            "uncertainty": None if self.uncertainty is None else self.uncertainty.to_json(),
            "methods": [m.to_json() for m in self.methods],
            "skipped_views": [{"index": v.index, "name": v.name, "reason": v.reason} for v in self.skipped_views],
            "views": [v.to_json() for v in self.views],
            "conditioning": self.conditioning.to_json(),
            "intrinsics": {"K": self.K.tolist(), "dist": self.dist.tolist(),
                           **({} if self.intrinsics_std is None else {"std": dict(self.intrinsics_std)})},
            "loss": self.loss,
            "f_scale_px": self.f_scale_px,
            "warnings": list(self.warnings),
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> HandEyeResult:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            got = d.get("schema") if isinstance(d, dict) else type(d).__name__
            raise DataError(f"hand-eye result: expected schema {SCHEMA!r}, got {got!r}")
        try:
            return HandEyeResult(
                str(d["method"]),
                check_rigid(d["tcp_T_cam"], "hand-eye result tcp_T_cam"),
                check_rigid(d["base_T_board"], "hand-eye result base_T_board"),
                Residuals.from_json(d["residuals"]),
                None if d.get("fit") is None else FitSummary.from_json(d["fit"]),
                None if d.get("uncertainty") is None else Uncertainty.from_json(d["uncertainty"]),
                tuple(MethodResult.from_json(m) for m in d["methods"]),
                tuple(ViewReport.from_json(v) for v in d["views"]),
                ConditioningReport.from_json(d["conditioning"]),
                np.asarray(d["intrinsics"]["K"], dtype=np.float64).reshape(3, 3),
                np.asarray(d["intrinsics"]["dist"], dtype=np.float64).reshape(-1),
                str(d["loss"]), float(d["f_scale_px"]), tuple(str(w) for w in d.get("warnings", ())),
                None if d["intrinsics"].get("std") is None
                else {str(k): float(v) for k, v in d["intrinsics"]["std"].items()},
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise DataError(f"hand-eye result: missing or malformed field ({type(exc).__name__}: {exc})") from None

    def save(self, path: Path | str, **extra: Any) -> Path:
        """Write :meth:`to_json` (plus ``extra`` keys) through the hand-eye file's one writer."""
        details = {**self.to_json(), **extra}
        details.pop("tcp_T_cam")
        return write_handeye_file(path, self.tcp_T_cam, **details)

    @staticmethod
    def load(path: Path | str) -> HandEyeResult:
        """Read a file written by :meth:`save`; errors name the file."""
        return read_json_as(path, HandEyeResult.from_json)

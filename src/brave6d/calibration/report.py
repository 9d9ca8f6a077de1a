"""Calibration report: a Markdown page with the method table and residuals, and a residual plot.

:func:`write_report` writes ``<stem>.md`` and ``<stem>_residuals.png`` (matplotlib, Agg,
no global pyplot state) into a folder, atomically. With ``truth_tcp_T_cam`` (simulated
captures) the method table also lists each method's error against the truth.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from brave6d.core.atomic import atomic_write_bytes, atomic_write_text
from brave6d.core.transforms import matrix_to_rpy_deg
from brave6d.calibration.handeye_result import HandEyeResult
from brave6d.calibration.intrinsics import IntrinsicsResult

__all__ = ["ReportPaths", "handeye_markdown", "intrinsics_markdown", "plot_residuals", "write_report"]


@dataclass(frozen=True)
class ReportPaths:
    markdown: Path
    plot: Path | None


def _f(x: float | None, digits: int = 3) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def intrinsics_markdown(result: IntrinsicsResult) -> list[str]:
    """Markdown lines of the intrinsics section."""
    K, std = result.K, result.std

    def pm(key: str, value: float) -> str:
        return f"{value:.3f} +- {std[key]:.3f}" if key in std else f"{value:.3f}"

    lines = [
        "## Intrinsics",
        "",
        (f"Source: **{result.source}**, image {result.width} x {result.height} px, distortion model "
         f"`{result.distortion_model}`, overall reprojection RMS **{result.rms_px:.3f} px** "
         f"({sum(v.used for v in result.views)} of {len(result.views)} views used, {result.rounds} round(s))."),
        "",
        *_table(["fx", "fy", "cx", "cy"], [[pm("fx", K[0, 0]), pm("fy", K[1, 1]), pm("cx", K[0, 2]), pm("cy", K[1, 2])]]),
        "",
        f"Distortion: `{np.array2string(result.dist, precision=5, separator=', ')}`",
        "",
        *_table(["view", "corners", "RMS px", "status"],
                [[v.name, str(v.n_corners), _f(v.rms_px), v.reason] for v in result.views]),
        "",
    ]
    lines += [f"- model: {n}" for n in result.notes]
    lines += [f"- warning: {w}" for w in result.warnings]
    return lines


def handeye_markdown(result: HandEyeResult, truth_tcp_T_cam: ArrayLike | None = None,
                     setup: str = "eye-in-hand") -> list[str]:
    """Markdown lines of the hand-eye section (method table, residuals, uncertainty, views);
    ``setup="eye-to-hand"``: ``result`` is an eye-to-hand solution (its ``tcp_T_cam`` is ``base_T_cam``)."""
    name, axes = ("base_T_cam", "base") if setup == "eye-to-hand" else ("tcp_T_cam", "TCP")
    X = result.tcp_T_cam
    t_mm = 1000.0 * X[:3, 3]
    rpy = matrix_to_rpy_deg(X[:3, :3])
    unc = result.uncertainty
    errors = result.errors_against(truth_tcp_T_cam) if truth_tcp_T_cam is not None else {}
    lines = [
        f"## Hand-eye ({setup})",
        "",
        f"Result: **{result.method}**",
        "",
        f"- {name} translation: [{t_mm[0]:.3f}, {t_mm[1]:.3f}, {t_mm[2]:.3f}] mm",
        f"- {name} rotation (roll, pitch, yaw about x, y, z, extrinsic): [{rpy[0]:.4f}, {rpy[1]:.4f}, {rpy[2]:.4f}] deg",
    ]
    if unc is not None:
        ts, rs = unc.translation_sigma_mm, unc.rotation_sigma_deg
        lines.append(
            f"- 1-sigma uncertainty: translation [{ts[0]:.3f}, {ts[1]:.3f}, {ts[2]:.3f}] mm "
            f"(norm {unc.translation_sigma_norm_mm:.3f}), rotation [{rs[0]:.4f}, {rs[1]:.4f}, {rs[2]:.4f}] deg "
            f"(norm {unc.rotation_sigma_norm_deg:.4f}), about the {axes} axes"
        )
    r = result.residuals
    lines += [
        (f"- residuals: reprojection RMS {r.reprojection_rms_px:.3f} px (median {r.reprojection_median_px:.3f}, "
         f"max {r.reprojection_max_px:.3f}) = {r.reprojection_rms_mm:.3f} mm on the board; AX = XB RMS "
         f"{r.axxb_rotation_rms_deg:.4f} deg / {r.axxb_translation_rms_mm:.3f} mm; board pose spread "
         f"{r.board_rotation_rms_deg:.4f} deg / {r.board_translation_rms_mm:.3f} mm "
         f"({r.n_views} views, {r.n_corners} corners)"),
    ]
    if result.fit is not None:
        f = result.fit
        source = (f" (estimated from the corrections; configured {f.robot_sigma_configured_mm:g} mm / "
                  f"{f.robot_sigma_configured_deg:g} deg)"
                  if f.robot_sigma_configured_mm is not None and f.robot_sigma_configured_deg is not None else "")
        robot = (f"robot error model {f.robot_sigma_mm:.3g} mm / {f.robot_sigma_deg:.3g} deg per axis{source}, "
                 f"estimated corrections RMS {_f(f.robot_correction_rms_mm)} mm / {_f(f.robot_correction_rms_deg, 4)} deg"
                 if f.robot_sigma_mm and f.robot_sigma_deg else "robot poses taken as exact")
        lines.append(f"- refinement: fit RMS {f.fit_rms_px:.3f} px, pixel noise {f.pixel_sigma_px:.3f} px, {robot}; "
                     f"{f.iterations} function evaluations")
    c = result.conditioning
    lines += [
        f"- conditioning: {c.n_poses} poses, rotation span {c.rotation_span_deg:.1f} deg, largest angle between "
        f"motion axes {c.max_axis_angle_deg:.1f} deg"
        + (f", robot/camera angle mismatch (median) {c.median_angle_mismatch_deg:.3f} deg"
           if c.median_angle_mismatch_deg is not None else ""),
        "",
        "### Methods",
        "",
        (f"Residuals of every method are measured the same way: its {name}, its best board pose, the robot "
         "poses as reported."),
        "",
    ]
    header = ["method", "reproj RMS px", "reproj RMS mm", "AX=XB deg", "AX=XB mm", "board spread mm", "time ms"]
    if errors:
        header += ["error mm", "error deg"]
    rows = []
    for m in result.methods:
        res = m.residuals
        row = [
            m.method if m.error is None else f"{m.method} ({m.error})",
            _f(res.reprojection_rms_px if res else None, 4), _f(res.reprojection_rms_mm if res else None, 4),
            _f(res.axxb_rotation_rms_deg if res else None, 4), _f(res.axxb_translation_rms_mm if res else None, 3),
            _f(res.board_translation_rms_mm if res else None, 3), _f(1000.0 * m.time_s, 1),
        ]
        if errors:
            e = errors.get(m.method)
            row += [_f(e[0] if e else None, 4), _f(e[1] if e else None, 5)]
        rows.append(row)
    lines += _table(header, rows)
    lines += ["", "### Views", ""]
    lines += _table(
        ["view", "corners", "RMS px", "weight", "robot corr. mm", "robot corr. deg", "status"],
        [[v.name, str(v.n_corners), _f(v.rms_px), _f(v.mean_weight, 2), _f(v.robot_correction_mm),
          _f(v.robot_correction_deg, 4), v.reason] for v in result.views],
    )
    lines.append("")
    lines += [f"- warning: {w}" for w in result.warnings]
    return lines


def plot_residuals(
    handeye: HandEyeResult | None, intrinsics: IntrinsicsResult | None = None
) -> bytes:
    """PNG bytes: per-view reprojection RMS (hand-eye, intrinsics) and the corner error histogram."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    panels = (2 if handeye is not None else 0) + (1 if intrinsics is not None else 0)
    fig = Figure(figsize=(5.0 * max(panels, 1), 3.6), dpi=110)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, max(panels, 1), k + 1) for k in range(max(panels, 1))]
    k = 0
    if handeye is not None:
        ax = axes[k]
        views = handeye.views
        x = np.arange(len(views))
        rms = [v.rms_px if v.rms_px is not None else 0.0 for v in views]
        colors = ["tab:gray" if not v.used else ("tab:orange" if v.reason != "used" else "tab:blue") for v in views]
        ax.bar(x, rms, color=colors)
        for xi, v in zip(x, views, strict=True):
            if not v.used:
                ax.plot(xi, 0.0, "x", color="tab:red")
        ax.set_xlabel("view (red x: skipped, orange: down-weighted)")
        ax.set_ylabel("reprojection RMS [px]")
        ax.set_title("hand-eye: per-view residual")
        ax = axes[k + 1]
        errs = np.concatenate([np.asarray(v.corner_errors_px) for v in views if v.used] or [np.zeros(0)])
        ax.hist(errs, bins=40, color="tab:blue")
        ax.set_xlabel("corner reprojection error [px]")
        ax.set_ylabel("corners")
        ax.set_title(f"hand-eye: {len(errs)} corners, RMS {handeye.fit.fit_rms_px if handeye.fit else 0:.3f} px")
        k += 2
    if intrinsics is not None:
        ax = axes[k]
        views_i = intrinsics.views
        rms_i = [v.rms_px if v.rms_px is not None else 0.0 for v in views_i]
        ax.bar(np.arange(len(views_i)), rms_i, color=["tab:blue" if v.used else "tab:gray" for v in views_i])
        ax.set_xlabel("view (grey: dropped)")
        ax.set_ylabel("reprojection RMS [px]")
        ax.set_title(f"intrinsics: RMS {intrinsics.rms_px:.3f} px")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def write_report(
    out_dir: Path | str,
    handeye: HandEyeResult | None = None,
    intrinsics: IntrinsicsResult | None = None,
    truth_tcp_T_cam: ArrayLike | None = None,
    stem: str = "report",
    setup: str = "eye-in-hand",
) -> ReportPaths:
    """Write ``<stem>.md`` and ``<stem>_residuals.png`` into ``out_dir`` (atomically); ``setup`` as
    for :func:`handeye_markdown`."""
    folder = Path(out_dir)
    lines = ["# Calibration report", ""]
    if intrinsics is not None:
        lines += intrinsics_markdown(intrinsics) + [""]
    if handeye is not None:
        lines += handeye_markdown(handeye, truth_tcp_T_cam, setup) + [""]
    plot = None
    if handeye is not None or intrinsics is not None:
        plot = atomic_write_bytes(folder / f"{stem}_residuals.png", plot_residuals(handeye, intrinsics))
        lines += ["## Residual plot", "", f"![residuals]({plot.name})", ""]
    md = atomic_write_text(folder / f"{stem}.md", "\n".join(lines))
    return ReportPaths(md, plot)

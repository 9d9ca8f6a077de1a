"""Eye-to-hand calibration: a static camera, the board on the robot's tool; ``base_T_cam``.

The standard reduction to eye-in-hand: with the board on the tool, view ``i`` sees
``cam_T_board_i = inv(base_T_cam) base_T_tcp_i tcp_T_board``. Written with the inverted robot
poses ``G'_i = inv(base_T_tcp_i)`` this is ``inv(X) inv(G'_i) W``, the eye-in-hand model of
:func:`~brave6d.calibration.handeye.calibrate_handeye` with ``X = base_T_cam`` and
``W = tcp_T_board``. So every step (PnP per view, the conditioning gate, the closed forms, the
joint refinement, the uncertainty, the refusal) runs unchanged on the inverted poses; the
motions' axes and the 1-sigma then refer to the base frame. One difference: the refinement's
per-view robot pose corrections act on the inverted pose, i.e. in the base frame rather than
the TCP frame (a rotation about the base origin); the robot noise level is re-estimated from
the data either way.

:class:`EyeToHandResult` names the two transforms for what they are (``base_T_cam``,
``tcp_T_board``) and writes ``handeye.json`` with ``"setup": "eye-to-hand"`` and ``base_T_cam``
(never ``tcp_T_cam``, which the capture pipeline would take for a camera on the tool) through
:func:`brave6d.core.calibration_io.write_eye_to_hand_file`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.atomic import read_json_as
from brave6d.core.calibration_io import write_eye_to_hand_file
from brave6d.core.errors import DataError
from brave6d.core.transforms import check_rigid, invert
from brave6d.calibration.handeye import HandEyeOptions, HandEyeView, solve_handeye
from brave6d.calibration.handeye_result import SCHEMA, HandEyeResult
from brave6d.calibration.intrinsics_covariance import IntrinsicsCovariance

__all__ = ["EYE_TO_HAND_SCHEMA", "EyeToHandResult", "calibrate_eye_to_hand"]

EYE_TO_HAND_SCHEMA = "brave6d.eye_to_hand/1"
Array = NDArray[np.float64]
#: JSON keys of the inverted problem's solution -> what they are for a static camera.
_RENAMED = {"tcp_T_cam": "base_T_cam", "base_T_board": "tcp_T_board"}


def _rename(obj: Any, names: Mapping[str, str]) -> Any:
    if isinstance(obj, dict):
        return {names.get(k, k): _rename(v, names) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_rename(v, names) for v in obj]
    return obj


@dataclass(frozen=True)
class EyeToHandResult:
    """An eye-to-hand calibration. ``solution`` is the eye-in-hand result of the inverted problem
    (see the module docstring): its ``tcp_T_cam`` is ``base_T_cam``, its ``base_T_board`` is
    ``tcp_T_board``, its uncertainty refers to the base frame; use the names below."""

    solution: HandEyeResult

    setup = "eye-to-hand"

    @property
    def base_T_cam(self) -> Array:
        """The static camera's pose in the robot base frame."""
        return self.solution.tcp_T_cam

    @property
    def tcp_T_board(self) -> Array:
        """The board's pose on the tool."""
        return self.solution.base_T_board

    def camera_pose(self, base_T_tcp: ArrayLike | None = None) -> Array:
        """``base_T_cam`` (the same for every robot pose: the camera is static)."""
        return self.base_T_cam

    def errors_against(self, base_T_cam_true: ArrayLike) -> dict[str, tuple[float, float]]:
        """``{method: (translation error mm, rotation error deg)}`` against a known ``base_T_cam``."""
        return self.solution.errors_against(base_T_cam_true)

    def to_json(self) -> dict[str, Any]:
        body = _rename(self.solution.to_json(), _RENAMED)
        body.pop("schema")
        return {"schema": EYE_TO_HAND_SCHEMA, "setup": self.setup, **body}

    @staticmethod
    def from_json(d: dict[str, Any]) -> EyeToHandResult:
        if not isinstance(d, dict) or d.get("schema") != EYE_TO_HAND_SCHEMA:
            got = d.get("schema") if isinstance(d, dict) else type(d).__name__
            raise DataError(f"eye-to-hand result: expected schema {EYE_TO_HAND_SCHEMA!r}, got {got!r}")
        body = _rename({k: v for k, v in d.items() if k not in ("schema", "setup")},
                       {v: k for k, v in _RENAMED.items()})
        return EyeToHandResult(HandEyeResult.from_json({"schema": SCHEMA, **body}))

    def save(self, path: Path | str, **extra: Any) -> Path:
        """Write :meth:`to_json` (plus ``extra`` keys) through the hand-eye file's one writer."""
        details = {**self.to_json(), **extra}
        details.pop("base_T_cam")
        return write_eye_to_hand_file(path, self.base_T_cam, **details)

    @staticmethod
    def load(path: Path | str) -> EyeToHandResult:
        """Read a file written by :meth:`save`; errors name the file."""
        return read_json_as(path, EyeToHandResult.from_json)


def calibrate_eye_to_hand(
    views: Sequence[HandEyeView],
    object_points: ArrayLike,
    K: ArrayLike,
    dist: ArrayLike = (),
    options: HandEyeOptions | None = None,
    intrinsics_std: Mapping[str, float] | None = None,
    intrinsics_cov: IntrinsicsCovariance | None = None,
) -> EyeToHandResult:
    """Eye-to-hand calibration: ``views`` carry the robot poses ``base_T_tcp`` as reported (the
    board is on the tool) and the corners the static camera saw; the rest as for
    :func:`~brave6d.calibration.handeye.calibrate_handeye`, whose errors it raises too."""
    inverted = []
    for k, v in enumerate(views):
        G = check_rigid(v.base_T_tcp, f"{v.name or f'view_{k:03d}'}: base_T_tcp")
        inverted.append(replace(v, base_T_tcp=invert(G)))
    return EyeToHandResult(solve_handeye(inverted, object_points, K, dist, options, intrinsics_std, intrinsics_cov,
                                         "eye-to-hand"))

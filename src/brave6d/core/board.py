"""The ChArUco board of a scene spec: OpenCV board object, geometry and texture.

Board frame (OpenCV's convention, checked in the tests): the origin is the outer top-left
corner of the printed pattern, x runs along the image columns (``squares_x`` squares), y
along the image rows (``squares_y`` squares), z = x cross y points *into* the board. A board
lying face-up on a table therefore has its z axis pointing down (``rpy_deg: [180, 0, 0]``).

Both the simulated camera (to texture the board) and calibration (to detect it) use this
module, so the two always agree on where the corners are.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from brave6d.core.aruco_dictionary import aruco_dictionary
from brave6d.core.spec import BoardSpec


def make_charuco_board(spec: BoardSpec) -> cv2.aruco.CharucoBoard:
    """The ``cv2.aruco.CharucoBoard`` described by ``spec`` (its dictionary predefined, custom or from a file)."""
    dictionary = aruco_dictionary(spec.dictionary, spec.dictionary_file)
    board = cv2.aruco.CharucoBoard(
        (spec.squares_x, spec.squares_y), spec.square_length_m, spec.marker_length_m, dictionary
    )
    board.setLegacyPattern(spec.legacy_pattern)
    return board


def board_size_m(spec: BoardSpec) -> tuple[float, float]:
    """Width (x) and height (y) of the pattern in metres."""
    return spec.squares_x * spec.square_length_m, spec.squares_y * spec.square_length_m


def chessboard_corners(spec: BoardSpec) -> NDArray[np.float64]:
    """(M, 3) inner chessboard corners in the board frame; row ``i`` is ChArUco corner id ``i``."""
    return np.asarray(make_charuco_board(spec).getChessboardCorners(), dtype=np.float64).reshape(-1, 3)


def board_image(spec: BoardSpec, px_per_m: float) -> NDArray[np.uint8]:
    """Grey uint8 image of the pattern, no margin, ``px_per_m`` pixels per metre.

    Pixel ``(u, v)`` (centre at integer coordinates) shows board point
    ``((u + 0.5) / px_per_m, (v + 0.5) / px_per_m, 0)``.
    """
    width_m, height_m = board_size_m(spec)
    size = (int(round(width_m * px_per_m)), int(round(height_m * px_per_m)))
    return make_charuco_board(spec).generateImage(size, marginSize=0, borderBits=1)

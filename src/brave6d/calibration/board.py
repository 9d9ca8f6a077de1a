"""ChArUco board for calibration: detection, exact textures with a margin, printable export.

Builds on :mod:`brave6d.core.board` (the OpenCV board object and the corner table), so the
simulated camera, the printout and the detector agree on every corner.

Board frame (OpenCV's): origin at the outer top-left corner of the chessboard pattern, x along
the image columns (``squares_x`` squares), y along the image rows (``squares_y`` squares),
z = x cross y pointing *into* the board, away from the printed face. A camera that looks at the
printed face with the board upright in its image has ``cam_R_board = I``.

Texture convention (:class:`BoardTexture`): pixel ``(u, v)`` (column, row; pixel centres at
integer coordinates, as in OpenCV) shows the board point
``X = (u + 0.5) / px_per_m - margin_m``, ``Y = (v + 0.5) / px_per_m - margin_m``, ``Z = 0``.
The image's outer top-left edge is the board point ``(-margin_m, -margin_m, 0)``, its outer
bottom-right edge ``(width_m + margin_m, height_m + margin_m, 0)``. A renderer textures the
plane z = 0 of the board frame with that rectangle (u along +x, v along +y), viewed from -z.
"""

from __future__ import annotations

import functools
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from brave6d.core.board import board_size_m, chessboard_corners, make_charuco_board
from brave6d.core.errors import BraveError
from brave6d.core.spec import BoardSpec
from brave6d.calibration.opencv_threads import on_one_opencv_thread

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "BoardTexture",
    "CharucoDetection",
    "board_corner_points",
    "detect_charuco",
    "draw_board_figure",
    "export_board",
    "render_board",
]


class CharucoDetection(NamedTuple):
    """ChArUco corners found in one image; both arrays are empty (never None) when none are.

    ``corner_ids``: (N,) int32 ids, row ``i`` of :func:`board_corner_points`;
    ``corners_px``: (N, 2) float64 pixel positions (OpenCV convention: pixel centres at integers).
    """

    corner_ids: NDArray[np.int32]
    corners_px: NDArray[np.float64]

    @property
    def count(self) -> int:
        """Number of corners found."""
        return len(self.corner_ids)

    @staticmethod
    def empty() -> CharucoDetection:
        """A detection with no corners."""
        return CharucoDetection(np.zeros(0, np.int32), np.zeros((0, 2), np.float64))


def board_corner_points(spec: BoardSpec) -> NDArray[np.float64]:
    """(M, 3) ChArUco (inner chessboard) corners in the board frame, metres; row i = corner id i."""
    return chessboard_corners(spec)


@functools.lru_cache(maxsize=8)
def _detector(spec: BoardSpec) -> cv2.aruco.CharucoDetector:
    # One detector per board; a detector holds its own copy of the board and its parameters.
    return cv2.aruco.CharucoDetector(make_charuco_board(spec))


@on_one_opencv_thread
def detect_charuco(image: NDArray[np.uint8], spec: BoardSpec) -> CharucoDetection:
    """ChArUco corners of ``spec``'s board in an 8-bit grey, RGB or RGBA image.

    Corners are interpolated from the detected markers and refined to sub-pixel accuracy by
    OpenCV. Returns empty arrays when no board (or too few markers) is visible.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise BraveError(f"detect_charuco: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2GRAY)
    elif img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    elif img.ndim != 2:
        raise BraveError(f"detect_charuco: expected an (H, W) or (H, W, 3|4) image, got shape {img.shape}")
    corners, ids, _, _ = _detector(spec).detectBoard(np.ascontiguousarray(img))
    if ids is None or corners is None or len(ids) == 0:
        return CharucoDetection.empty()
    return CharucoDetection(
        np.asarray(ids, dtype=np.int32).reshape(-1), np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    )


# ----------------------------------------------------------------------------- textures
@dataclass(frozen=True)
class BoardTexture:
    """A rendered board image and the exact map between its pixels and the board frame.

    ``px_per_m`` is the effective scale: the requested one rounded so that one square is a
    whole number of pixels (chessboard corners then fall exactly on pixel edges).
    """

    image: NDArray[np.uint8]
    px_per_m: float
    margin_m: float

    @property
    def pixel_to_board(self) -> NDArray[np.float64]:
        """3x3 affine map: ``(X, Y, 1) = A @ (u, v, 1)`` from pixel centres to board metres."""
        s = 1.0 / self.px_per_m
        off = 0.5 * s - self.margin_m
        return np.array([[s, 0.0, off], [0.0, s, off], [0.0, 0.0, 1.0]])

    @property
    def board_to_pixel(self) -> NDArray[np.float64]:
        """3x3 affine map from board metres ``(X, Y, 1)`` to pixel coordinates ``(u, v, 1)``."""
        return np.linalg.inv(self.pixel_to_board)


def render_board(spec: BoardSpec, px_per_m: float, margin_m: float = 0.0) -> BoardTexture:
    """Grey uint8 image of the board at ``px_per_m`` (rounded, see :class:`BoardTexture`),
    with a white margin of ``margin_m`` (rounded to whole pixels) on every side."""
    if not np.isfinite(px_per_m) or px_per_m <= 0:
        raise BraveError(f"render_board: px_per_m must be positive, got {px_per_m}")
    if not np.isfinite(margin_m) or margin_m < 0:
        raise BraveError(f"render_board: margin_m must be >= 0, got {margin_m}")
    square_px = int(np.rint(spec.square_length_m * px_per_m))
    if square_px < 2 * (_marker_bits(spec) + 2):
        raise BraveError(
            f"render_board: {px_per_m:.0f} px/m gives {square_px} px per square, too few to draw "
            f"the markers; use at least {2 * (_marker_bits(spec) + 2) / spec.square_length_m:.0f} px/m"
        )
    eff = square_px / spec.square_length_m
    margin_px = int(np.rint(margin_m * eff))
    size = (spec.squares_x * square_px + 2 * margin_px, spec.squares_y * square_px + 2 * margin_px)
    image = make_charuco_board(spec).generateImage(size, marginSize=margin_px, borderBits=1)
    return BoardTexture(np.ascontiguousarray(image, dtype=np.uint8), eff, margin_px / eff)


def _marker_bits(spec: BoardSpec) -> int:
    return int(make_charuco_board(spec).getDictionary().markerSize)


# ----------------------------------------------------------------------------- printable export
def _black_cells(spec: BoardSpec) -> list[tuple[float, float, float, float]]:
    """Black rectangles ``(x, y, w, h)`` in board metres (y down): squares and marker bits."""
    board = make_charuco_board(spec)
    sq = spec.square_length_m
    obj = [np.asarray(p, dtype=np.float64).reshape(4, 3) for p in board.getObjPoints()]
    ids = np.asarray(board.getIds()).reshape(-1)
    dictionary = board.getDictionary()
    bits = int(dictionary.markerSize) + 2
    white = {(int(p[:, 0].mean() // sq), int(p[:, 1].mean() // sq)) for p in obj}
    cells = [
        (ix * sq, iy * sq, sq, sq)
        for iy in range(spec.squares_y)
        for ix in range(spec.squares_x)
        if (ix, iy) not in white
    ]
    for corners, marker_id in zip(obj, ids, strict=True):
        x0, y0 = corners[:, 0].min(), corners[:, 1].min()
        cell = (corners[:, 0].max() - x0) / bits
        pattern = cv2.aruco.generateImageMarker(dictionary, int(marker_id), bits, borderBits=1)
        for r in range(bits):  # merge runs of black bits along each row
            c = 0
            while c < bits:
                if pattern[r, c] < 128:
                    start = c
                    while c < bits and pattern[r, c] < 128:
                        c += 1
                    cells.append((x0 + start * cell, y0 + r * cell, (c - start) * cell, cell))
                else:
                    c += 1
    return cells


_LABEL_PT = 6.0  # label font size
_LINE_M = _LABEL_PT * 1.35 / 72 * 0.0254  # line height on paper, metres


def board_label_lines(spec: BoardSpec, width_m: float, height_m: float, chars_per_line: int) -> list[str]:
    legacy = "yes" if spec.legacy_pattern else "no"
    text = (
        f"ChArUco {spec.squares_x} x {spec.squares_y} squares, square {spec.square_length_m * 1000:.2f} mm, "
        f"marker {spec.marker_length_m * 1000:.2f} mm, {spec.dictionary_label}, legacy pattern: {legacy}. "
        f"Pattern {width_m * 1000:.1f} x {height_m * 1000:.1f} mm. Print at 100 % (no fit-to-page) and "
        "measure the bar. Board frame: origin at the top-left outer corner, x right, y down."
    )
    return textwrap.wrap(text, max(chars_per_line, 20))


def draw_board_figure(spec: BoardSpec, margin_m: float = 0.015, label: bool = True) -> Figure:
    """A matplotlib Figure of the board at true physical size (figure inches = metres / 0.0254).

    The pattern is vector graphics (one filled path), so a PDF prints exactly at any
    resolution; below it the label names the board and its dimensions next to a check bar
    (50 mm, or 20 mm on small boards), wrapped to the page width.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import PathPatch, Rectangle
    from matplotlib.path import Path as MplPath

    width_m, height_m = board_size_m(spec)
    bar = 0.05 if width_m >= 0.12 else 0.02
    text_w = width_m + margin_m - bar - 0.006
    lines = board_label_lines(spec, width_m, height_m, int(text_w / (0.55 * _LABEL_PT / 72 * 0.0254))) if label else []
    text_m = len(lines) * _LINE_M + 0.004 if label else 0.0
    fig_w, fig_h = width_m + 2 * margin_m, height_m + 2 * margin_m + text_m
    fig = Figure(figsize=(fig_w / 0.0254, fig_h / 0.0254))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(-margin_m, width_m + margin_m)
    ax.set_ylim(height_m + margin_m + text_m, -margin_m)  # y down, as in the board frame
    ax.set_axis_off()
    verts: list[tuple[float, float]] = []
    codes: list[int] = []
    for x, y, w, h in _black_cells(spec):
        verts += [(x, y), (x + w, y), (x + w, y + h), (x, y + h), (x, y)]
        codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY]
    ax.add_patch(PathPatch(MplPath(verts, codes), facecolor="black", edgecolor="none", linewidth=0))
    if label:
        y_text = height_m + 0.5 * margin_m
        ax.add_patch(Rectangle((0.0, y_text), bar, 0.0015, facecolor="black", edgecolor="none"))
        ax.text(0.0, y_text + 0.003, f"{bar * 1000:.0f} mm", fontsize=_LABEL_PT + 1, va="top", ha="left")
        ax.text(bar + 0.006, y_text - 0.0005, "\n".join(lines), fontsize=_LABEL_PT, va="top", ha="left",
                linespacing=1.2)
    return fig


def export_board(spec: BoardSpec, path: Path | str, margin_m: float = 0.015, dpi: int = 600) -> Path:
    """Write the printable board at true scale; the suffix picks the format (.pdf, .png, .svg).

    PDF/SVG pages measure exactly the pattern plus margins; a PNG is rasterised at ``dpi``
    and carries that resolution in its metadata, so printing it at 100 % is true scale too.
    """
    import io

    from brave6d.core.atomic import atomic_write_bytes

    target = Path(path)
    fmt = target.suffix.lower().lstrip(".")
    if fmt not in ("pdf", "png", "svg"):
        raise BraveError(f"export_board: unsupported format {target.suffix!r} (use .pdf, .png or .svg)")
    fig = draw_board_figure(spec, margin_m=margin_m)
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=dpi)
    return atomic_write_bytes(target, buf.getvalue())

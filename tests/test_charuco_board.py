"""ChArUco board: texture geometry, detection, printable export."""

from __future__ import annotations

import io
import re

import cv2
import numpy as np
import pytest

from brave6d.core.board import board_size_m
from brave6d.core.errors import BraveError
from brave6d.core.spec import BoardSpec
from brave6d.calibration.board import (
    BoardTexture,
    CharucoDetection,
    board_corner_points,
    detect_charuco,
    draw_board_figure,
    export_board,
    render_board,
)

SPEC = BoardSpec()  # 7 x 5 squares of 30 mm, 22 mm markers, DICT_5X5_100


def _pixels_of(texture: BoardTexture, points: np.ndarray) -> np.ndarray:
    h = np.c_[points[:, :2], np.ones(len(points))]
    return (texture.board_to_pixel @ h.T).T[:, :2]


@pytest.mark.parametrize("margin_m", [0.0, 0.012])
def test_texture_corners_are_where_the_documented_map_says(margin_m: float) -> None:
    tex = render_board(SPEC, 3000.0, margin_m=margin_m)
    det = detect_charuco(tex.image, SPEC)
    assert det.count == len(board_corner_points(SPEC)) == (SPEC.squares_x - 1) * (SPEC.squares_y - 1)
    expected = _pixels_of(tex, board_corner_points(SPEC)[det.corner_ids])
    assert np.max(np.abs(det.corners_px - expected)) < 0.05


def test_texture_scale_and_margin_are_exact() -> None:
    tex = render_board(SPEC, 3010.0, margin_m=0.01)  # rounded to a whole number of pixels per square
    assert SPEC.square_length_m * tex.px_per_m == pytest.approx(round(SPEC.square_length_m * tex.px_per_m))
    w, h = board_size_m(SPEC)
    assert tex.image.shape == (
        round((h + 2 * tex.margin_m) * tex.px_per_m), round((w + 2 * tex.margin_m) * tex.px_per_m)
    )
    # the map: pixel centre (0, 0) is half a pixel inside the outer edge (-margin, -margin)
    corner = tex.pixel_to_board @ np.array([-0.5, -0.5, 1.0])
    assert corner[:2] == pytest.approx([-tex.margin_m, -tex.margin_m])
    assert tex.board_to_pixel @ tex.pixel_to_board == pytest.approx(np.eye(3))
    # outer squares in the corners are black, the margin is white
    m = int(np.rint(tex.margin_m * tex.px_per_m))
    assert tex.image[m + 3, m + 3] == 0 and tex.image[1, 1] == 255


def test_render_board_rejects_bad_scale() -> None:
    with pytest.raises(BraveError, match="px/m"):
        render_board(SPEC, 100.0)
    with pytest.raises(BraveError, match="margin"):
        render_board(SPEC, 3000.0, margin_m=-0.01)


def test_detect_returns_empty_arrays_without_a_board() -> None:
    det = detect_charuco(np.full((240, 320), 200, np.uint8), SPEC)
    assert isinstance(det, CharucoDetection)
    assert det.corner_ids.shape == (0,) and det.corner_ids.dtype == np.int32
    assert det.corners_px.shape == (0, 2) and det.corners_px.dtype == np.float64
    ids, corners = det  # unpacks as (corner_ids, corners_px)
    assert len(ids) == len(corners) == 0


def test_detect_accepts_rgb_and_partial_boards() -> None:
    tex = render_board(SPEC, 2500.0, margin_m=0.015)
    rgb = np.repeat(tex.image[:, :, None], 3, axis=2)
    assert detect_charuco(rgb, SPEC).count == 24
    half = tex.image.copy()
    half[:, half.shape[1] // 2:] = 255  # right half hidden
    det = detect_charuco(half, SPEC)
    assert 0 < det.count < 24
    expected = _pixels_of(tex, board_corner_points(SPEC)[det.corner_ids])
    assert np.max(np.abs(det.corners_px - expected)) < 0.1


def test_detect_rejects_float_images() -> None:
    with pytest.raises(BraveError, match="8-bit"):
        detect_charuco(np.zeros((10, 10), np.float32), SPEC)


def test_legacy_pattern_board_is_detected_with_its_own_spec() -> None:
    spec = BoardSpec(squares_x=6, squares_y=4, legacy_pattern=True)
    tex = render_board(spec, 2500.0, margin_m=0.015)
    det = detect_charuco(tex.image, spec)
    assert det.count == 15
    expected = _pixels_of(tex, board_corner_points(spec)[det.corner_ids])
    assert np.max(np.abs(det.corners_px - expected)) < 0.05


def test_vector_drawing_matches_the_opencv_board() -> None:
    """The printable (vector) board rasterised at 300 dpi is detected with the right ids/positions."""
    fig = draw_board_figure(SPEC, margin_m=0.015, label=False)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=300)
    img = cv2.imdecode(np.frombuffer(buf.getvalue(), np.uint8), cv2.IMREAD_GRAYSCALE)
    det = detect_charuco(img, SPEC)
    assert det.count == 24
    px_per_m = 300 / 0.0254
    expected = (board_corner_points(SPEC)[det.corner_ids, :2] + 0.015) * px_per_m - 0.5
    # Agg rounds the figure height to whole pixels and anchors the drawing at the bottom.
    expected[:, 1] -= fig.get_figheight() * 300 - img.shape[0]
    assert np.max(np.abs(det.corners_px - expected)) < 0.15  # 0.013 mm on paper


def test_pdf_export_is_true_scale(tmp_path) -> None:
    path = export_board(SPEC, tmp_path / "board.pdf", margin_m=0.015)
    data = path.read_bytes()
    box = [float(v) for v in re.search(rb"MediaBox \[([^\]]*)\]", data).group(1).split()]
    fig = draw_board_figure(SPEC, margin_m=0.015)
    w, h = board_size_m(SPEC)
    # the page is the figure, and the pattern spans exactly width_m of it (1 pt = 1/72 inch)
    assert box[2] - box[0] == pytest.approx((w + 0.03) / 0.0254 * 72, abs=0.01)
    assert box[3] - box[1] == pytest.approx(fig.get_figheight() * 72, abs=0.01)
    assert fig.get_figheight() * 0.0254 > h + 0.03  # room for the label below the pattern


def test_png_export_carries_its_resolution(tmp_path) -> None:
    path = export_board(SPEC, tmp_path / "board.png", dpi=150)
    data = path.read_bytes()
    i = data.index(b"pHYs")
    ppm_x = int.from_bytes(data[i + 4:i + 8], "big")
    assert ppm_x == pytest.approx(150 / 0.0254, abs=1)
    with pytest.raises(BraveError, match="format"):
        export_board(SPEC, tmp_path / "board.jpg")

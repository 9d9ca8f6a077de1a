"""VSD's depth renderer by OpenGL's rules (brave6d.evaluation.metrics.gl_raster).

Coverage against an exact reference (Python integers, the textbook top-left rule) on random
triangles; watertight meshes; degenerate triangles and poses; and bop_toolkit's own renders
(tests/data/bop_toolkit_vispy, vispy on Mesa's llvmpipe): the same pixels and depths.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.evaluation.metrics import DepthRenderer, load_models
from brave6d.evaluation.metrics.gl_raster import bbox_corners, gl_depth, triangle_coverage

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "tests" / "data" / "bop_toolkit_vispy" / "renders.npz"
MODELS = ROOT / "data" / "samples" / "blenderproc_train_pbr" / "models"
W, H = 24, 16


def _snap(v: float) -> int:
    """llvmpipe's sub-pixel snap: (v - 0.5) * 256 in float32, rounded to nearest even."""
    return int(np.rint(np.float32(np.float32(v) - np.float32(0.5)) * np.float32(256)))


def _reference_coverage(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """Exact top-left rule (y grows downwards, as the framebuffer rows) on the snapped vertices."""
    pts = [(_snap(x), _snap(y)) for x, y in xy]

    def cross(o, a, b) -> int:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    area = cross(*pts)
    out = np.zeros((height, width), dtype=bool)
    if area == 0:
        return out
    s = 1 if area > 0 else -1
    edges = [(pts[0], pts[1], pts[2]), (pts[1], pts[2], pts[0]), (pts[2], pts[0], pts[1])]
    for row in range(height):
        for col in range(width):
            p = (col * 256, row * 256)
            inside = True
            for a, b, c in edges:
                e = cross(a, b, p) * s
                if e > 0:
                    continue
                if e < 0:
                    inside = False
                    break
                if a[1] == b[1]:  # horizontal: a top edge when the triangle lies below it
                    top_left = c[1] > a[1]
                else:  # a left edge when the inside lies towards +x
                    top_left = cross(a, b, (a[0] + 1, a[1])) * s > 0
                if not top_left:
                    inside = False
                    break
            out[row, col] = inside
    return out


# Coordinates on a coarse grid hit pixel centres and shared edges exactly (the fill rule's
# cases); free floats test the snapping.
_coord = st.one_of(st.integers(-8, 2 * 32).map(lambda k: k / 2.0),
                   st.floats(-4.0, 30.0, allow_nan=False, width=32))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(_coord, _coord), min_size=3, max_size=3))
def test_coverage_is_the_top_left_rule_on_snapped_vertices(tri):
    xy = np.array(tri, dtype=np.float64)
    np.testing.assert_array_equal(triangle_coverage(xy, W, H), _reference_coverage(xy, W, H))


def test_fill_rule_cases_by_hand():
    # A 4 x 4 px square's two triangles, corners on pixel centres (x + 0.5): the left and top
    # edges' centres are in, the right and bottom ones out; each pixel once.
    a, b = (2.5, 3.5), (6.5, 3.5)
    c, d = (6.5, 7.5), (2.5, 7.5)
    t1 = triangle_coverage(np.array([a, b, c]), W, H)
    t2 = triangle_coverage(np.array([a, c, d]), W, H)
    assert not (t1 & t2).any()
    expect = np.zeros((H, W), dtype=bool)
    expect[3:7, 2:6] = True
    np.testing.assert_array_equal(t1 | t2, expect)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(2.0, 7.0), st.sampled_from([0.0, 0.2]))
def test_shared_edges_cover_each_pixel_once(seed, cell, jitter):
    rng = np.random.default_rng(seed)
    nx, ny = int(np.ceil((W + 8) / cell)) + 1, int(np.ceil((H + 8) / cell)) + 1
    gx, gy = np.meshgrid(np.arange(nx) * cell - 4.0, np.arange(ny) * cell - 4.0)
    gx = gx + rng.uniform(-jitter, jitter, gx.shape) * cell
    gy = gy + rng.uniform(-jitter, jitter, gy.shape) * cell
    count = np.zeros((H, W), dtype=np.int64)
    for j in range(ny - 1):
        for i in range(nx - 1):
            q = [(gx[j, i], gy[j, i]), (gx[j, i + 1], gy[j, i + 1]), (gx[j + 1, i + 1], gy[j + 1, i + 1]),
                 (gx[j + 1, i], gy[j + 1, i])]
            tris = ([q[0], q[1], q[2]], [q[0], q[2], q[3]]) if rng.random() < 0.5 else \
                ([q[0], q[1], q[3]], [q[1], q[2], q[3]])
            for t in tris:
                order = rng.permutation(3)  # either winding
                count += triangle_coverage(np.array(t)[order], W, H)
    np.testing.assert_array_equal(count, np.ones((H, W), dtype=np.int64))


K = np.array([[200.0, 0.0, 11.5], [0.0, 200.0, 7.5], [0.0, 0.0, 1.0]])


def _render(v, f, R=np.eye(3), t=(0.0, 0.0, 0.0)):
    v = np.asarray(v, dtype=np.float64)
    return gl_depth(v, np.asarray(f), bbox_corners(v), np.asarray(R, float), np.asarray(t, float), K, W, H)


def test_degenerate_triangles_draw_nothing_or_one_pixel():
    f = [[0, 1, 2]]
    assert not _render([[0, 0, 100], [5, 5, 100], [10, 10, 100]], f).any()  # zero area
    assert not _render([[0, 0, -100], [5, 0, -100], [0, 5, -100]], f).any()  # behind the camera
    assert not _render([[0, 0, 0], [5, 0, 0], [0, 5, 0]], f).any()  # in the camera plane
    tiny = _render([[0, 0, 100], [0.01, 0, 100], [0, 0.01, 100]], f)  # 0.02 px
    assert (tiny > 0).sum() <= 1
    big = _render([[-1e5, -1e5, 100], [1e5, -1e5, 100], [0, 1e5, 100]], f)  # 2e5 px across
    assert (big > 0).all()
    np.testing.assert_allclose(big, 100.0, rtol=1e-5)
    # 4e12 px across: float32 clipping cannot place its edges (nor can GL's), but what it draws is finite and on it
    huge = _render([[-1e12, -1e12, 100], [1e12, -1e12, 100], [0, 1e12, 100]], f)
    assert np.isfinite(huge).all()
    np.testing.assert_allclose(huge[huge > 0], 100.0, rtol=1e-5)
    # half behind the camera: only what lies in front is drawn, at depths in front
    # the plane z = 50 + y / 2, two corners behind the camera: only what lies in front is drawn,
    # the image centre's pixels at about 50 mm
    half = _render([[-1000, -200, -50], [1000, -200, -50], [0, 600, 350]], f)
    assert np.isfinite(half).all() and (half > 0).all() and half.max() <= 350.0
    np.testing.assert_allclose(half[7:9, 11:13], 50.0, atol=0.2)


_xyz = st.floats(-300.0, 300.0, allow_nan=False, allow_infinity=False)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(_xyz, _xyz, _xyz), min_size=3, max_size=7),
       st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6), st.integers(0, 6)), min_size=1, max_size=8),
       st.tuples(_xyz, _xyz, st.floats(-400.0, 600.0)))
def test_any_mesh_and_pose_gives_finite_depths_within_the_mesh(verts, faces, t):
    v = np.array(verts)
    f = np.array([[a % len(v), b % len(v), c % len(v)] for a, b, c in faces])
    d = _render(v, f, t=t)
    assert d.shape == (H, W) and np.isfinite(d).all() and (d >= 0).all()
    z = v[:, 2] + t[2]
    if (z <= 0).all():
        assert not d.any()
    drawn = d[d > 0]
    if drawn.size:  # a drawn depth lies on the mesh: between its nearest (clipped) and farthest points
        span = z.max() - max(z.min(), 0.0)
        assert drawn.max() <= z.max() + 1e-4 * span + 1e-5 * z.max()
        assert drawn.min() >= max(z.min(), 0.0) - 1e-4 * span - 1e-5 * z.max()


def test_renders_equal_bop_toolkits_own():  # the reference ships with the tests: missing is a failure
    ref = np.load(REFERENCE)
    w, h = int(ref["width"]), int(ref["height"])
    ids = sorted({int(ref[f"obj_id_{i}"]) for i in range(len(ref["index"]))})
    models = load_models(MODELS, ids)
    renderer = DepthRenderer()
    for o in ids:
        renderer.add_object(o, models[o].points, models[o].faces)
    for i in range(len(ref["index"])):
        cam_K = ref[f"cam_K_{i}"]
        K_project = cam_K.copy()
        K_project[0, 2] -= 0.5
        K_project[1, 2] -= 0.5
        d = renderer.render(int(ref[f"obj_id_{i}"]), ref[f"R_{i}"], ref[f"t_{i}"], K_project, w, h)
        expect = np.zeros(w * h)
        expect[ref[f"pixels_{i}"]] = ref[f"depth_{i}"]
        np.testing.assert_array_equal(np.flatnonzero(d), ref[f"pixels_{i}"], err_msg=f"render {i}: pixels")
        np.testing.assert_array_equal(d.ravel(), expect, err_msg=f"render {i}: depths")

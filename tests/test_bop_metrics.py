"""BOP pose errors (VSD, MSSD, MSPD), symmetry sets and the depth renderer, on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.evaluation.metrics.bop_metrics import (
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VSD_TAUS,
    VSD_THRESHOLDS,
    as_symmetries,
    depth_to_distance,
    estimate_visib_mask_est,
    estimate_visib_mask_gt,
    mspd,
    mspd_normalized,
    mssd,
    overlapping_sphere_projections,
    symmetry_transformations,
    vsd,
    vsd_from_depths,
)
from brave6d.evaluation.metrics.depth_renderer import DepthRenderer, render_depth

W, H = 640, 480
K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
I3 = np.eye(3)


def rot_z(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


def flat4(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> list[float]:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T.reshape(-1).tolist()


@pytest.fixture(scope="module")
def nut() -> trimesh.Trimesh:
    """Hexagonal prism (nut-like): circumradius 10 mm, height 8 mm, centred; 60 deg symmetric."""
    return trimesh.creation.cylinder(radius=10.0, height=8.0, sections=6)


@pytest.fixture(scope="module")
def nut_syms():
    return symmetry_transformations({"symmetries_discrete": [flat4(rot_z(60 * k)) for k in range(1, 6)]})


@pytest.fixture(scope="module")
def cylinder() -> trimesh.Trimesh:
    """Cylinder r = 20 mm, h = 40 mm along z, centred (diameter sqrt(40^2 + 40^2) = 56.6 mm)."""
    return trimesh.creation.cylinder(radius=20.0, height=40.0, sections=96)


@pytest.fixture(scope="module")
def renderer(nut, cylinder) -> DepthRenderer:
    r = DepthRenderer()
    r.add_object(1, nut.vertices, nut.faces)
    r.add_object(2, cylinder.vertices, cylinder.faces)
    box = trimesh.creation.box(extents=(40.0, 40.0, 40.0))
    r.add_object(3, box.vertices, box.faces)
    return r


# ----------------------------------------------------------------------------- constants
def test_bop19_threshold_lists():
    assert len(VSD_TAUS) == len(VSD_THRESHOLDS) == len(MSSD_THRESHOLDS) == len(MSPD_THRESHOLDS) == 10
    np.testing.assert_allclose(VSD_TAUS, np.linspace(0.05, 0.5, 10))
    np.testing.assert_allclose(MSSD_THRESHOLDS, np.linspace(0.05, 0.5, 10))
    np.testing.assert_allclose(MSPD_THRESHOLDS, np.arange(5, 55, 5))


# ----------------------------------------------------------------------------- symmetries
def test_symmetry_set_identity_first_and_counts(nut_syms):
    assert len(nut_syms) == 6
    np.testing.assert_array_equal(nut_syms.R[0], I3)
    np.testing.assert_array_equal(nut_syms.t[0], 0)
    cont = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    assert len(symmetry_transformations(cont)) == math.ceil(math.pi / 0.01) == 315
    assert len(symmetry_transformations(cont, max_sym_disc_step=0.05)) == 63
    both = {**cont, "symmetries_discrete": [flat4(Rotation.from_euler("x", 180, degrees=True).as_matrix())]}
    s = symmetry_transformations(both)
    assert len(s) == 2 * 315
    # All are proper rotations.
    np.testing.assert_allclose(np.linalg.det(s.R), 1.0, atol=1e-12)
    assert len(symmetry_transformations({})) == 1


def test_declared_symmetries_map_the_nut_onto_itself(nut, nut_syms):
    v = np.asarray(nut.vertices)
    for R, t in zip(nut_syms.R, nut_syms.t):
        moved = v @ R.T + t
        d = np.min(np.linalg.norm(moved[:, None] - v[None], axis=2), axis=1)
        assert d.max() < 1e-9


def test_continuous_symmetry_with_offset_keeps_the_axis():
    # Axis along z through (5, 0, 0): the point (5, 0, 7) is on the axis and must stay fixed.
    s = symmetry_transformations({"symmetries_continuous": [{"axis": [0, 0, 2], "offset": [5, 0, 0]}]})
    p = np.array([5.0, 0.0, 7.0])
    np.testing.assert_allclose(p @ s.R.transpose(0, 2, 1) + s.t, np.broadcast_to(p, (len(s), 3)), atol=1e-12)


def test_as_symmetries_accepts_bop_toolkit_dicts():
    s = as_symmetries([{"R": I3, "t": np.zeros((3, 1))}, {"R": rot_z(90), "t": [1, 2, 3]}])
    assert len(s) == 2 and s.t.shape == (2, 3)
    assert len(as_symmetries(None)) == 1


def test_bad_symmetry_entries_raise():
    with pytest.raises(ValueError, match="symmetries_discrete"):
        symmetry_transformations({"symmetries_discrete": [[1, 0, 0]]})
    with pytest.raises(ValueError, match="axis"):
        symmetry_transformations({"symmetries_continuous": [{"axis": [0, 0, 0], "offset": [0, 0, 0]}]})


# ----------------------------------------------------------------------------- MSSD / MSPD
def test_exact_pose_has_zero_errors(nut, nut_syms):
    R = Rotation.from_euler("xyz", [20, -30, 45], degrees=True).as_matrix()
    t = np.array([10.0, -5.0, 400.0])
    assert mssd(R, t, R, t, nut.vertices, nut_syms) == pytest.approx(0.0, abs=1e-9)
    assert mspd(R, t, R, t, K, nut.vertices, nut_syms) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("dt", [(3.0, 4.0, 0.0), (0.0, 0.0, -7.5), (1.0, -2.0, 2.0)])
def test_mssd_of_a_translation_is_its_length(nut, dt):
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    t = np.array([0.0, 0.0, 500.0])
    assert mssd(R, t + dt, R, t, nut.vertices) == pytest.approx(float(np.linalg.norm(dt)), rel=1e-12)


def test_mspd_of_a_lateral_translation_of_a_plate():
    # A square plate facing the camera at z = 500 mm: every point moves by f * |d| / z pixels.
    g = np.linspace(-20, 20, 9)
    pts = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    pts = np.hstack([pts, np.zeros((len(pts), 1))])
    t = np.array([0.0, 0.0, 500.0])
    d = np.array([3.0, 4.0, 0.0])
    err = mspd(I3, t + d, I3, t, K, pts)
    assert err == pytest.approx(600.0 * 5.0 / 500.0, rel=1e-12)  # 6 px
    assert mspd_normalized(err, 640) == pytest.approx(6.0)
    assert mspd_normalized(err, 1280) == pytest.approx(3.0)  # scaled to a 640 px wide image


def test_mspd_uses_the_nearest_points_for_a_3d_object(cylinder):
    # Lateral shift of a cylinder facing the camera: the maximum is at its near cap (z = 480 mm).
    t = np.array([0.0, 0.0, 500.0])
    err = mspd(I3, t + [5.0, 0.0, 0.0], I3, t, K, cylinder.vertices)
    assert err == pytest.approx(600.0 * 5.0 / 480.0, rel=1e-9)


def test_rotation_by_a_declared_discrete_symmetry_scores_zero(nut, nut_syms):
    Rg = Rotation.from_euler("xyz", [30, 10, -20], degrees=True).as_matrix()
    t = np.array([5.0, 5.0, 450.0])
    Re = Rg @ rot_z(120)  # rotate the model by its 120 deg symmetry
    assert mssd(Re, t, Rg, t, nut.vertices, nut_syms) < 1e-9
    assert mspd(Re, t, Rg, t, K, nut.vertices, nut_syms) < 1e-9
    # Without symmetries the same pose is far off: vertices move 2 r sin(60 deg) = 17.3 mm.
    assert mssd(Re, t, Rg, t, nut.vertices) == pytest.approx(2 * 10 * math.sin(math.radians(60)), rel=1e-9)
    # A rotation that is not a symmetry (30 deg) keeps an error of 2 r sin(15 deg).
    assert mssd(Rg @ rot_z(30), t, Rg, t, nut.vertices, nut_syms) == pytest.approx(20 * math.sin(math.radians(15)), rel=1e-9)


def test_rotation_about_a_continuous_symmetry_axis_scores_about_zero(cylinder):
    syms = symmetry_transformations({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]})
    Rg = Rotation.from_euler("xy", [40, 25], degrees=True).as_matrix()
    t = np.array([0.0, 10.0, 600.0])
    for angle in (37.0, 123.4, 271.0):
        e = mssd(Rg @ rot_z(angle), t, Rg, t, cylinder.vertices, syms)
        # The discretisation leaves at most half a step: r * (2 pi / 315) / 2 = 0.2 mm.
        assert e < 20.0 * math.pi / 315 + 1e-9
        assert mspd(Rg @ rot_z(angle), t, Rg, t, K, cylinder.vertices, syms) < 1.0
    assert mssd(Rg @ rot_z(90.0), t, Rg, t, cylinder.vertices) > 20.0


def test_bad_inputs_do_not_produce_nan(nut):
    t = np.array([0.0, 0.0, 500.0])
    # Points on the camera plane (z = 0): finite, not NaN.
    e = mspd(I3, [0.0, 0.0, 0.0], I3, t, K, nut.vertices)
    assert math.isfinite(e) and e > 0
    assert mssd(np.full((3, 3), np.nan), t, I3, t, nut.vertices) == math.inf
    assert mspd(I3, [np.inf, 0, 0], I3, t, K, nut.vertices) == math.inf
    with pytest.raises(ValueError):
        mssd(I3, t, I3, t, np.empty((0, 3)))


# ----------------------------------------------------------------------------- visibility, VSD
def test_visibility_masks_bop19_by_hand():
    d_test = np.array([[0.0, 100.0, 100.0, 50.0, 100.0]])
    d_gt = np.array([[100.0, 110.0, 120.0, 100.0, 0.0]])
    np.testing.assert_array_equal(estimate_visib_mask_gt(d_test, d_gt, 15.0), [[True, True, False, False, False]])
    np.testing.assert_array_equal(estimate_visib_mask_gt(d_test, d_gt, 15.0, "bop18"), [[False, True, False, False, False]])
    # The estimate is 40 mm behind the surface at pixel 1, but inside the GT-visible area: visible.
    d_est = np.array([[0.0, 140.0, 140.0, 0.0, 100.0]])
    visib_gt = estimate_visib_mask_gt(d_test, d_gt, 15.0)
    np.testing.assert_array_equal(estimate_visib_mask_est(d_test, d_est, visib_gt, 15.0), [[False, True, False, False, True]])


def test_vsd_from_depths_by_hand():
    # A huge focal length makes distance == depth; 1 x 5 image.
    Kbig = np.array([[1e9, 0.0, 0.0], [0.0, 1e9, 0.0], [0.0, 0.0, 1.0]])
    d_test = np.array([[100.0, 100.0, 100.0, 100.0, 0.0]])
    d_gt = np.array([[100.0, 100.0, 100.0, 0.0, 0.0]])
    d_est = np.array([[100.0, 105.0, 0.0, 100.0, 0.0]])
    # visib_gt = {0,1,2}, visib_est = {0,1,3}: union 4, intersection {0,1} with distances 0, 5 mm.
    errs = vsd_from_depths(d_est, d_gt, d_test, Kbig, 15.0, [0.05, 0.15, 0.5], True, 50.0)
    np.testing.assert_allclose(errs, [3 / 4, 2 / 4, 2 / 4])
    # Step cost: a distance equal to tau counts as wrong (dist >= tau).
    errs_mm = vsd_from_depths(d_est, d_gt, d_test, Kbig, 15.0, [4.0, 5.0, 6.0], False, 50.0)
    np.testing.assert_allclose(errs_mm, [3 / 4, 3 / 4, 2 / 4])
    # Nothing rendered: union empty -> 1 for every tau.
    z = np.zeros_like(d_test)
    assert vsd_from_depths(z, z, d_test, Kbig, 15.0, [0.1, 0.2], True, 50.0) == [1.0, 1.0]


def test_depth_to_distance():
    """bop_toolkit's formula on the BOP cam_K (the project's K + 0.5 px): the pixel at the BOP
    principal point (1.5, 1.5) lies between pixels, so pixel (1, 1) is half a pixel off-axis."""
    d = np.full((3, 3), 100.0)
    d[0, 0] = np.nan
    k = np.array([[1.0, 0, 1.0], [0, 1.0, 1.0], [0, 0, 1]])
    dist = depth_to_distance(d, k)
    assert dist[0, 0] == 0.0
    assert dist[1, 1] == pytest.approx(100.0 * math.sqrt(1.5))
    assert dist[1, 2] == pytest.approx(100.0 * math.sqrt(1.5))  # x - cx = +0.5, y - cy = -0.5
    assert dist[2, 2] == pytest.approx(100.0 * math.sqrt(1.5))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 3000.0, width=32), min_size=12, max_size=12),
       st.floats(100.0, 2000.0), st.floats(-50.0, 700.0), st.floats(100.0, 2000.0), st.floats(-50.0, 500.0))
def test_depth_to_distance_is_bop_toolkits_arithmetic_bit_for_bit(depths: list[float], fx: float, cx: float,
                                                                 fy: float, cy: float) -> None:
    """The same float64 operations as bop_toolkit's depth_im_to_dist_im_fast on the BOP cam_K
    (restated here from its source, misc.py): VSD's threshold decisions then fall the same way."""
    d = np.array(depths, dtype=np.float32).reshape(3, 4)
    k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    xs, ys = np.meshgrid(np.arange(4), np.arange(3))
    pre_x = (xs - (cx + 0.5)) / np.float64(fx)
    pre_y = (ys - (cy + 0.5)) / np.float64(fy)
    theirs = np.sqrt(np.multiply(pre_x, d) ** 2 + np.multiply(pre_y, d) ** 2 + d.astype(np.float64) ** 2)
    np.testing.assert_array_equal(depth_to_distance(d, k), theirs)


def _scene_depth(renderer: DepthRenderer, objects, background_mm: float | None = 900.0) -> np.ndarray:
    """Test depth image: the nearest rendered surface of the objects over a background plane."""
    depth = np.full((H, W), np.inf)
    for obj_id, R, t in objects:
        d = renderer.render(obj_id, R, t, K, W, H)
        depth = np.where((d > 0) & (d < depth), d, depth)
    bg = 0.0 if background_mm is None else background_mm
    return np.where(np.isfinite(depth), depth, bg)


def test_vsd_exact_far_and_depth_shifted(renderer, cylinder):
    R = Rotation.from_euler("x", 30, degrees=True).as_matrix()
    t = np.array([10.0, -20.0, 500.0])
    diameter = math.hypot(40.0, 40.0)
    depth = _scene_depth(renderer, [(2, R, t)])
    fn = renderer.render_fn(2, K, W, H)
    assert vsd(R, t, R, t, depth, K, 15.0, VSD_TAUS, True, diameter, fn) == [0.0] * 10
    # Far off in the image: the masks do not intersect -> 1.
    assert vsd(R, t + [150.0, 0.0, 0.0], R, t, depth, K, 15.0, VSD_TAUS, True, diameter, fn) == [1.0] * 10
    # 30 mm deeper (more than delta, more than 0.5 diameter): every pixel is wrong.
    far = vsd(R, t + [0.0, 0.0, 30.0], R, t, depth, K, 15.0, VSD_TAUS, True, diameter, fn)
    assert min(far) > 0.95
    # 10 mm deeper (0.177 diameter): wrong for tau <= 0.15, nearly right for tau >= 0.25.
    mid = vsd(R, t + [0.0, 0.0, 10.0], R, t, depth, K, 15.0, VSD_TAUS, True, diameter, fn)
    assert all(a >= b for a, b in zip(mid, mid[1:]))
    assert min(mid[:3]) > 0.9 and max(mid[4:]) < 0.1


def test_vsd_with_missing_test_depth_and_occlusion(renderer):
    R = I3
    t = np.array([0.0, 0.0, 500.0])
    fn = renderer.render_fn(3, K, W, H)
    # bop19: missing depth (0) counts as visible -> exact pose still 0, a wrong one still wrong.
    zeros = np.zeros((H, W))
    assert vsd(R, t, R, t, zeros, K, 15.0, VSD_TAUS, True, 69.3, fn) == [0.0] * 10
    assert min(vsd(R, t + [0, 0, 40.0], R, t, zeros, K, 15.0, VSD_TAUS, True, 69.3, fn)) > 0.95
    # A plate in front of the left half of the cube: the exact pose stays 0.
    depth = _scene_depth(renderer, [(3, R, t)])
    depth[:, :320] = np.where(depth[:, :320] > 0, 300.0, depth[:, :320])
    assert vsd(R, t, R, t, depth, K, 15.0, VSD_TAUS, True, 69.3, fn) == [0.0] * 10


def test_sphere_projection_overlap():
    assert overlapping_sphere_projections(30.0, [0, 0, 500], [10, 0, 500])
    assert not overlapping_sphere_projections(30.0, [0, 0, 500], [100, 0, 500])
    assert not overlapping_sphere_projections(30.0, [0, 0, 0], [0, 0, 500])


# ----------------------------------------------------------------------------- renderer
def test_render_cube_depth_and_silhouette(renderer):
    t = np.array([0.0, 0.0, 500.0])
    depth = renderer.render(3, I3, t, K, W, H)
    # Front face at z = 480 mm; silhouette = projection of the 40 mm face at 480 mm: 50 px wide.
    assert depth[240, 320] == pytest.approx(480.0, abs=1e-3)
    cols = np.flatnonzero(depth[240] > 0)
    assert cols.size == pytest.approx(50, abs=1)
    assert depth[0, 0] == 0.0
    assert np.all((depth == 0) | (np.abs(depth - 480.0) < 1e-3))


def test_render_partly_outside_and_behind(renderer):
    # Cube at x = 250 mm: its front face spans u = 607..657 px, so the right image edge cuts it;
    # its left side face (x = 230 mm, z = 480..520 mm) starts at u = 319.5 + 600 * 230 / 520 = 584.9.
    d = renderer.render(3, I3, [250.0, 0.0, 500.0], K, W, H)
    cols = np.flatnonzero(d[240] > 0)
    assert cols.max() == W - 1 and 584 <= cols.min() <= 586
    assert not np.any(renderer.render(3, I3, [0.0, 0.0, -500.0], K, W, H))
    # Camera inside the cube: every ray hits the inside of a face in front.
    inside = renderer.render(3, I3, [0.0, 0.0, 5.0], K, 64, 48)
    assert np.all(inside > 0)


def test_render_depth_one_off_matches_renderer(renderer, nut):
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    t = np.array([5.0, 5.0, 300.0])
    np.testing.assert_array_equal(render_depth(nut.vertices, nut.faces, R, t, K, W, H), renderer.render(1, R, t, K, W, H))


# ----------------------------------------------------------------------------- properties
rotations = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1).map(
    lambda q: Rotation.from_quat(q).as_matrix()
)
translations = st.tuples(st.floats(-200, 200), st.floats(-200, 200), st.floats(-300, 1500)).map(np.array)


@given(Re=rotations, te=translations, Rg=rotations, tg=translations)
def test_mssd_mspd_finite_and_nonnegative(nut, nut_syms, Re, te, Rg, tg):
    e1 = mssd(Re, te, Rg, tg, nut.vertices, nut_syms)
    e2 = mspd(Re, te, Rg, tg, K, nut.vertices, nut_syms)
    assert math.isfinite(e1) and e1 >= 0
    assert math.isfinite(e2) and e2 >= 0
    # More symmetries can only lower the error; a centred model's MSSD is at least |dt|.
    e0 = mssd(Re, te, Rg, tg, nut.vertices)
    assert e1 <= e0 + 1e-9
    assert e0 >= float(np.linalg.norm(te - tg)) - 1e-6


@settings(max_examples=25)
@given(Re=rotations, Rg=rotations, dx=st.floats(-80, 80), dz=st.floats(-100, 300))
def test_vsd_in_unit_interval(renderer, Re, Rg, dx, dz):
    tg = np.array([0.0, 0.0, 400.0])
    te = tg + [dx, 0.0, dz]
    depth = _scene_depth(renderer, [(1, Rg, tg)])
    errs = vsd(Re, te, Rg, tg, depth, K, 15.0, VSD_TAUS, True, 21.5, renderer.render_fn(1, K, W, H))
    assert len(errs) == 10
    assert all(math.isfinite(e) and 0.0 <= e <= 1.0 for e in errs)
    assert all(a >= b for a, b in zip(errs, errs[1:]))  # larger tolerance, smaller error

"""Colour in registration (brave6d.evaluation.agents.appearance): the model's colours sampled with
its points, the colour disagreement of a pose (finite and bounded for any input), and the flip
that depth cannot see and colour can: a two-coloured bar on a table, ray cast with Open3D."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from brave6d.core.errors import BraveError
from brave6d.core.transforms import invert, look_at, make_transform
from brave6d.evaluation.agents import RegistrationOptions, perceive, register_model, sample_model
from brave6d.evaluation.agents.appearance import color_disagreement
from brave6d.evaluation.agents.registration import visible_points

K = np.array([[277.0, 0.0, 159.5], [0.0, 277.0, 119.5], [0.0, 0.0, 1.0]])  # 320 x 240
W, H = 320, 240
RED, BLUE, GREY = np.array([200, 30, 30]), np.array([30, 40, 190]), np.array([120, 120, 120])


def two_colour_bar() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 40 x 20 x 12 mm bar resting on z = 0 (mm), red where y > 0 and blue where y < 0: its
    depth is the same after a half turn about z, its colours are swapped."""
    mesh = trimesh.creation.box((40, 20, 12), make_transform(np.eye(3), (0, 0, 6)))
    mesh = mesh.subdivide().subdivide()  # vertices on the y = 0 seam keep the halves apart
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    colors = np.where(mesh.vertices[:, 1:2] > 1e-9, RED, BLUE).astype(np.uint8)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces), colors


def cast(vertices_mm: np.ndarray, faces: np.ndarray, colors: np.ndarray, world_T_obj: np.ndarray,
         world_T_cam: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Depth (m) and RGB (uint8) of the bar on a grey table, ray cast with Open3D, with 0.5 mm depth
    noise and a little colour noise; each pixel takes the colour of the triangle's first vertex."""
    import open3d as o3d

    obj = (vertices_mm / 1000.0) @ world_T_obj[:3, :3].T + world_T_obj[:3, 3]
    table = trimesh.creation.box((0.6, 0.6, 0.01), make_transform(np.eye(3), (0, 0, -0.005)))
    verts = np.vstack([obj, table.vertices]).astype(np.float32)
    tris = np.vstack([faces, np.asarray(table.faces) + len(obj)]).astype(np.uint32)
    face_rgb = np.vstack([colors[faces[:, 0]], np.repeat(GREY[None], len(table.faces), axis=0)])
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris))
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    dirs_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1)
    dirs = dirs_cam @ world_T_cam[:3, :3].T
    origins = np.broadcast_to(world_T_cam[:3, 3], dirs.shape)
    rays = np.concatenate([origins, dirs], -1).reshape(-1, 6).astype(np.float32)
    hit = rc.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().reshape(H, W)  # along dirs, whose camera z is 1: t is the depth
    prim = hit["primitive_ids"].numpy().reshape(H, W)
    ok = np.isfinite(t)
    rng = np.random.default_rng(seed)
    depth = np.where(ok, t + rng.normal(0, 0.0005, t.shape), 0.0).astype(np.float32)
    rgb = np.zeros((H, W, 3))
    rgb[ok] = face_rgb[prim[ok].astype(np.int64)]
    rgb = np.clip(rgb + rng.normal(0, 4.0, rgb.shape), 0, 255).astype(np.uint8)
    return depth, rgb


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(R_a.T @ R_b) - 1) / 2, -1, 1))))


# ----------------------------------------------------------------------------- the model's colours
def test_model_points_carry_the_interpolated_vertex_colours_and_do_not_move() -> None:
    v, f, c = two_colour_bar()
    plain = sample_model(3, v, f, 46.2, 800, seed=1)
    coloured = sample_model(3, v, f, 46.2, 800, seed=1, vertex_colors=c)
    np.testing.assert_array_equal(coloured.points, plain.points)
    assert plain.colors is None and coloured.colors.shape == (800, 3)
    y = coloured.points[:, 1] * 1000.0
    away = np.abs(y) > 5.001  # off the triangles that span the seam (vertices every 5 mm)
    np.testing.assert_allclose(coloured.colors[away & (y > 0)], np.broadcast_to(RED / 255.0, (int((away & (y > 0)).sum()), 3)))
    np.testing.assert_allclose(coloured.colors[away & (y < 0)], np.broadcast_to(BLUE / 255.0, (int((away & (y < 0)).sum()), 3)))
    assert np.all((coloured.colors >= 0) & (coloured.colors <= 1))
    with pytest.raises(BraveError, match="object 3: 2 vertex colours for"):
        sample_model(3, v, f, 46.2, 800, vertex_colors=c[:2])


# ----------------------------------------------------------------------------- the disagreement
def _bar_view(yaw_deg: float, azimuth_deg: float = 200.0, elevation_deg: float = 55.0, distance: float = 0.25):
    v, f, c = two_colour_bar()
    model = sample_model(3, v, f, 46.2, 1500, seed=0, vertex_colors=c)
    world_T_obj = make_transform(Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix(), (0.01, -0.02, 0.0))
    centre = world_T_obj[:3, 3] + np.array([0.0, 0.0, 0.006])
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    world_T_cam = look_at(centre + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                         math.sin(el)]), centre)
    depth, rgb = cast(v, f, c, world_T_obj, world_T_cam)
    return model, world_T_obj, world_T_cam, depth, rgb


def _disagreement(model, cam_T_obj: np.ndarray, visible: np.ndarray, rgb: np.ndarray,  # type: ignore[no-untyped-def]
                  depth: np.ndarray, K: np.ndarray, tol: float) -> float:
    """:func:`color_disagreement` of ``model``'s ``visible`` points under ``cam_T_obj`` (as score_pose calls it)."""
    points = model.points[visible] @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3]
    return color_disagreement(model.colors[visible], points, rgb, depth, K, tol)


def test_the_true_pose_agrees_and_its_half_turn_disagrees() -> None:
    model, world_T_obj, world_T_cam, depth, rgb = _bar_view(30.0)
    cam_T_obj = invert(world_T_cam) @ world_T_obj
    half_turn = cam_T_obj @ make_transform(Rotation.from_euler("z", 180, degrees=True).as_matrix(), (0, 0, 0))
    true = _disagreement(model, cam_T_obj, visible_points(model, cam_T_obj), rgb, depth, K, 0.003)
    flipped = _disagreement(model, half_turn, visible_points(model, half_turn), rgb, depth, K, 0.003)
    assert true < -0.7 and flipped > 0.5, (true, flipped)  # seam triangles and noise blur the halves
    grey = np.full_like(rgb, 90)
    assert _disagreement(model, cam_T_obj, visible_points(model, cam_T_obj), grey, depth, K, 0.003) == 0.0
    floats = rgb.astype(np.float32) / 255.0  # floats in [0, 1] count alike
    assert _disagreement(model, cam_T_obj, visible_points(model, cam_T_obj), floats, depth, K, 0.003) == \
        pytest.approx(true, abs=1e-6)


finite = st.floats(-1e6, 1e6, allow_nan=False)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pose=arrays(np.float64, (3, 4), elements=st.one_of(finite, st.sampled_from([0.0, np.nan, np.inf, 1e300]))),
       image=arrays(np.uint8, (6, 8, 3)),
       depth=arrays(np.float32, (6, 8), elements=st.one_of(st.floats(0, 5, width=32),
                                                           st.sampled_from([np.nan, np.inf, 0.0]))),
       flat_model=st.booleans())
def test_the_disagreement_is_finite_and_bounded_for_any_pose_image_and_depth(pose, image, depth, flat_model) -> None:
    """Singular, non-finite and far poses, NaN / inf / empty depth, flat images and one-coloured
    models: a number in [-1, 1], 0 when there is nothing to compare."""
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 0.01, (200, 3))
    colors = np.full((200, 3), 0.5) if flat_model else rng.random((200, 3))
    model = sample_model(1, pts * 1000, None, 30.0, 200, vertex_colors=(colors * 255).astype(np.uint8))
    T = np.vstack([pose, [0, 0, 0, 1]])
    k = np.array([[5.0, 0, 4.0], [0, 5.0, 3.0], [0, 0, 1]])
    with np.errstate(all="ignore"):
        d = _disagreement(model, T, np.arange(200), image, depth, k, 0.01)
    assert math.isfinite(d) and -1.0 <= d <= 1.0
    if flat_model:
        assert d == 0.0


# ----------------------------------------------------------------------------- registration
@pytest.mark.parametrize("yaw_deg", [30.0, 100.0, 215.0])
def test_colour_decides_the_flip_that_depth_cannot_see(yaw_deg: float) -> None:
    """The bar and its half turn about z explain the depth alike. With the colour image the
    registration finds the true yaw; with the colours swapped in the image it finds the half turn,
    so the colour, not luck, decides."""
    model, world_T_obj, world_T_cam, depth, rgb = _bar_view(yaw_deg)
    seen = perceive(depth, K, world_T_cam, model, None)
    assert seen.cluster is not None
    cam_T_obj = invert(world_T_cam) @ world_T_obj
    up_flip = make_transform(Rotation.from_euler("y", 180, degrees=True).as_matrix(), (0, 0, 0))

    def error(reg_T: np.ndarray, truth: np.ndarray) -> float:  # the bar upside down shows the same colours
        return min(rotation_error_deg(reg_T[:3, :3], truth[:3, :3]),
                   rotation_error_deg(reg_T[:3, :3], (truth @ up_flip)[:3, :3]))

    reg = register_model(model, seen.cluster, seen.plane, depth, K, RegistrationOptions(), seen.min_height, rgb)
    assert error(reg.cam_T_obj, cam_T_obj) < 10.0
    swapped = rgb.copy()
    red = np.all(np.abs(rgb.astype(int) - RED) < 30, axis=-1)
    blue = np.all(np.abs(rgb.astype(int) - BLUE) < 30, axis=-1)
    swapped[red], swapped[blue] = BLUE, RED
    reg = register_model(model, seen.cluster, seen.plane, depth, K, RegistrationOptions(), seen.min_height, swapped)
    half_turn = cam_T_obj @ make_transform(Rotation.from_euler("z", 180, degrees=True).as_matrix(), (0, 0, 0))
    assert error(reg.cam_T_obj, half_turn) < 10.0


def test_a_colour_image_of_another_size_is_refused() -> None:
    model, world_T_obj, world_T_cam, depth, rgb = _bar_view(30.0)
    seen = perceive(depth, K, world_T_cam, model, None)
    with pytest.raises(BraveError, match=r"colour image is \(120, 160, 3\), the depth image \(240, 320\)"):
        register_model(model, seen.cluster, seen.plane, depth, K, RegistrationOptions(), seen.min_height,
                       rgb[::2, ::2])


@pytest.mark.parametrize("weight", [-0.1, math.nan, math.inf])
def test_a_colour_weight_that_is_not_a_finite_non_negative_number_is_refused(weight: float) -> None:
    with pytest.raises(BraveError, match="RegistrationOptions.color_weight must be a finite number >= 0"):
        RegistrationOptions(color_weight=weight)

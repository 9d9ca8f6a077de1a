"""The active learned agent's view fusion: triangulation from rays (exact on exact rays, None and
never NaN when the rays are too close to parallel or the point is behind a camera), and ICP over
several views' depth points (the facing test with several cameras)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.evaluation.agents.learned.fusion import MIN_PARALLAX_DEG, triangulate


def _directions_around(rng: np.random.Generator, n: int, spread_deg: float) -> np.ndarray:
    """n unit directions within ``spread_deg`` of +z, the first along it and the second ``spread_deg`` off."""
    angles = np.radians(np.concatenate([[0.0, spread_deg], rng.uniform(0.0, spread_deg, size=n - 2)]))
    azimuths = np.concatenate([[0.0, 0.0], rng.uniform(0.0, 2 * np.pi, size=n - 2)])
    return np.stack([np.sin(angles) * np.cos(azimuths), np.sin(angles) * np.sin(azimuths), np.cos(angles)], axis=1)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(2, 6), spread=st.floats(MIN_PARALLAX_DEG + 0.5, 80.0),
       scale=st.sampled_from([1e-3, 0.3, 50.0]))
def test_exact_rays_meet_at_their_point(seed: int, n: int, spread: float, scale: float) -> None:
    rng = np.random.default_rng(seed)
    point = rng.normal(size=3) * scale
    d = _directions_around(rng, n, spread) @ Rotation.random(random_state=seed).as_matrix().T
    origins = point - d * rng.uniform(0.2, 2.0, size=(n, 1)) * scale
    got = triangulate(origins, d * rng.uniform(0.1, 10.0, size=(n, 1)))
    assert got is not None and np.allclose(got, point, atol=1e-6 * scale)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(2, 6), spread=st.floats(0.0, MIN_PARALLAX_DEG - 0.1))
def test_near_parallel_rays_fix_no_point(seed: int, n: int, spread: float) -> None:
    rng = np.random.default_rng(seed)
    d = _directions_around(rng, n, spread / 2.0)  # any two at most ``spread`` apart
    assert triangulate(rng.normal(size=(n, 3)) * 0.01, d) is None


def test_a_point_behind_a_camera_degenerate_or_non_finite_rays_give_none() -> None:
    origins = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    meet = np.array([[0.0, 0.0, -1.0], [-0.1, 0.0, -1.0]])  # these meet at (0, 0, -1); reversed, behind both
    assert np.allclose(triangulate(origins, meet), (0.0, 0.0, -1.0)) and triangulate(origins, -meet) is None
    away = meet
    assert triangulate(origins[:1], away[:1]) is None
    assert triangulate(origins, np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])) is None
    assert triangulate(np.array([[np.nan, 0, 0], [0.1, 0, 0]]), -away) is None
    assert triangulate(np.array([[0.0, 0, 0], [np.inf, 0, 0], [0.1, 0, 0]]), np.array([[0, 0, 1.0], [0, 0, 1.0],
                                                                                      [-0.1, 0, 1.0]])) is not None


def test_icp_over_two_views_recovers_a_rotation_one_view_leaves_ambiguous() -> None:
    """A box seen from two sides 90 deg apart: the fused cloud pins a 10 deg rotation error back."""
    import trimesh

    from brave6d.evaluation.learned.refine import icp_refine, sample_surface

    mesh = trimesh.creation.box(extents=(0.03, 0.02, 0.01))
    surface = sample_surface(mesh.vertices, mesh.faces, float(np.linalg.norm([0.03, 0.02, 0.01])))
    truth = np.eye(4)
    truth[:3, 3] = (0.0, 0.0, 0.3)
    eyes = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.3]])
    posed = surface.points @ truth[:3, :3].T + truth[:3, 3]
    normals = surface.normals @ truth[:3, :3].T
    seen = [((e - posed) * normals).sum(axis=1) > 0 for e in eyes]
    cloud = np.concatenate([posed[s] for s in seen])
    start = truth.copy()
    start[:3, :3] = Rotation.from_euler("y", 10, degrees=True).as_matrix()
    fused, refined, fit = icp_refine(start, cloud, surface, max_points=None, eyes=eyes)
    err = np.degrees(Rotation.from_matrix(fused[:3, :3] @ truth[:3, :3].T).magnitude())
    assert refined and fit > 0.9 and err < 1.0 and np.all(np.isfinite(fused))

"""The one silhouette ray caster (brave6d.annotation.SilhouetteCaster) and the two rules built on it: the
BOP export's masks (brave6d.annotation.visibility.MaskRenderer) and the server's visible fractions with
splat occlusion (brave6d.serve.visibility.VisibilityComputer). Pixel-exact expectations on thin plates."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.annotation import SilhouetteCaster, bbox_xywh
from brave6d.annotation.models import MeshData
from brave6d.annotation.visibility import MaskRenderer
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import NonRigidTransformError
from brave6d.core.transforms import look_at, make_transform
from brave6d.serve.visibility import VisibilityComputer

# 64 x 64 camera, f = 100 px, at the world origin looking along +z (identity pose): a point (x, y, Z)
# lands on u = 31.5 + 100 x / Z, so plate edges fall on half-integer pixel coordinates.
CAMERA = PinholeCamera(64, 64, 100.0, 100.0, 31.5, 31.5)
EYE = np.eye(4)


def camera_poses(first: np.ndarray, views: list) -> np.ndarray:
    """``first`` and the ``look_at`` pose of every (eye, aim) view that has one, stacked (N, 4, 4)."""
    poses = [first]
    for eye, aim in views:
        try:
            poses.append(look_at(eye, aim))
        except NonRigidTransformError:
            continue
    return np.stack(poses)


def plate(x0: float, x1: float, y0: float, y1: float) -> tuple[np.ndarray, np.ndarray]:
    """A 1 mm thick box whose face nearest the camera is the model's z = 0 plane (metres)."""
    v = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (0.0, 0.001)], dtype=float)
    f = np.array([(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6),
                  (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)], dtype=np.int64)
    return v, f


def at(z: float) -> np.ndarray:
    return make_transform(np.eye(3), [0.0, 0.0, z])


# A: 20 x 20 px at 1 m (u, v 22..41); B: 10 x 20 px at 0.5 m over A's right half (u 32..41);
# C: 20 x 20 px at 1 m, 13 of its columns left of the image (u -13..6).
A = plate(-0.1, 0.1, -0.1, 0.1)
B = plate(0.0, 0.05, -0.05, 0.05)
C = plate(-0.45, -0.25, -0.1, 0.1)
MODELS = {1: A, 2: B, 3: C}
INSTANCES = [(1, at(1.0)), (2, at(0.5)), (3, at(1.0))]


def test_silhouettes_count_the_whole_object_alone() -> None:
    a, b, c = SilhouetteCaster(MODELS, INSTANCES).silhouettes(EYE, CAMERA)
    assert (a.px_count_all, a.bbox_all) == (400, (22, 22, 19, 19))  # B in front does not cut A's silhouette
    assert (b.px_count_all, b.bbox_all) == (200, (32, 22, 9, 19))
    np.testing.assert_allclose(a.depth, 1.0, atol=1e-6)
    np.testing.assert_allclose(b.depth, 0.5, atol=1e-6)
    np.testing.assert_allclose(a.rays[:, 2], 1.0)
    # the truncated strip keeps its canvas pixels; only 7 columns lie in the image
    assert (c.px_count_all, c.bbox_all) == (400, (-13, 22, 19, 19))
    inside = c.within(CAMERA.width, CAMERA.height)
    assert (inside.px_count_all, inside.bbox_all) == (140, (0, 22, 6, 19))
    np.testing.assert_allclose(inside.depth, 1.0, atol=1e-6)


def test_objects_behind_the_camera_have_no_silhouette() -> None:
    (behind,) = SilhouetteCaster({1: A}, [(1, at(-1.0))]).silhouettes(EYE, CAMERA)
    assert behind.px_count_all == 0 and behind.bbox_all is None


def test_first_instance_sees_the_nearest_surface_and_static_meshes_own_no_instance() -> None:
    # a static plate at z = 0.8 m over x -0.1..-0.05 m covers A's columns u = 22..25 (u 19..25.25 at 0.8 m)
    occ_v, occ_f = plate(-0.1, -0.05, -0.1, 0.1)
    occluder = (occ_v + [0.0, 0.0, 0.8], occ_f)  # world frame
    caster = SilhouetteCaster(MODELS, INSTANCES, static=[occluder])
    a = next(iter(caster.silhouettes(EYE, CAMERA)))
    owner = caster.first_instance(EYE, a.rays)
    u = a.xs
    assert set(owner[u >= 32]) == {1}  # B in front of A's right half
    assert set(owner[u <= 25]) == {-1}
    assert set(owner[(u >= 26) & (u < 32)]) == {0}


def test_mask_renderer_masks_follow_the_caster() -> None:
    masks = MaskRenderer(CAMERA, {k: MeshData(*m) for k, m in MODELS.items()}, INSTANCES).render(EYE)
    a, b, c = masks
    assert (a.mask.sum(), a.mask_visib.sum(), a.px_count_all) == (400, 200, 400)
    assert a.mask_visib[22:42, 22:32].all() and not a.mask_visib[:, 32:].any()
    assert (b.mask.sum(), b.mask_visib.sum()) == (200, 200)
    assert (c.mask.sum(), c.px_count_all, c.bbox_all) == (140, 400, (-13, 22, 19, 19))
    assert not (a.mask_visib & ~a.mask).any()


def test_served_visibility_equals_the_bop_masks_without_splat() -> None:
    """One algorithm: with no splat depth the server's counts are the BOP export's."""
    world_T_cam = look_at((0.3, -0.2, -0.4), (0.0, 0.0, 1.0))
    served = VisibilityComputer([MODELS[k] for k, _ in INSTANCES], [T for _, T in INSTANCES]).compute(
        world_T_cam, CAMERA)
    masks = MaskRenderer(CAMERA, {k: MeshData(*m) for k, m in MODELS.items()}, INSTANCES).render(world_T_cam)
    assert any(0 < v.visib_fract < 1 for v in served)  # the view has occlusion to compare
    for v, m in zip(served, masks):
        ys, xs = np.nonzero(m.mask_visib)
        assert (v.px_count_all, v.px_count_visib) == (m.px_count_all, int(m.mask_visib.sum()))
        assert v.bbox_visib == bbox_xywh(xs, ys)
        assert v.bbox_obj == (m.bbox_all if v.px_count_visib else None)


def test_splat_depth_occludes_beyond_the_tolerance_only() -> None:
    vc = VisibilityComputer([A], [at(1.0)], occlusion_tolerance=0.015)
    depth = np.zeros((64, 64), dtype=np.float32)  # 0 = no splat data: never occludes
    depth[22:42, 22:27] = 0.9  # 10 cm in front of A: occludes 5 columns
    depth[22:42, 27:32] = 0.99  # 1 cm in front: within the tolerance, A stays visible
    depth[22:42, 32:37] = 1.2  # behind A
    (v,) = vc.compute(EYE, CAMERA, depth)
    assert (v.px_count_all, v.px_count_visib, v.visib_fract) == (400, 300, 0.75)
    assert v.bbox_visib == (27, 22, 14, 19) and v.bbox_obj == (22, 22, 19, 19)
    (unoccluded,) = vc.compute(EYE, CAMERA, None)
    assert unoccluded.px_count_visib == 400
    depth[:] = 0.5  # a wall in front of everything
    assert vc.compute(EYE, CAMERA, depth)[0].to_json() == {
        "px_count_all": 400, "px_count_visib": 0, "visib_fract": 0.0, "bbox_obj": None, "bbox_visib": None}


def test_served_visibility_is_the_same_from_many_threads() -> None:
    """Server worker threads share one computer, from its first call on (Open3D builds a scene's
    acceleration structure on the first cast)."""
    models, poses_obj = [MODELS[k] for k, _ in INSTANCES], [T for _, T in INSTANCES]
    vc = VisibilityComputer(models, poses_obj)
    poses = [look_at((0.05 * k - 0.2, 0.03 * k - 0.1, -0.3), (0.0, 0.0, 1.0)) for k in range(8)]
    expected = [[v.to_json() for v in VisibilityComputer(models, poses_obj).compute(T, CAMERA)] for T in poses]
    assert len({str(e) for e in expected}) > 1  # the poses differ, so a mix-up would show
    got: dict[int, list] = {}

    def work(k: int) -> None:
        for _ in range(5):
            got.setdefault(k, []).append([v.to_json() for v in vc.compute(poses[k], CAMERA)])

    threads = [threading.Thread(target=work, args=(k,)) for k in range(len(poses))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k, runs in got.items():
        assert all(r == expected[k] for r in runs), k
    assert sorted(got) == list(range(len(poses)))


@pytest.mark.parametrize("bad", [np.diag([1.0, 1.0, 2.0, 1.0]), np.full((4, 4), np.nan)])
def test_non_rigid_instance_poses_are_refused(bad: np.ndarray) -> None:
    with pytest.raises(NonRigidTransformError, match="instance 0: world_T_model"):
        SilhouetteCaster({1: A}, [(1, bad)])


def needle(length: float = 0.2, width: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """A thin tetrahedron along its bounding box's diagonal: it fills little of the box's projection."""
    v = np.array([[0.0, 0.0, 0.0], [width, 0.0, 0.0], [0.0, width, 0.0], [length, length, length]], dtype=float)
    return v, np.array([(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)], dtype=np.int64)


def full_canvas_hits(caster: SilhouetteCaster, n: int, world_T_cam: np.ndarray, camera: PinholeCamera
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Instance ``n`` alone cast at every pixel of the 3x canvas (no region of interest): hit pixels and depths."""
    from brave6d.annotation.visibility import pixel_rays
    from brave6d.core.transforms import invert

    key, world_T_model = caster.instances[n]
    u, v = np.meshgrid(np.arange(-camera.width, 2 * camera.width, dtype=np.float64),
                       np.arange(-camera.height, 2 * camera.height, dtype=np.float64))
    rays = pixel_rays(camera, u.ravel(), v.ravel())
    model_T_cam = invert(world_T_model) @ world_T_cam
    t, _ = caster._cast(caster._model_scenes[key], model_T_cam[:3, 3], model_T_cam[:3, :3], rays)
    hit = np.isfinite(t)
    return u.ravel()[hit].astype(np.int64), v.ravel()[hit].astype(np.int64), t[hit]


# eye positions around the plates (at z 0.5-1 m) and the needle: far, close (truncated), beside and behind them
EYES = st.tuples(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(-0.5, 1.6))
AIMS = st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(0.3, 1.2))


@given(views=st.lists(st.tuples(EYES, AIMS), min_size=1, max_size=4),
       exact=st.sampled_from([None, 0.005, 0.0025]))
@settings(max_examples=25, deadline=None)
def test_many_cameras_cast_every_pixel_that_can_be_hit(views: list, exact: float | None) -> None:
    """silhouettes_many casts only the pixels near the projected bounding box's hull: for any pose
    (objects whole, truncated, behind the camera; plate edges exactly on pixel centres) its pixels
    and depths are those of a cast at every canvas pixel, and those of silhouettes() one view at a time."""
    models = {**MODELS, 4: needle()}
    instances = [*INSTANCES, (4, make_transform(np.eye(3), [-0.1, -0.05, 0.6]))]
    if exact is not None:  # a plate whose edges project onto pixel centres (u, v = 31.5 + 100 x / 1 m)
        models[5] = plate(-exact - 0.1, exact, -exact, exact + 0.1)
        instances.append((5, at(1.0)))
    caster = SilhouetteCaster(models, instances)
    poses = camera_poses(EYE, views)  # the first: the plates' edges exactly as documented above
    for n, batch in enumerate(caster.silhouettes_many(poses, CAMERA)):
        for c, T in enumerate(poses):
            mine = batch.owner == c
            xs, ys, depth = full_canvas_hits(caster, n, T, CAMERA)
            np.testing.assert_array_equal(batch.xs[mine], xs)
            np.testing.assert_array_equal(batch.ys[mine], ys)
            np.testing.assert_array_equal(batch.depth[mine], depth)
            one = list(caster.silhouettes(T, CAMERA))[n]
            np.testing.assert_array_equal(batch.xs[mine], one.xs)
            np.testing.assert_array_equal(batch.rays[mine], one.rays)

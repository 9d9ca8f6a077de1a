"""Visible fractions of many views at once (VisibilityComputer.compute_many) equal one view at a
time bit for bit: with the reference geometry's occluders, the splat's depth, or none, for views
that see the objects whole, truncated (the camera close over them) or not at all."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from brave6d.core.transforms import look_at
from brave6d.serve.bundle import load_bundle
from brave6d.serve.episodes import SceneServer
from brave6d.serve.toy_scene import make_synthetic_bundle


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SceneServer:
    root = tmp_path_factory.mktemp("vis_batch")
    make_synthetic_bundle(root, n_gaussians=2000, depth=True)  # depth: the bundle has a reference geometry
    return SceneServer(load_bundle(root / "bundle"), "cpu")


def test_many_views_equal_single_views(scene: SceneServer) -> None:
    rng = np.random.default_rng(0)
    cam = scene.camera_for(160, 120)
    poses = [scene.random_start(scene.bundle.objects[i % 2], rng) for i in range(12)]
    poses += [look_at((0.45 + 0.01 * rng.normal(), 0.01 * rng.normal(), 0.05), (0.46, 0.0, 0.0)) for _ in range(3)]
    poses += [look_at((0.3, 0.0, 0.3), (0.0, 0.5, 0.3))]  # looking away: nothing seen
    poses += [look_at((0.49, 0.11 + 0.01 * k, 0.03), (0.45, -0.03, 0.01)) for k in range(2)]  # blue before red
    poses = np.stack(poses)
    vc, ref = scene.visibility, scene.reference
    assert vc is not None and ref is not None
    caster = vc._caster  # the cubes hide each other in some views: pixels of one hit first by the other
    assert any((caster.first_instance(T, sil.within(160, 120).rays) != n).any()
               for T in poses for n, sil in enumerate(caster.silhouettes(T, cam)))
    many = vc.compute_many(poses, cam, occluder_depths=ref.depth_along_many)
    assert many == [vc.compute(T, cam, None, partial(ref.depth_along, T)) for T in poses]
    seen = [v for views in many for v in views]
    assert any(0 < v.visib_fract < 1 for v in seen) and any(v.px_count_all == 0 for v in seen)
    depths = [rng.uniform(0.0, 0.6, (120, 160)).astype(np.float32) for _ in poses]  # random occluders
    assert vc.compute_many(poses, cam, splat_depths=depths) == [vc.compute(T, cam, d) for T, d in zip(poses, depths)]
    assert vc.compute_many(poses, cam) == [vc.compute(T, cam) for T in poses]
    assert vc.compute_many(np.zeros((0, 4, 4)), cam) == []


def test_observe_batch_equals_observe(scene: SceneServer) -> None:
    rng = np.random.default_rng(1)
    cam = scene.camera_for(64, 48)
    poses = [scene.random_start(scene.bundle.objects[0], rng) for _ in range(4)]
    batch = scene.observe_batch(poses, cam, [0, 1, None, 0])
    for view, T, gt in zip(batch, poses, [0, 1, None, 0]):
        one = scene.observe(T, cam, gt)
        assert [o.model_dump(mode="json") for o in view.objects] == [o.model_dump(mode="json") for o in one.objects]
        np.testing.assert_array_equal(view.depth, one.depth)


def test_a_scored_batch_holds_the_targets_truth_and_completes_to_observes(scene: SceneServer) -> None:
    """targets_only (what a scored manager asks): each view holds its target's truth alone, equal to
    observe's; complete() adds every object's, equal to observe's bit for bit."""
    rng = np.random.default_rng(2)
    cam = scene.camera_for(64, 48)
    poses = [scene.random_start(scene.bundle.objects[k % 2], rng) for k in range(4)]
    poses.append(look_at((0.49, 0.12, 0.03), (0.45, -0.03, 0.01)))  # the blue cube before the red one
    targets = [0, 1, None, 1, 0]
    for view, T, gt in zip(scene.observe_batch(poses, cam, targets, targets_only=True), poses, targets):
        one = scene.observe(T, cam, gt)
        assert not view.complete and one.complete
        assert [o.model_dump(mode="json") for o in view.objects] == [
            o.model_dump(mode="json") for o in one.objects if o.is_target]
        full = scene.complete(view)
        assert full.complete and scene.complete(full) is full
        assert [o.model_dump(mode="json") for o in full.objects] == [o.model_dump(mode="json") for o in one.objects]
        np.testing.assert_array_equal(full.depth, one.depth)
    assert any(0 < o.visib_fract < 1 for o in scene.observe(poses[-1], cam, 0).objects)

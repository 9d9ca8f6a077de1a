"""Issue #68: the visible fractions' stride (one ray per s x s block, VisibilityComputer's ``stride``),
the action log lines made without the pydantic model (episode_log.format_action) and the vector env's
read-only observation batches."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_silhouettes import camera_poses

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.transforms import look_at, make_transform
from brave6d.serve import EpisodeManager, SceneServer
from brave6d.serve import visibility as vis_module
from brave6d.serve.bundle import load_bundle
from brave6d.serve.episode_log import ActionRecord, format_action, format_record, read_episode_log
from brave6d.serve.toy_scene import make_synthetic_bundle
from brave6d.serve.vector_env import VECTOR_VISIBILITY_STRIDE, BraveVectorEnv
from brave6d.serve.visibility import VisibilityComputer, effective_stride, lattice_camera


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SceneServer:
    root = tmp_path_factory.mktemp("stride_scene")
    make_synthetic_bundle(root, n_gaussians=2000, depth=True)
    return SceneServer(load_bundle(root / "bundle"), "cpu")


# ----------------------------------------------------------------------------- the stride
def test_effective_stride_divides_the_image() -> None:
    cam = PinholeCamera(320, 240, 300.0, 300.0, 159.5, 119.5)
    assert [effective_stride(cam, s) for s in (1, 2, 4, 7, 8, 9)] == [1, 2, 4, 5, 8, 8]
    assert effective_stride(PinholeCamera(321, 241, 300.0, 300.0, 160.0, 120.0), 4) == 1  # no common divisor
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="stride"):
            effective_stride(cam, bad)
    lattice = lattice_camera(cam, 4)  # its pixel (i, j) looks along the camera's pixel (4 i + 2, 4 j + 2)
    assert (lattice.width, lattice.height) == (80, 60)
    for i, j in ((0, 0), (79, 59), (13, 40)):
        np.testing.assert_allclose([(i - lattice.cx) / lattice.fx, (j - lattice.cy) / lattice.fy],
                                   [(4 * i + 2 - cam.cx) / cam.fx, (4 * j + 2 - cam.cy) / cam.fy], rtol=1e-12)


def plate(half: float) -> tuple[np.ndarray, np.ndarray]:
    """A square 1 mm thick box, ``2 half`` wide, its near face at the model's z = 0 (metres)."""
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (0.0, 0.001)], dtype=float)
    f = np.array([(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6),
                  (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)], dtype=np.int64)
    return v, f


CAMERA = PinholeCamera(96, 72, 120.0, 120.0, 47.5, 35.5)
# a large plate at 1 m (48 px), a tiny one (about 2 px, smaller than a block) and one hidden behind the large one
MODELS = [plate(0.2), plate(0.008), plate(0.05)]
POSES = [make_transform(np.eye(3), [0.0, 0.0, 1.0]), make_transform(np.eye(3), [0.25, 0.1, 0.7]),
         make_transform(np.eye(3), [0.0, 0.0, 1.3])]
EYES = st.tuples(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(-1.0, 0.6))
AIMS = st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.7, 1.4))


@given(views=st.lists(st.tuples(EYES, AIMS), min_size=1, max_size=5), stride=st.sampled_from([2, 3, 4, 8]),
       splat=st.booleans())
@settings(max_examples=30, deadline=None)
def test_strided_fractions_are_sane_and_equal_one_view_at_a_time(views: list, stride: int, splat: bool) -> None:
    """Any poses (objects whole, tiny, at and over the border, hidden, behind the camera): every fraction
    is finite and in [0, 1]; counts are whole blocks or exact; a silhouette under EXACT_BELOW_SAMPLES
    samples is exactly stride 1's (so a tiny visible object is never unseen); a hidden or unseen object
    is 0 with no boxes; the batch equals compute() one view at a time bit for bit."""
    computer = VisibilityComputer(MODELS, POSES)
    poses = camera_poses(np.eye(4), views)
    rng = np.random.default_rng(len(poses))
    depths = [rng.uniform(0.0, 1.5, (CAMERA.height, CAMERA.width)).astype(np.float32) for _ in poses] if splat else None
    s = effective_stride(CAMERA, stride)
    many = computer.compute_many(poses, CAMERA, splat_depths=depths, stride=stride)
    exact = computer.compute_many(poses, CAMERA, splat_depths=depths)
    for c, T in enumerate(poses):
        assert many[c] == computer.compute(T, CAMERA, None if depths is None else depths[c], stride=stride)
        for got, want in zip(many[c], exact[c]):
            assert np.isfinite(got.visib_fract) and 0.0 <= got.visib_fract <= 1.0
            assert got.px_count_visib <= got.px_count_all
            if got == want:
                continue
            assert got.px_count_all % (s * s) == 0 and got.px_count_visib % (s * s) == 0
            assert got.px_count_all // (s * s) >= vis_module.EXACT_BELOW_SAMPLES  # small ones are exact
            if got.px_count_visib == 0:
                assert got.bbox_obj is None and got.bbox_visib is None
            else:
                x, y, w, h = got.bbox_visib
                assert 0 <= x and 0 <= y and x + w < CAMERA.width and y + h < CAMERA.height
    straight = many[0]  # the identity view: the large plate whole, the tiny one seen, the third hidden
    assert straight[1] == exact[0][1] and straight[1].px_count_visib > 0
    assert straight[2].px_count_visib == 0 and straight[2].visib_fract == 0.0 and straight[2].px_count_all > 0
    if not splat:
        assert straight[0].visib_fract == exact[0][0].visib_fract == 1.0


def test_stride_on_the_scene_with_its_reference(scene: SceneServer) -> None:
    """The synthetic scene's views at 320x240 through the reference geometry: stride 4 equals one view at
    a time (the server's observe and observe_batch paths), its fractions are within 0.1 of stride 1's and
    stride 1 is unchanged by the stride's code."""
    rng = np.random.default_rng(0)
    cam = scene.camera_for(320, 240)
    poses = np.stack([scene.random_start(scene.bundle.objects[i % 2], rng) for i in range(8)]
                     + [look_at((0.49, 0.11, 0.03), (0.45, -0.03, 0.01))])  # blue before red
    vc, ref = scene.visibility, scene.reference
    many = vc.compute_many(poses, cam, occluder_depths=ref.depth_along_many, stride=4)
    exact = vc.compute_many(poses, cam, occluder_depths=ref.depth_along_many)
    assert many == [vc.compute(T, cam, None, partial(ref.depth_along, T), 4) for T in poses]
    assert exact == [vc.compute(T, cam, None, partial(ref.depth_along, T)) for T in poses]
    assert many != exact  # the stride is used
    for got, want in zip(many, exact):
        assert [abs(g.visib_fract - w.visib_fract) < 0.1 for g, w in zip(got, want)] == [True, True]
    batch = scene.observe_batch(list(poses[:3]), cam, [0, 1, 0], stride=4)
    for view, T, gt in zip(batch, poses, [0, 1, 0]):
        one = scene.observe(T, cam, gt, 4)
        assert view.visibility_stride == 4
        assert [o.model_dump(mode="json") for o in view.objects] == [o.model_dump(mode="json") for o in one.objects]
        exact_view = scene.observe(T, cam, gt)  # a submit records the exact truth whatever the stride
        assert [o.model_dump(mode="json") for o in scene.complete(view).objects] == [
            o.model_dump(mode="json") for o in exact_view.objects]


def test_episode_managers_and_vector_envs_share_one_stride(scene: SceneServer, tmp_path) -> None:
    """A vector env given a manager of another stride is refused; managers of stride 2 give the same
    moves and logs batched and one at a time; a submit's objects are exact at any stride."""
    with pytest.raises(BraveError, match="stride 2"):
        BraveVectorEnv(EpisodeManager(scene, visibility_stride=2), 2, visibility_stride=4)
    assert BraveVectorEnv(scene, 2).manager.visibility_stride == VECTOR_VISIBILITY_STRIDE
    assert BraveVectorEnv(EpisodeManager(scene, visibility_stride=2), 2).manager.visibility_stride == 2
    assert EpisodeManager(scene).visibility_stride == 1  # a server: every pixel unless told
    with pytest.raises(ValueError, match="visibility_stride"):
        EpisodeManager(scene, visibility_stride=0)
    training = "training"
    batched = EpisodeManager(scene, tmp_path / "b", mode=training, log_key=None, visibility_stride=2)
    single = EpisodeManager(scene, tmp_path / "s", mode=training, log_key=None, visibility_stride=2)
    exact = EpisodeManager(scene, tmp_path / "e", mode=training, log_key=None, visibility_stride=1)
    ids = {m: [m.reset(target="cube_red", width=160, height=120, seed=s).episode_id for s in range(3)]
           for m in (batched, single, exact)}
    twists = [((0, 0, 0.05), (0, 0, 0)), ((0.02, 0, 0), (0, 0.3, 0)), ((0, 0.01, 0), (0, 0, 0.2))]
    from brave6d.serve.episode_manager import MoveRequest

    results = batched.move_many([MoveRequest(e, v, w, 0.5) for e, (v, w) in zip(ids[batched], twists)])
    for k, (res, (v, w)) in enumerate(zip(results, twists)):
        one = single.move(ids[single][k], v, w, 0.5)
        assert [o.model_dump(mode="json") for o in res.observation.objects] == [
            o.model_dump(mode="json") for o in one.observation.objects]
        exact.move(ids[exact][k], v, w, 0.5)
    estimate = [{"obj_id": scene.bundle.objects[0].obj_id, "R": np.eye(3).tolist(), "t_m": [0.0, 0.0, 0.3]}]
    submits = []
    for m in (batched, single, exact):
        m.submit(ids[m][0], estimate)
        records = read_episode_log(m.log_dir / f"{ids[m][0]}.jsonl")
        submits.append([o.model_dump(mode="json") for o in records[-2].objects])
        if m is not exact:
            assert records[1].target_visib_fract == results[0].observation.target().visib_fract
    assert submits[0] == submits[1] == submits[2]


# ----------------------------------------------------------------------------- log lines
FLOATS = st.floats(allow_nan=False, allow_infinity=False, width=64)
MATRIX = st.lists(FLOATS, min_size=16, max_size=16).map(lambda v: np.array(v).reshape(4, 4))
JSONISH = st.recursive(st.none() | st.booleans() | st.integers(-10**6, 10**6) | FLOATS | st.text(max_size=8),
                       lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
                       max_leaves=8)


@given(event=st.sampled_from(["move", "set_pose"]), step=st.integers(0, 10**6), accepted=st.booleans(),
       collided=st.booleans(), refusal=st.none() | st.dictionaries(st.text(max_size=6), JSONISH, max_size=3),
       requested=st.dictionaries(st.text(max_size=6), JSONISH, max_size=4), before=MATRIX, after=MATRIX,
       adjustments=st.integers(0, 10**6), move=st.none() | st.dictionaries(st.text(max_size=6), JSONISH, max_size=3),
       timings=st.dictionaries(st.text(max_size=6), FLOATS | st.integers(-1000, 1000), max_size=5),
       target=st.none() | MATRIX, fract=st.none() | FLOATS | st.integers(0, 1), same_pose=st.booleans())
@settings(max_examples=120, deadline=None)
def test_action_lines_are_the_models_bytes(event, step, accepted, collided, refusal, requested, before, after,
                                           adjustments, move, timings, target, fract, same_pose, tmp_path_factory) -> None:
    """format_action writes ActionRecord's line byte for byte (any values: ints among the timings, -0.0,
    huge and tiny floats, nested dicts; a pose written before and reused), and it reads back as a
    valid record of the log schema."""
    fields = dict(event=event, step=step, accepted=accepted, collided=collided, refusal=refusal, requested=requested,
                  world_T_cam_before=before, world_T_cam=before if same_pose else after, adjustments=adjustments,
                  move=move, timings_ms=timings, target_cam_T_obj=target, target_visib_fract=fract,
                  time="2026-12-08T00:00:00.000+00:00")
    line = format_action(**fields)
    assert line == format_action(**fields)  # the second time from the matrices' cache
    assert line == format_record(ActionRecord(**fields))
    from pydantic import TypeAdapter

    from brave6d.serve.episode_log import LogRecord

    assert TypeAdapter(LogRecord).validate_json(line).model_dump(mode="json") == ActionRecord(**fields).model_dump(
        mode="json")


@pytest.mark.parametrize("bad", [
    {"world_T_cam": np.full((4, 4), np.nan)}, {"target_cam_T_obj": np.eye(3)}, {"target_visib_fract": float("inf")},
    {"timings_ms": {"render": float("nan")}}, {"event": "reset"}, {"accepted": None}, {"requested": [1, 2]},
    {"world_T_cam_before": np.diag([1.0, 1.0, np.inf, 1.0])}])
def test_bad_action_fields_are_refused_as_the_model_refuses_them(bad: dict) -> None:
    fields = dict(event="move", step=1, accepted=True, collided=False, refusal=None, requested={"duration": 0.5},
                  world_T_cam_before=np.eye(4), world_T_cam=np.eye(4), adjustments=1, move=None,
                  timings_ms={"render": 1.0}, target_cam_T_obj=None, target_visib_fract=None)
    fields.update(bad)
    with pytest.raises(ValueError):
        format_record(ActionRecord(**fields))
    with pytest.raises(ValueError):
        format_action(**fields)


# ----------------------------------------------------------------------------- observations
@pytest.mark.parametrize("mode", ["scored", "training"])
def test_observations_are_read_only_and_never_change_after_they_are_returned(scene: SceneServer, mode: str) -> None:
    """An agent cannot write into its observation (what it is scored on), and a batch returned once is not
    changed by later steps (moves, null twists, refusals, autoresets), while each step's batch is the one
    rendered for it."""
    vec = BraveVectorEnv(scene, 3, target="cube_red", width=64, height=48, max_steps=3, mode=mode)
    obs, _ = vec.reset(seed=4)
    kept = [(obs, {k: v.copy() for k, v in obs.items()})]
    rng = np.random.default_rng(2)
    for step in range(7):
        actions = rng.uniform(-1, 1, (3, 6)) * (rng.random((3, 1)) > 0.3)
        obs, *_ = vec.step(actions)
        kept.append((obs, {k: v.copy() for k, v in obs.items()}))
        for key in ("rgb", "depth"):
            assert not obs[key].flags.writeable
            with pytest.raises(ValueError, match="read-only"):
                obs[key][0, 0, 0] = 0
        for i in range(3):  # the batch holds each agent's current view
            view = vec._views[i]
            np.testing.assert_array_equal(obs["rgb"][i], view.rgb)
            np.testing.assert_array_equal(obs["depth"][i], view.depth)
    for returned, copy in kept:
        for key in copy:
            np.testing.assert_array_equal(returned[key], copy[key], err_msg=key)
    vec.close()


def test_a_view_without_truth_keeps_every_other_field(scene: SceneServer) -> None:
    """RenderedView.without_truth builds the view field by field: it equals dataclasses.replace's."""
    import dataclasses

    view = scene.observe(scene.random_start(scene.bundle.objects[0], np.random.default_rng(0)),
                         scene.camera_for(64, 48), 0, 2)
    bare, replaced = view.without_truth(), dataclasses.replace(view, objects=())
    assert bare.objects == () and view.objects
    for f in dataclasses.fields(view):
        assert getattr(bare, f.name) is getattr(replaced, f.name), f.name


def test_render_batch_writes_into_the_arrays_given(scene: SceneServer) -> None:
    """SplatRenderer.render_batch(out=...): the views' images are written into the arrays given (their
    RenderOutputs hold them), equal to a render without them; a None entry keeps the renderer's own."""
    cam = scene.camera_for(64, 48)
    rng = np.random.default_rng(3)
    poses = [scene.random_start(scene.bundle.objects[k % 2], rng) for k in range(3)]
    rgb, depth = np.zeros((3, 48, 64, 3), np.uint8), np.zeros((3, 48, 64), np.float32)
    out = [(rgb[0], depth[0]), None, (rgb[2], depth[2])]
    given = scene.renderer.render_batch(poses, cam, out=out)
    plain = scene.renderer.render_batch(poses, cam)
    for k in range(3):
        np.testing.assert_array_equal(given[k].rgb, plain[k].rgb)
        np.testing.assert_array_equal(given[k].depth, plain[k].depth)
    assert given[0].rgb is rgb[0] or np.shares_memory(given[0].rgb, rgb)
    np.testing.assert_array_equal(rgb[2], plain[2].rgb)
    np.testing.assert_array_equal(depth[0], plain[0].depth)
    assert not rgb[1].any() and not np.shares_memory(given[1].rgb, rgb)

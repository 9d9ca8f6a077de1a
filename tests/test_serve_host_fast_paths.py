"""Issue #68 item 1 (training mode): the vector env's host-side shortcuts give what the plain code gives,
bit for bit. The objects' truth records built without pydantic's validation (``object_state``), the
views' inverses and object poses of a whole batch (``invert_stack``, ``SceneServer._objects_many``),
the occluder rays of many cameras at once (``ReferenceGeometry.depth_along_many``), and in training
mode every agent's view holds the same objects' records as one ``move`` at a time."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from brave6d.core.transforms import invert, look_at
from brave6d.serve import EpisodeManager, SceneServer
from brave6d.serve.bundle import BundleObject, load_bundle
from brave6d.serve.episodes import invert_stack, object_state
from brave6d.serve.schema import ObjectState
from brave6d.serve.toy_scene import make_synthetic_bundle
from brave6d.serve.vector_env import BraveVectorEnv
from brave6d.serve.visibility import Visibility

W, H = 64, 48


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> SceneServer:
    root = tmp_path_factory.mktemp("fast_paths_scene")
    make_synthetic_bundle(root, n_gaussians=2000, depth=True)
    return SceneServer(load_bundle(root / "bundle"), "cpu")


def validated(obj: BundleObject, cam_T_obj: np.ndarray, vis: Visibility | None, is_target: bool) -> ObjectState:
    """The record as pydantic validates it (object_state before its shortcut)."""
    fields = vis.to_json() if vis is not None else {}
    return ObjectState(gt_id=obj.gt_id, obj_id=obj.obj_id, name=obj.name, is_target=is_target, cam_T_obj=cam_T_obj,
                       **fields)


def assert_same_record(a: ObjectState, b: ObjectState) -> None:
    assert type(a) is type(b) is ObjectState
    assert a.model_fields_set == b.model_fields_set
    assert list(a.__dict__) == list(b.__dict__)
    for key, value in a.__dict__.items():
        other = b.__dict__[key]
        if isinstance(value, np.ndarray):
            assert other.dtype == value.dtype and other.shape == value.shape
            assert other.tobytes() == value.tobytes()
        else:
            assert type(value) is type(other) and value == other, key
    assert a.model_dump(mode="json") == b.model_dump(mode="json")
    assert a.model_dump_json() == b.model_dump_json()


def instance(gt_id: object = 0, obj_id: object = 1, name: str = "cube") -> BundleObject:
    return BundleObject(gt_id, obj_id, name, np.eye(4), "models/obj.ply", 20.0)  # type: ignore[arg-type]


def rigid(rotvec: list[float], t: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


FLOATS = st.floats(-1e6, 1e6, allow_nan=False)
ROTVECS = st.lists(st.floats(-4.0, 4.0), min_size=3, max_size=3)
TRANSLATIONS = st.lists(st.one_of(FLOATS, st.floats(-1e-6, 1e-6), st.sampled_from([0.0, -0.0])), min_size=3, max_size=3)
BOXES = st.one_of(st.none(), st.tuples(*[st.integers(-10**6, 10**6)] * 4))
VISIBILITIES = st.one_of(st.none(), st.builds(Visibility, st.integers(0, 10**7), st.integers(0, 10**7),
                                              st.floats(0.0, 1.0), BOXES, BOXES))


@given(rotvec=ROTVECS, t=TRANSLATIONS, vis=VISIBILITIES, is_target=st.booleans(), gt_id=st.integers(0, 10**6),
       name=st.text(max_size=8), checked=st.booleans())
@settings(max_examples=150, deadline=None)
def test_object_record_without_validation_equals_the_validated_model(rotvec, t, vis, is_target, gt_id, name,
                                                                     checked) -> None:
    """For any pose, visibility (none, unseen, any counts and boxes), flag and ids: the same model, fields
    set, dump and JSON as pydantic's validation gives."""
    obj = instance(gt_id, gt_id + 1, name)
    M = rigid(rotvec, t)
    assert_same_record(object_state(obj, M, vis, is_target, True if checked else None),
                       validated(obj, M, vis, is_target))


@pytest.mark.parametrize("odd", ["numpy ints", "numpy bool", "float32 matrix", "list matrix", "bool count",
                                 "int fraction", "numpy fraction", "list box"])
def test_object_record_of_other_types_is_validated(odd: str) -> None:
    """Values of any other type than the model's own go through the validation: the same model as before."""
    obj = instance(1, 2)
    M, flag = rigid([0.1, 0.2, 0.3], [0.1, -0.2, 0.5]), True
    vis = Visibility(40, 20, 0.5, (1, 2, 3, 4), (1, 2, 3, 3))
    if odd == "numpy ints":
        obj = instance(np.int64(1), np.int32(2))
    elif odd == "numpy bool":
        flag = np.bool_(True)
    elif odd == "float32 matrix":
        M = M.astype(np.float32)
    elif odd == "list matrix":
        M = M.tolist()
    elif odd == "bool count":
        vis = Visibility(True, 1, 1.0, (1, 2, 3, 4), (1, 2, 3, 4))
    elif odd == "int fraction":
        vis = Visibility(40, 40, 1, (1, 2, 3, 4), (1, 2, 3, 4))
    elif odd == "numpy fraction":
        vis = Visibility(40, 20, np.float64(0.5), (1, 2, 3, 4), (1, 2, 3, 3))
    else:
        vis = Visibility(40, 20, 0.5, [1, 2, 3, 4], (1, 2, 3, 3))  # type: ignore[arg-type]
    fast = object_state(obj, M, vis, flag)
    assert_same_record(fast, validated(obj, M, vis, flag))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_object_record_refuses_what_the_model_refuses(bad: float) -> None:
    """A matrix or fraction that is not finite is refused, as the model refuses it, whether the caller
    checked the matrix (finite=False) or not."""
    obj = instance()
    M = np.eye(4)
    M[1, 3] = bad
    for finite in (None, False):
        with pytest.raises(ValidationError, match="finite"):
            object_state(obj, M, None, True, finite)
    with pytest.raises(ValidationError, match="finite"):
        object_state(obj, np.eye(4), Visibility(4, 2, bad, (0, 0, 1, 1), (0, 0, 1, 1)), True)


@given(poses=st.lists(st.tuples(ROTVECS, TRANSLATIONS), min_size=1, max_size=8))
@settings(max_examples=100, deadline=None)
def test_invert_stack_equals_invert_bit_for_bit(poses: list) -> None:
    Ts = np.stack([rigid(r, t) for r, t in poses])
    got = invert_stack(Ts)
    for T, inv in zip(Ts, got):
        assert inv.tobytes() == invert(T).tobytes()


def test_objects_of_a_batch_equal_one_view_at_a_time(scene: SceneServer) -> None:
    """SceneServer._objects_many: each view's records are the validated models of the plain formula
    (invert(T) @ world_T_obj per view), in training (every object) and scored (the target) modes."""
    rng = np.random.default_rng(3)
    poses = [look_at(rng.uniform(-0.4, 0.4, 3) + [0, 0, 0.5], rng.uniform(-0.05, 0.05, 3)) for _ in range(12)]
    objects = scene.bundle.objects
    vis = [[Visibility(int(rng.integers(1, 99)), 1, 0.25, (1, 2, 3, 4), None) if rng.random() < 0.7 else None
            for _ in objects] for _ in poses]
    targets = [objects[k % len(objects)].gt_id for k in range(len(poses))]
    for every in (True, False):
        many = scene._objects_many(poses, vis, targets, every)
        for T, v, target, records in zip(poses, vis, targets, many):
            plain = tuple(validated(o, invert(T) @ o.world_T_obj, vo, o.gt_id == target)
                          for o, vo in zip(objects, v) if every or o.gt_id == target)
            assert len(records) == len(plain) == (len(objects) if every else 1)
            for a, b in zip(records, plain):
                assert_same_record(a, b)


@given(sizes=st.lists(st.integers(0, 40), min_size=1, max_size=6), seed=st.integers(0, 2**16),
       mask=st.sampled_from(["none", "some", "all off"]))
@settings(max_examples=40, deadline=None)
def test_occluder_depth_of_a_ray_does_not_depend_on_the_rays_cast_with_it(scene: SceneServer, sizes: list, seed: int,
                                                                          mask: str) -> None:
    """depth_along_many: each set's part equals depth_along of that set alone, bit for bit, whatever the
    other sets and the rays not needed (0 there); finite, never negative."""
    ref = scene.reference
    rng = np.random.default_rng(seed)
    poses = [look_at(rng.uniform(-0.5, 0.5, 3) + [0, 0, 0.6], rng.uniform(-0.1, 0.1, 3)) for _ in sizes]
    sets = [np.c_[rng.uniform(-0.8, 0.8, (n, 2)), np.ones(n)].astype(np.float32) for n in sizes]
    total = sum(sizes)
    needed = None if mask == "none" else (rng.random(total) < 0.5) if mask == "some" else np.zeros(total, bool)
    many = ref.depth_along_many(poses, sets, needed)
    assert many.shape == (total,) and many.dtype == np.float32 and np.all(np.isfinite(many)) and np.all(many >= 0)
    end = 0
    for T, d in zip(poses, sets):
        start, end = end, end + len(d)
        alone = ref.depth_along(T, d)
        want = alone if needed is None else np.where(needed[start:end], alone, np.float32(0.0))
        assert many[start:end].tobytes() == want.tobytes()
        for k in range(0, len(d), 7):  # one ray alone: the same depth
            assert ref.depth_along(T, d[k:k + 1])[0] == alone[k]


def test_occluder_depths_match_the_test_depth(scene: SceneServer) -> None:
    """The occluder rays (float32 sums, one ray at a time) against the test depth's matrix product: at
    most float32 rounding apart (the visible fractions compare them with a 15 mm tolerance)."""
    ref = scene.reference
    cam = scene.bundle.camera.scaled(W, H)
    T = look_at([0.2, -0.3, 0.5], [0.0, 0.0, 0.02])
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.c_[(u.ravel() - cam.cx) / cam.fx, (v.ravel() - cam.cy) / cam.fy, np.ones(W * H)].astype(np.float32)
    along = ref.depth_along(T, rays).reshape(H, W)
    depth = ref.depth(T, cam)
    assert (along > 0).sum() > 200  # the table and cubes in view
    np.testing.assert_array_equal(along > 0, depth > 0)
    assert np.max(np.abs(along.astype(np.float64) - depth)) < 1e-5


def test_training_views_hold_the_objects_of_one_move_at_a_time(scene: SceneServer) -> None:
    """Training mode: every agent's view after each vector step holds the records (every object's pose and
    visible fraction) that one EpisodeManager.move gives at the vector env's stride, bit for bit."""
    n = 5
    vec = BraveVectorEnv(scene, n, target="cube_red", width=W, height=H, max_steps=100, mode="training",
                         max_linear=0.2)
    single = EpisodeManager(scene, mode="training", visibility_stride=vec.manager.visibility_stride)
    vec.reset(seed=4)
    ids = [single.reset(target="cube_red", width=W, height=H, seed=4 + i).episode_id for i in range(n)]
    rng = np.random.default_rng(9)
    seen = 0
    for _ in range(6):
        actions = rng.uniform(-1, 1, (n, 6))
        vec.step(actions)
        for i in range(n):
            one = single.move(ids[i], actions[i, :3] * 0.2, actions[i, 3:] * 0.5, 0.5).observation
            mine = vec._views[i]
            assert mine is not None and len(mine.objects) == len(one.objects) == len(scene.bundle.objects)
            for a, b in zip(mine.objects, one.objects):
                assert_same_record(a, b)
            seen += sum(o.px_count_visib or 0 for o in one.objects) > 0
    assert seen > 0  # some views see the cubes
    vec.close()


def test_a_log_without_a_file_makes_no_lines(scene: SceneServer, tmp_path, monkeypatch) -> None:
    """An episode log without a file (a manager without a log folder, the vector env's own) writes nothing,
    so no action line is made for it; with a folder every action's line is made and written as before."""
    from brave6d.serve import episode_manager

    made: list[str] = []
    real = episode_manager.format_action

    def counting(**fields):
        made.append(real(**fields))
        return made[-1]

    monkeypatch.setattr(episode_manager, "format_action", counting)
    for log_dir in (None, tmp_path / "logs"):
        made.clear()
        manager = EpisodeManager(scene, log_dir, mode="training", log_key=None)
        eid = manager.reset(target="cube_red", width=W, height=H, seed=1).episode_id
        manager.move(eid, (0.0, 0.0, 0.02), (0.0, 0.0, 0.0), 0.5)
        manager.move(eid, (0.0, 0.0, 0.0), (0.0, 0.1, 0.0), 0.5)
        if log_dir is None:
            assert made == []
            assert manager.get(eid).log.writes is False
        else:
            lines = (log_dir / f"{eid}.jsonl").read_text().splitlines(keepends=True)
            assert len(made) == 2 and lines[1:3] == made

"""The vector environment (issue #46 item 4): N agents whose steps render in one batch give the
observations and rewards of N independent :class:`BraveEnv` s over HTTP with the same seeds."""

from __future__ import annotations


import gymnasium
import numpy as np
import pytest

from brave6d.core.errors import BraveError
from brave6d.serve import BraveEnv, EpisodeManager, SceneServer
from brave6d.serve.app import create_app
from brave6d.serve.bundle import Bundle, load_bundle
from brave6d.serve.episode_manager import MoveRequest
from brave6d.serve.episodes import InvalidAction
from brave6d.serve.runner import ServerThread
from brave6d.serve.toy_scene import make_synthetic_bundle
from brave6d.serve.vector_env import BraveVectorEnv, sub_seeds

W, H, N, SEED, MAX_STEPS = 64, 48, 3, 11, 3
ACTIONS = [  # per step, one twist per agent: forward, a turn, a null twist, strafes
    [[0, 0, 1.0, 0, 0, 0], [0, 0, 0, 0, 0, 0], [0.5, 0, 0, 0, 0.3, 0]],
    [[0, 0, 0.5, 0, 0, 0.2], [0, 0, 1.0, 0, 0, 0], [0, 0, 0, 0, 0, 0]],
    [[-1.0, 0.5, 0, 0, 0, 0], [0, 0, -0.5, 0.2, 0, 0], [0, 0, 1.0, 0, 0, 0]],
]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Bundle:
    root = tmp_path_factory.mktemp("vector_scene")
    make_synthetic_bundle(root, n_gaussians=4000)
    return load_bundle(root / "bundle")


@pytest.fixture(scope="module")
def scene(bundle: Bundle) -> SceneServer:
    return SceneServer(bundle, "cpu")


def make_vector(scene: SceneServer, n: int = N, mode: str = "scored", stride: int | None = None) -> BraveVectorEnv:
    return BraveVectorEnv(scene, n, target="cube_red", width=W, height=H, max_steps=MAX_STEPS, mode=mode,
                          visibility_stride=stride)


def assert_same_obs(batched: dict[str, np.ndarray], i: int, single: dict[str, np.ndarray]) -> None:
    for key in ("rgb", "depth", "K", "world_T_cam"):
        np.testing.assert_array_equal(batched[key][i], single[key], err_msg=key)


@pytest.mark.parametrize("stride", [1, 2])
def test_vector_env_equals_independent_single_envs(bundle: Bundle, scene: SceneServer, stride: int) -> None:
    # training mode: the rewards (the target's visible area) are compared too; scored, they are all 0.
    # The server and the vector env at one visible-fraction stride (every pixel; one per 2x2 block)
    app = create_app(bundle, device="cpu", scene=scene, warm_up=False, mode="training", visibility_stride=stride)
    vec = make_vector(scene, mode="training", stride=stride)
    assert vec.manager.visibility_stride == stride
    with ServerThread(app) as server:
        singles = [BraveEnv(server.url, target="cube_red", width=W, height=H, max_steps=MAX_STEPS, mode="training")
                   for _ in range(N)]
        obs, _ = vec.reset(seed=SEED)
        for i, env in enumerate(singles):
            assert_same_obs(obs, i, env.reset(seed=SEED + i)[0])
        for step, actions in enumerate(ACTIONS, start=1):
            obs, rewards, terminated, truncated, info = vec.step(np.array(actions))
            assert not terminated.any()
            for i, env in enumerate(singles):
                o, r, term, trunc, _ = env.step(np.array(actions[i]))
                assert_same_obs(obs, i, o)
                assert rewards[i] == r and truncated[i] == trunc == (step == MAX_STEPS) and not term
        assert rewards.any()  # the moves changed what the agents see
        # NEXT_STEP autoreset: the step after truncation starts new episodes from the agents' generators
        obs, rewards, _, truncated, info = vec.step(np.array(ACTIONS[0]))
        assert not rewards.any() and not truncated.any() and not info["adjustments"].any()
        for i, env in enumerate(singles):
            seed = int(np.random.default_rng(SEED + i).integers(2**31))
            assert_same_obs(obs, i, env.reset(seed=seed)[0])
            env.close()
    vec.close()


def test_vector_env_spaces_and_api(scene: SceneServer) -> None:
    vec = make_vector(scene, 2)
    assert isinstance(vec, gymnasium.vector.VectorEnv) and vec.num_envs == 2
    assert vec.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    assert vec.single_observation_space == BraveEnv(width=W, height=H).observation_space
    assert vec.action_space.shape == (2, 6)
    with pytest.raises(RuntimeError, match="reset"):
        vec.step(np.zeros((2, 6)))
    obs, info = vec.reset(seed=0)
    assert vec.observation_space.contains(obs) and obs["rgb"].shape == (2, H, W, 3)
    assert info["_episode_id"].all() and len(set(info["episode_id"])) == 2
    with pytest.raises(BraveError, match=r"shape \(2, 6\)"):
        vec.step(np.zeros(6))
    obs, rewards, _, _, info = vec.step(vec.action_space.sample())
    assert vec.observation_space.contains(obs) and rewards.shape == (2,) and np.all(np.isfinite(rewards))
    vec.close()
    assert all(vec.manager.get(i).closed for i in info["episode_id"])


def test_sub_seeds() -> None:
    assert sub_seeds(5, 3) == [5, 6, 7] and sub_seeds(None, 2) == [None, None] and sub_seeds([1, None], 2) == [1, None]
    with pytest.raises(BraveError, match="2 seeds given for 3"):
        sub_seeds([1, 2], 3)


def test_move_many_equals_moves_one_by_one(scene: SceneServer) -> None:
    """The batched manager call: same poses, images, counters as ``move`` on twin episodes; a
    repeated episode refuses the batch before anything moves."""
    batched, single = EpisodeManager(scene), EpisodeManager(scene)
    twists = [((0, 0, 0.05), (0, 0, 0)), ((0.02, 0, 0), (0, 0.3, 0)), ((0, 0, 0), (0, 0, 0.2))]
    ids_b = [batched.reset(target="cube_red", width=W, height=H, seed=s).episode_id for s in range(3)]
    ids_s = [single.reset(target="cube_red", width=W, height=H, seed=s).episode_id for s in range(3)]
    results = batched.move_many([MoveRequest(e, v, w, 0.5) for e, (v, w) in zip(ids_b, twists)])
    for res, eid, (v, w) in zip(results, ids_s, twists):
        one = single.move(eid, v, w, 0.5)
        assert (res.accepted, res.adjustments, res.step) == (one.accepted, one.adjustments, one.step)
        np.testing.assert_array_equal(res.observation.rgb, one.observation.rgb)
        np.testing.assert_array_equal(res.observation.depth, one.observation.depth)
        np.testing.assert_array_equal(res.observation.world_T_cam, one.observation.world_T_cam)
    with pytest.raises(InvalidAction, match="once per batch"):
        batched.move_many([MoveRequest(ids_b[0], (0, 0, 0.01), (0, 0, 0), 0.5)] * 2)
    assert batched.get(ids_b[0]).steps == 1


def test_autoreset_draws_fresh_episodes_reproducibly(scene: SceneServer) -> None:
    a, b = make_vector(scene, 2), make_vector(scene, 2)
    for vec in (a, b):
        vec.reset(seed=3)
        for _ in range(MAX_STEPS + 1):
            obs, *_ = vec.step(np.zeros((2, 6)))
    obs_b, *_ = b.step(np.zeros((2, 6)))
    obs_a, *_ = a.step(np.zeros((2, 6)))
    np.testing.assert_array_equal(obs_a["world_T_cam"], obs_b["world_T_cam"])
    a.close()
    b.close()


VOLATILE = {"time", "timings_ms", "duration_s", "elapsed_s", "episode_id", "digest", "render_ms_median"}


def log_records(log_dir, episode_id: str) -> list[dict]:
    """An episode's log records without what differs between two runs (times, ids, the keyed digest)."""
    from brave6d.serve.episode_log import read_episode_log

    records = [{k: v for k, v in r.model_dump(mode="json").items() if k not in VOLATILE}
               for r in read_episode_log(log_dir / f"{episode_id}.jsonl")]
    for r in records:
        if "final_view" in r:  # the depth file is named after the episode
            assert r["final_view"].pop("depth_file") == f"{episode_id}_final_depth.png"
    return records


@pytest.mark.parametrize(("mode", "stride"), [("scored", 1), ("training", 1), ("scored", 4), ("training", 2)])
def test_vector_env_logs_and_submissions_equal_single_episodes(scene: SceneServer, tmp_path, mode: str,
                                                               stride: int) -> None:
    """Random walks of 6 agents (free, stopped and refused moves, null twists) through the vector
    env and through one ``EpisodeManager.move`` at a time: the same observations, rewards and log
    lines, and the same submissions (final view, every object's truth, the final depth file), at
    any visible-fraction stride the two share."""
    n, steps = 6, 12
    vec = BraveVectorEnv(EpisodeManager(scene, tmp_path / "vec", mode=mode, log_key=None, visibility_stride=stride),
                         n, target="cube_red", width=W, height=H, max_steps=100, mode=mode, max_linear=0.2)
    single = EpisodeManager(scene, tmp_path / "one", mode=mode, log_key=None, visibility_stride=stride)
    assert vec.manager.visibility_stride == stride
    obs, _ = vec.reset(seed=SEED)
    ids = [single.reset(target="cube_red", width=W, height=H, seed=SEED + i).episode_id for i in range(n)]
    rng = np.random.default_rng(5)
    outcomes = set()
    for step in range(steps):  # each twist twice: a move stopped at a box is refused when repeated
        if step % 2 == 0:
            actions = rng.uniform(-1, 1, (n, 6)) * (rng.random((n, 1)) > 0.15)  # some null twists
        obs, rewards, _, _, info = vec.step(actions)
        for i in range(n):
            if not actions[i].any():
                continue
            res = single.move(ids[i], actions[i, :3] * 0.2, actions[i, 3:] * 0.5, 0.5)
            outcomes.add("refused" if not res.accepted else "stopped" if res.collided else "free")
            np.testing.assert_array_equal(obs["rgb"][i], res.observation.rgb)
            np.testing.assert_array_equal(obs["world_T_cam"][i], res.observation.world_T_cam)
            assert (info["accepted"][i], info["collided"][i], info["adjustments"][i]) == (
                res.accepted, res.collided, res.adjustments)
    assert outcomes == {"free", "stopped", "refused"}
    estimate = [{"obj_id": scene.bundle.objects[0].obj_id, "R": np.eye(3).tolist(), "t_m": [0.0, 0.0, 0.3]}]
    for i in range(n):
        vec.manager.submit(vec._ids[i], estimate)
        single.submit(ids[i], estimate)
        a, b = log_records(tmp_path / "vec", vec._ids[i]), log_records(tmp_path / "one", ids[i])
        assert a == b and [r["event"] for r in a][-2:] == ["submit", "close"]
        assert (a[0]["mode"], "target_visib_fract" in a[1]) == (mode, True)
        depth = f"{{}}{'_final_depth.png'}"
        assert (tmp_path / "vec" / depth.format(vec._ids[i])).read_bytes() == (
            tmp_path / "one" / depth.format(ids[i])).read_bytes()
    vec.close()


def test_infos_are_gymnasiums_add_info(scene: SceneServer) -> None:
    """The step's infos, gathered key by key, equal gymnasium's ``_add_info`` of each sub-environment's
    info in turn (key order, masks, dtypes, values): resets, null twists and moves mixed."""
    vec = make_vector(scene, 4)
    entries = [(2, {"episode_id": "c", "accepted": True, "collided": False, "adjustments": 0}),
               (0, {"episode_id": "a", "accepted": True, "noop": True}),
               (3, {"episode_id": "d", "accepted": False, "collided": True, "adjustments": 5}),
               (1, {"episode_id": "b", "accepted": True, "collided": True, "adjustments": 2})]
    expected: dict = {}
    for i, info in entries:
        expected = vec._add_info(expected, info, i)
    got = vec._infos(entries)
    assert list(got) == list(expected)
    for key in expected:
        assert got[key].dtype == expected[key].dtype, key
        assert got[key].tolist() == expected[key].tolist(), key
    assert vec._infos([]) == {}


@pytest.mark.parametrize("bad", [
    MoveRequest("", (0, 0, float("nan")), (0, 0, 0), 0.5), MoveRequest("", (0, 0, 0.01, 0), (0, 0, 0), 0.5),
    MoveRequest("", (0, 0, 0.01), (0, 0, 99.0), 0.5), MoveRequest("", (0, 0, 0.01), (0, 0, 0), 0.0),
    MoveRequest("", "abc", (0, 0, 0), 0.5), MoveRequest("", (0, 0, 0.01), (0, 0, 0), float("inf"))])
def test_move_many_refuses_a_bad_twist_as_move_does(scene: SceneServer, bad: MoveRequest) -> None:
    """The batch's twists are checked together; a bad one among good ones gets move's own error and
    nothing moves."""
    manager = EpisodeManager(scene)
    ids = [manager.reset(target="cube_red", width=W, height=H, seed=s).episode_id for s in range(3)]
    with pytest.raises(Exception) as one:
        manager.move(ids[1], bad.linear, bad.angular, bad.duration)
    requests = [MoveRequest(ids[0], (0, 0, 0.01), (0, 0, 0), 0.5),
                MoveRequest(ids[1], bad.linear, bad.angular, bad.duration),
                MoveRequest(ids[2], (0, 0, 0.01), (0, 0, 0), 0.5)]
    with pytest.raises(type(one.value)) as many:
        manager.move_many(requests)
    assert type(many.value) is type(one.value) and str(many.value) == str(one.value)
    assert [manager.get(i).steps for i in ids] == [0, 0, 0]

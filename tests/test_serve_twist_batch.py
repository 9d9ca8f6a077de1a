"""Many twists at once (brave6d.serve.twist_batch) equal ``integrate_twist`` one by one, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.transforms import look_at, make_transform, rpy_deg_to_matrix
from brave6d.serve.geometry import CollisionWorld, MoveResult, OrientedBox, Workspace, integrate_twist
from brave6d.serve.twist_batch import integrate_twists

WS = Workspace((0.0, -0.6, 0.02), (0.94, 0.6, 0.9))
TABLE = OrientedBox("table", make_transform(np.eye(3), (0.55, 0.0, -0.375)), (0.8, 1.0, 0.75))
POST = OrientedBox("post", make_transform(rpy_deg_to_matrix((0, 0, 45)), (0.45, 0.22, 0.15)), (0.06, 0.06, 0.3))
THIN = OrientedBox("thin", make_transform(np.eye(3), (0.3, -0.2, 0.2)), (0.002, 0.2, 0.2))
WORLD = CollisionWorld((TABLE, POST, THIN), WS, camera_radius=0.02)


def assert_same(batched: MoveResult, single: MoveResult) -> None:
    np.testing.assert_array_equal(batched.world_T_cam, single.world_T_cam)
    assert (batched.refusal, batched.fraction, batched.substeps, batched.path_m) == (
        single.refusal, single.fraction, single.substeps, single.path_m)


finite = st.floats(-1.0, 1.0, allow_nan=False)
move = st.tuples(st.tuples(st.floats(0.05, 0.9), st.floats(-0.5, 0.5), st.floats(0.03, 0.6)),  # eye
                 st.lists(finite, min_size=6, max_size=6),  # twist in [-1, 1]
                 st.sampled_from([0.1, 0.5, 1.0, 0.0]),  # linear scale
                 st.sampled_from([0.5, 1e-7, 0.0, 2.0]),  # angular scale (tiny: the series branch)
                 st.sampled_from([0.5, 0.05, 1.5]), st.sampled_from(["camera", "world"]))


@settings(max_examples=40, deadline=None)
@given(st.lists(move, min_size=1, max_size=12))
def test_batched_twists_equal_single_ones(moves: list) -> None:
    """Free moves, moves stopped part-way and moves refused at once, in both frames, near the post,
    the table and a box thinner than a substep: every result equals the scalar one."""
    starts = np.stack([look_at(eye, (0.45, 0.1, 0.05)) for eye, *_ in moves])
    lin = np.array([np.array(tw[:3]) * s for _, tw, s, *_ in moves])
    ang = np.array([np.array(tw[3:]) * s for _, tw, _, s, *_ in moves])
    dur = np.array([d for *_, d, _ in moves])
    frames = [f for *_, f in moves]
    for res, T, v, w, d, f in zip(integrate_twists(WORLD, starts, lin, ang, dur, frames), starts, lin, ang, dur, frames):
        assert_same(res, integrate_twist(WORLD, T, v, w, float(d), f))


def test_random_walks_hit_every_kind_of_stop() -> None:
    """Many agents walking at random: refusals, part-way stops and free moves all occur, all equal."""
    rng = np.random.default_rng(0)
    eyes = np.column_stack([rng.uniform(0.1, 0.8, 64), rng.uniform(-0.4, 0.4, 64), rng.uniform(0.04, 0.4, 64)])
    poses = np.stack([look_at(e, (0.45, 0.0, 0.0)) for e in eyes])
    kinds = set()
    for _ in range(15):
        lin, ang = rng.uniform(-0.1, 0.1, (64, 3)), rng.uniform(-0.5, 0.5, (64, 3))
        results = integrate_twists(WORLD, poses, lin, ang, np.full(64, 0.5))
        for i, res in enumerate(results):
            assert_same(res, integrate_twist(WORLD, poses[i], lin[i], ang[i], 0.5))
            kinds.add("refused" if not res.moved else "stopped" if res.collided else "free")
        poses = np.stack([r.world_T_cam for r in results])
    assert kinds == {"refused", "stopped", "free"}


def test_invalid_moves_raise_the_scalar_error() -> None:
    T = look_at((0.3, 0.0, 0.3), (0.45, 0.0, 0.0))
    with pytest.raises(ValueError, match="too long"):
        integrate_twists(WORLD, [T, T], [[0, 0, 0.1], [0, 0, 1e3]], np.zeros((2, 3)), [0.5, 0.5])
    with pytest.raises(ValueError, match="not a finite number"):
        integrate_twists(WORLD, [T], [[np.nan, 0, 0]], np.zeros((1, 3)), [0.5])
    with pytest.raises(ValueError, match="frame"):
        integrate_twists(WORLD, [T], np.zeros((1, 3)), np.zeros((1, 3)), [0.5], ["body"])
    assert integrate_twists(WORLD, np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros((0, 3)), []) == []

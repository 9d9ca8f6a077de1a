"""The baseline's camera policies driven step by step with scripted perception (no server, no
Open3D): where the active policy moves, how it retries refused poses, that it goes back to its
start view, and that the static policy never moves."""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from brave6d.core.transforms import invert, look_at
from brave6d.evaluation.agents import (
    ActivePolicy,
    Cluster,
    EpisodeState,
    ModelCloud,
    Perception,
    PerceptionOptions,
    StaticPolicy,
    View,
    standoff_m,
)

TARGET = np.array([0.0, 0.0, 0.01])
MODEL = ModelCloud(7, np.zeros((3, 3)), np.zeros((3, 3)), 0.03, np.array([0.03, 0.02, 0.01]))
BUNDLE = {"start": {"distances_m": [0.3, 0.2]}}


def pose_from(distance: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return look_at(TARGET + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                 math.sin(el)]), TARGET)


def where(world_T_cam: np.ndarray) -> tuple[float, float, float]:
    """(distance m, azimuth deg, elevation deg) of a camera around the target."""
    v = world_T_cam[:3, 3] - TARGET
    return (float(np.linalg.norm(v)), math.degrees(math.atan2(v[1], v[0])),
            math.degrees(math.atan2(v[2], math.hypot(v[0], v[1]))))


def seen(world_T_cam: np.ndarray, box_px: int | None) -> Perception:
    """A perception of the target (at TARGET) covering a ``box_px`` square, or of nothing."""
    if box_px is None:
        return Perception(None, None, 0)
    p_cam = (invert(world_T_cam) @ np.append(TARGET, 1.0))[:3]
    return Perception(None, Cluster(np.stack([p_cam, p_cam]), np.array([[0, 0], [box_px - 1, box_px - 1]])), 1)


class ScriptedEpisode(EpisodeState):
    """An episode whose views show the target with the box sizes of ``boxes``, in turn."""

    def __init__(self, start_box: int | None, boxes: list[int | None]) -> None:
        start = pose_from(0.4, 0.0, 45.0)
        obs = SimpleNamespace(world_T_cam=start, depth=np.full((4, 4), 0.4, np.float32))
        super().__init__(MODEL, BUNDLE, [View(obs, seen(start, start_box))], TARGET.copy(), PerceptionOptions())
        self.boxes = list(boxes)

    def look(self, observation: Any) -> View:
        return View(observation, seen(observation.world_T_cam, self.boxes.pop(0)))


def drive(plan: Any, accept: Callable[[int], bool]) -> tuple[list[np.ndarray], View]:
    """Run a policy's plan, answering the i-th pose with an accepted step when ``accept(i)``;
    the start view's depth is shown again at the start pose."""
    poses: list[np.ndarray] = []
    try:
        pose = next(plan)
        while True:
            poses.append(pose)
            depth = np.full((4, 4), 0.4 if where(pose)[0] > 0.39 else 0.2, np.float32)
            pose = plan.send(SimpleNamespace(accepted=accept(len(poses) - 1),
                                             observation=SimpleNamespace(world_T_cam=pose, depth=depth)))
    except StopIteration as done:
        return poses, done.value


def test_standoff_is_the_nearest_capture_ring() -> None:
    assert standoff_m(BUNDLE) == pytest.approx(0.2)
    assert standoff_m({}) == pytest.approx(0.10)
    assert standoff_m({"start": {"distances_m": []}}) == pytest.approx(0.10)


def test_static_policy_never_moves() -> None:
    episode = ScriptedEpisode(20, [])
    poses, final = drive(StaticPolicy().explore(episode), lambda i: True)
    assert poses == [] and final is episode.views[0]


def test_active_policy_does_not_fly_towards_a_target_it_did_not_find() -> None:
    episode = ScriptedEpisode(None, [])
    poses, final = drive(ActivePolicy().explore(episode), lambda i: True)
    assert poses == [] and final is episode.views[0]


def test_active_policy_approaches_orbits_and_returns_to_its_start() -> None:
    """20 px at 0.4 m: move to half the distance (40 px aimed for), but no nearer than the nearest
    capture ring (0.2 m); 40 px is enough, so look from +-35 degrees azimuth there (the first
    try refused: retried 10 degrees higher), then go back to the start and submit there."""
    episode = ScriptedEpisode(20, [40, 40, 40])
    poses, final = drive(ActivePolicy().explore(episode), lambda i: i != 1)
    places = [tuple(round(x, 6) for x in where(p)) for p in poses]
    assert places == [(0.2, 0.0, 45.0), (0.2, 35.0, 45.0), (0.2, 35.0, 55.0), (0.2, -35.0, 45.0), (0.4, 0.0, 45.0)]
    np.testing.assert_array_equal(poses[-1], episode.views[0].observation.world_T_cam)
    assert len(episode.views) == 4  # start, approach, two side views (the refused pose is no view)
    assert final.perception is episode.views[0].perception and final.observation.world_T_cam is poses[-1]


def test_active_policy_looks_again_from_higher_when_a_move_loses_the_target() -> None:
    episode = ScriptedEpisode(20, [None, 40, 40, 40])
    poses, _ = drive(ActivePolicy().explore(episode), lambda i: True)
    places = [tuple(round(x, 6) for x in where(p)) for p in poses]
    assert places[:2] == [(0.2, 0.0, 45.0), (0.2, 0.0, 75.0)]  # relook 30 degrees higher, same distance
    assert places[2:4] == [(0.2, 35.0, 75.0), (0.2, -35.0, 75.0)] and places[4] == (0.4, 0.0, 45.0)


def test_active_policy_keeps_its_last_view_when_the_way_back_is_refused() -> None:
    episode = ScriptedEpisode(40, [40, 40])
    poses, final = drive(ActivePolicy().explore(episode), lambda i: i < 2)
    assert len(poses) == 3 and where(poses[0])[1] == pytest.approx(35.0)  # big enough: no approach
    assert final is episode.views[-1] and where(final.observation.world_T_cam)[1] == pytest.approx(-35.0)

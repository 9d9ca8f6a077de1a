"""The active policy: move closer to a target it found, look from the sides, go back to the start.

1. **Approach** (only towards a target found in the start view): while the target's cluster
   covers less than ``min_box_px`` (geometric mean of its pixel box), teleport along the line of
   sight so that it covers about ``approach_box_px`` (not more: MSPD counts pixels), keeping the
   elevation, but never nearer than the nearest capture ring (closer than any training view a
   splat shows artefacts, not detail) or 3 diameters. Refused poses are retried 10 degrees higher
   or lower, then farther. A move that loses the target is followed by one look from
   ``relook_lift_deg`` higher (a splat table seen obliquely can look centimetres higher than it is
   and swallow a small object).
2. **Orbit**: look from ``orbit_deg`` azimuth offsets at that distance (the sides one view misses).
3. **Back to the start**: return to the start pose (one more adjustment) and submit there. The
   start lies on the capture rings, where the splat was trained and its depth is trustworthy; the
   final view is where VSD (on that depth) and MSPD (in pixels) are scored. The agent fuses every
   view into the estimate given in that frame.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.transforms import look_at
from brave6d.evaluation.agents.perception import View
from brave6d.evaluation.agents.policy import EpisodeState, PolicyPlan

Array = NDArray[np.float64]
DEFAULT_STANDOFF_M = 0.10  # nearest approach when the bundle lists no capture ring
#: A look: yields poses, is sent steps, returns the accepted step (None: every try refused).
Look = Generator[Array, Any, Any]


@dataclass(frozen=True)
class ActiveOptions:
    """How the active policy moves; distances in metres, sizes in pixels of the episode's images."""

    min_box_px: float = 32.0  # move while the target's box (geometric mean of w, h) is smaller
    approach_box_px: float = 40.0  # ... aiming for about this size (MSPD, in pixels, punishes large boxes)
    max_moves: int = 4
    relook_lift_deg: float = 30.0  # a move lost the target: look again from this much higher
    orbit_deg: tuple[float, ...] = (35.0, -35.0)  # then look from these azimuth offsets too


def standoff_m(bundle: Mapping[str, Any]) -> float:
    """The nearest the agent goes: the nearest capture ring of the bundle (``GET /bundle``
    ``start.distances_m``; a splat renders artefacts where it was never trained, so a closer
    look shows less, not more), 0.10 m if the bundle lists none."""
    rings = (bundle.get("start") or {}).get("distances_m") or []
    return float(min(rings)) if rings else DEFAULT_STANDOFF_M


class ActivePolicy:
    """Approach, orbit, return to the start view (see the module docstring)."""

    def __init__(self, options: ActiveOptions = ActiveOptions()) -> None:
        self.options = options

    def explore(self, episode: EpisodeState) -> PolicyPlan:
        start = episode.views[0]
        if start.perception.cluster is None:  # never fly towards something not found
            return start
        view = yield from self._approach(episode, start)
        view = yield from self._orbit(episode, view)
        if len(episode.views) == 1:
            return view
        step = yield np.asarray(start.observation.world_T_cam, dtype=np.float64)
        if not step.accepted:
            return view
        if np.array_equal(step.observation.depth, start.observation.depth):
            return View(step.observation, start.perception)  # the same view: the same perception
        return episode.look(step.observation)

    def _approach(self, episode: EpisodeState, view: View) -> Generator[Array, Any, View]:
        """Move until the target covers ``min_box_px`` (seen from above the table's plane); when a
        move loses the target, look once more from ``relook_lift_deg`` higher, then stop."""
        o = self.options
        obs, seen = view
        relooked = False
        for _ in range(o.max_moves):
            if seen.cluster is None:
                if relooked:
                    break
                relooked = True
                eye = obs.world_T_cam[:3, 3]
                target_w = episode.target_w
                step = yield from _look_from(target_w, float(np.linalg.norm(eye - target_w)),
                                             _azimuth(eye, target_w), _elevation_deg(eye, target_w) + o.relook_lift_deg)
            else:
                episode.target_w = _to_world(obs, seen.cluster.centroid)
                if seen.cluster.box_px >= o.min_box_px and _elevation_deg(obs.world_T_cam[:3, 3], episode.target_w) >= 0:
                    break
                step = yield from self._move_towards(episode, obs, seen.cluster.box_px)
            if step is None:
                break
            obs, seen = episode.look(step.observation)
            episode.views.append(View(obs, seen))
        return View(obs, seen)

    def _orbit(self, episode: EpisodeState, view: View) -> Generator[Array, Any, View]:
        """Look at the target from ``orbit_deg`` azimuth offsets at the current distance and
        elevation; the last view seen."""
        target_w = episode.target_w
        eye = view.observation.world_T_cam[:3, 3]
        dist, azimuth, elevation = float(np.linalg.norm(eye - target_w)), _azimuth(eye, target_w), \
            _elevation_deg(eye, target_w)
        for offset in self.options.orbit_deg:
            step = yield from _look_from(target_w, dist, azimuth + math.radians(offset), elevation)
            if step is None:
                continue
            view = episode.look(step.observation)
            episode.views.append(view)
        return view

    def _move_towards(self, episode: EpisodeState, obs: Any, size_px: float) -> Look:
        """Look at the target from the distance where it covers about ``approach_box_px`` (never
        farther than now, never nearer than :func:`standoff_m` or 3 diameters), from the same
        azimuth and elevation (at least level with the target)."""
        target_w = episode.target_w
        eye = obs.world_T_cam[:3, 3]
        dist = float(np.linalg.norm(eye - target_w))
        near = max(standoff_m(episode.bundle), 3.0 * episode.model.diameter_m)
        goal = max(dist * min(size_px / self.options.approach_box_px, 1.0), near)
        if goal > 0.9 * dist:  # too little to gain for an adjustment (or it would back off)
            return None
        elevation = max(_elevation_deg(eye, target_w), 0.0)
        return (yield from _look_from(target_w, goal, _azimuth(eye, target_w), elevation))


def look_candidates(target_w: Array, distance: float, azimuth: float, elevation_deg: float) -> list[Array]:
    """Camera poses looking at ``target_w`` from ``distance``, ``azimuth`` (rad), ``elevation_deg``
    (kept within 5..88 degrees), then 10 degrees higher and lower, then the same 40 % farther: the
    order to try them in when the server refuses a pose."""
    poses = []
    for scale in (1.0, 1.4):
        for delta in (0.0, 10.0, -10.0):
            el = math.radians(float(np.clip(elevation_deg + delta, 5.0, 88.0)))
            d = np.array([math.cos(el) * math.cos(azimuth), math.cos(el) * math.sin(azimuth), math.sin(el)])
            poses.append(look_at(target_w + d * distance * scale, target_w))
    return poses


def _look_from(target_w: Array, distance: float, azimuth: float, elevation_deg: float) -> Look:
    """Teleport to look at ``target_w`` (:func:`look_candidates`, tried in order). Returns the
    accepted step (None if every try was refused)."""
    for pose in look_candidates(target_w, distance, azimuth, elevation_deg):
        step = yield pose
        if step.accepted:
            return step
    return None


def _azimuth(eye: Array, target: Array) -> float:
    return math.atan2(float(eye[1] - target[1]), float(eye[0] - target[0]))


def _to_world(obs: Any, point_cam: Array) -> Array:
    return obs.world_T_cam[:3, :3] @ point_cam + obs.world_T_cam[:3, 3]


def _elevation_deg(eye: Array, target: Array) -> float:
    """Elevation (degrees) of ``eye`` seen from ``target`` above the world's horizontal plane."""
    v = np.asarray(eye, dtype=np.float64) - np.asarray(target, dtype=np.float64)
    return math.degrees(math.atan2(float(v[2]), float(np.hypot(v[0], v[1]))))

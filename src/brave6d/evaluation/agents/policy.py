"""The camera policy protocol of the baseline agent: where to look next, and which view to submit from.

A policy is a generator: it yields the camera poses (``world_T_cam``) it wants to teleport to, is
sent back the server's step for each (accepted or refused), records the views it perceives in the
episode's state, and returns the view whose camera frame the estimate is submitted in. Written as
straight-line code, a policy's plan reads like the behaviour it implements; the agent turns it into
the decide/observe calls of :class:`brave6d.evaluation.agents.protocol.Agent`.
"""

from __future__ import annotations

from collections.abc import Generator, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from brave6d.evaluation.agents.model import ModelCloud
from brave6d.evaluation.agents.perception import PerceptionOptions, View, perceive_near

Array = NDArray[np.float64]
#: What :meth:`CameraPolicy.explore` returns: yields poses, is sent steps, returns the final view.
PolicyPlan = Generator[Array, Any, View]


@dataclass
class EpisodeState:
    """What a policy works with during one episode."""

    model: ModelCloud  # the target's model
    bundle: Mapping[str, Any]  # ``GET /bundle``: what a benchmark user is given about the scene
    views: list[View]  # every view of the episode so far (the start view first) and its perception
    target_w: Array  # where the target was last seen (world frame; at first on the start view's axis)
    perception: PerceptionOptions

    def look(self, observation: Any) -> View:
        """Perceive ``observation`` expecting the target where it was last seen; the view is not recorded."""
        return View(observation, perceive_near(observation, self.target_w, self.model, self.perception))


class CameraPolicy(Protocol):
    """Decides where the camera goes during an episode and which view the estimate is given in."""

    def explore(self, episode: EpisodeState) -> PolicyPlan:
        """The plan for one episode (see the module docstring); ``episode.views`` holds the start view."""
        ...

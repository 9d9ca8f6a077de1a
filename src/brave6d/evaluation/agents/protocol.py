"""The agent protocol: what any agent implements to run episodes against the render server."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray


@dataclass
class Submission:
    """What an agent hands in at the end of an episode: its pose estimates (in the camera frame
    of the current view, ``serve``'s client ``PoseEstimate``) and free-form notes on how it got
    there (reported beside the scores, never scored)."""

    estimates: list[Any]
    notes: Mapping[str, Any] = field(default_factory=dict)


class Agent(Protocol):
    """An agent in an episode: it observes each step the server answers, decides where the camera
    goes next (or that it is done), then submits. :func:`brave6d.evaluation.agents.episode.run_episode`
    drives it; the agent never talks to the episode endpoints itself."""

    name: str  # the agent's name on the episode logs and the leaderboard

    def observe(self, step: Any) -> None:
        """Take in the server's step (a reset starts a new episode; later steps answer :meth:`decide`)."""
        ...

    def decide(self) -> NDArray[np.float64] | None:
        """The camera pose (``world_T_cam``, 4x4, world frame) to teleport to next; None to submit."""
        ...

    def submit(self) -> Submission:
        """The episode's estimates, given in the camera frame of the last accepted view."""
        ...

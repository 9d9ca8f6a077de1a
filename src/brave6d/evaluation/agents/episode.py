"""The episode loop, written once for any :class:`~brave6d.evaluation.agents.protocol.Agent`."""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from brave6d.evaluation.agents.protocol import Agent


@dataclass
class EpisodeOutcome:
    """What one episode did, as the agent saw it (the scores come from the episode logs)."""

    episode_id: str
    agent: str
    target: str
    obj_id: int
    seed: int
    adjustments: int  # as the server counted them
    refused: int  # camera poses the server refused
    seconds: float
    estimates: list[Any]
    notes: Mapping[str, Any] = field(default_factory=dict)
    submission: dict[str, Any] = field(default_factory=dict)  # the server's reply to the submission


def scene_bundle(client: Any, cache: dict[Any, dict[str, Any]]) -> dict[str, Any]:
    """``GET /bundle`` of the client's current scene (what a benchmark user is given about it),
    fetched once per scene into ``cache``."""
    scene = getattr(client, "scene", None)
    if scene not in cache:
        cache[scene] = client.bundle(scene) if scene is not None else client.bundle()
    return cache[scene]


def run_episode(client: Any, agent: Agent, target: int | str, *, seed: int, width: int, height: int,
                scene: str | int | None = None) -> EpisodeOutcome:
    """Reset an episode on ``client`` (an :class:`~brave6d.evaluation.agents.transports.EpisodeClient`:
    ``serve``'s ``BraveClient``, gym, ROS 2 or ROS 1) for ``target`` (gt_id or
    name) of ``scene`` (None: the server's only scene) from the seeded random start, let
    ``agent`` observe and move until it decides to submit, and submit its estimates under its name."""
    t0 = time.perf_counter()
    step = client.reset(target=target, width=width, height=height, seed=seed, agent=agent.name, scene=scene)
    episode_id, info = step.episode_id, step.target
    agent.observe(step)
    refused = 0
    while (world_T_cam := agent.decide()) is not None:
        step = client.set_pose(world_T_cam)
        refused += not step.accepted
        agent.observe(step)
    submission = agent.submit()
    reply = client.submit(submission.estimates, agent=agent.name)
    return EpisodeOutcome(episode_id, agent.name, str(info.get("name", target)), int(info["obj_id"]), seed,
                          int(reply.get("adjustments", 0)), refused, time.perf_counter() - t0,
                          list(submission.estimates), submission.notes, reply)

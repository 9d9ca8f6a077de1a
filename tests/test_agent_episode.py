"""The agent protocol's episode loop and the agent registry, with a scripted client and agent
(no server, no Open3D): what ``run_episode`` sends, in which order, and what it reports."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from brave6d.core.errors import BraveError
from brave6d.evaluation.agents import (
    ACTIVE_AGENT,
    POLICIES,
    STATIC_AGENT,
    EpisodeOutcome,
    Submission,
    make_agent,
    run_episode,
)


class ScriptedClient:
    """Records the calls; refuses the set_pose calls whose index is in ``refuse``."""

    def __init__(self, refuse: set[int] = frozenset()) -> None:
        self.calls: list[tuple[str, Any]] = []
        self.refuse = refuse
        self.poses = 0

    def reset(self, **kwargs: Any) -> SimpleNamespace:
        self.calls.append(("reset", kwargs))
        return SimpleNamespace(episode_id="ep-1", action="reset", accepted=True,
                               target={"gt_id": 3, "obj_id": 7, "name": "hex_nut"})

    def set_pose(self, world_T_cam: np.ndarray) -> SimpleNamespace:
        self.calls.append(("set_pose", world_T_cam))
        accepted = self.poses not in self.refuse
        self.poses += 1
        return SimpleNamespace(episode_id="ep-1", action="set_pose", accepted=accepted, pose=world_T_cam)

    def submit(self, estimates: list[Any], agent: str | None = None) -> dict[str, Any]:
        self.calls.append(("submit", (estimates, agent)))
        return {"submitted": True, "adjustments": 2}


class ScriptedAgent:
    """Asks for ``moves`` poses (translations along x), then submits one estimate."""

    name = "scripted"

    def __init__(self, moves: int) -> None:
        self.moves = moves
        self.seen: list[tuple[str, bool]] = []

    def observe(self, step: Any) -> None:
        self.seen.append((step.action, step.accepted))

    def decide(self) -> np.ndarray | None:
        done = len(self.seen) - 1
        if done >= self.moves:
            return None
        pose = np.eye(4)
        pose[0, 3] = done
        return pose

    def submit(self) -> Submission:
        return Submission(["estimate"], {"views": len(self.seen)})


def test_run_episode_drives_an_agent_from_reset_to_submission() -> None:
    client, agent = ScriptedClient(refuse={1}), ScriptedAgent(moves=3)
    outcome = run_episode(client, agent, "hex_nut", seed=11, width=64, height=48)
    assert [name for name, _ in client.calls] == ["reset", "set_pose", "set_pose", "set_pose", "submit"]
    assert client.calls[0][1] == {"target": "hex_nut", "width": 64, "height": 48, "seed": 11, "agent": "scripted",
                                  "scene": None}
    assert [float(pose[0, 3]) for name, pose in client.calls if name == "set_pose"] == [0.0, 1.0, 2.0]
    assert agent.seen == [("reset", True), ("set_pose", True), ("set_pose", False), ("set_pose", True)]
    assert client.calls[-1][1] == (["estimate"], "scripted")
    assert isinstance(outcome, EpisodeOutcome)
    assert (outcome.episode_id, outcome.agent, outcome.target, outcome.obj_id, outcome.seed) == \
        ("ep-1", "scripted", "hex_nut", 7, 11)
    assert outcome.adjustments == 2 and outcome.refused == 1
    assert outcome.estimates == ["estimate"] and outcome.notes == {"views": 4}
    assert outcome.submission == {"submitted": True, "adjustments": 2}


def test_an_agent_that_never_moves_submits_right_after_the_reset() -> None:
    client = ScriptedClient()
    outcome = run_episode(client, ScriptedAgent(moves=0), 3, seed=0, width=32, height=24)
    assert [name for name, _ in client.calls] == ["reset", "submit"]
    assert outcome.refused == 0 and outcome.target == "hex_nut"


def test_registry_names_the_baselines_in_the_order_the_demo_runs_them(tmp_path) -> None:
    from brave6d.evaluation.agents import AgentSetup
    from brave6d.evaluation.learned import get_learn_preset
    from brave6d.evaluation.learned.model_file import write_model
    from learned_helpers import untrained_model

    # the two baselines come first (the demo runs them first); agents added later follow them
    assert list(POLICIES)[:2] == [STATIC_AGENT, ACTIVE_AGENT] == ["baseline-static", "baseline-active"]
    client = SimpleNamespace()
    write_model(tmp_path, untrained_model(get_learn_preset("tiny"), [1, 2]))  # what the learned agents load
    for name in POLICIES:
        agent = make_agent(name, client, AgentSetup(learned_model=tmp_path))
        assert agent.name == name and callable(agent.observe) and callable(agent.decide) and callable(agent.submit)
    with pytest.raises(BraveError, match="no agent named 'nope'.*baseline-static, baseline-active"):
        make_agent("nope", client)

"""The agent-run summary (``evaluation/baseline.json``): built from a leaderboard, written and read
back unchanged, and refused with the file and field named when it does not match the schema."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from pydantic import ValidationError

from brave6d.core.errors import DataError
from brave6d.evaluation.metrics import (AGENT_RUNS_FORMAT, AgentRuns, AgentRunsRow, agent_runs_from_board, agent_runs_path,
                                read_agent_runs, write_agent_runs)


def _board_agent(agent: str, ar: float, mean_adjustments: float) -> dict[str, Any]:
    """An agent row as ``AgentScore.to_json`` gives it (with the per-object table the file leaves out)."""
    return {"agent": agent, "mode": "scored", "episodes": 1, "submitted": 1, "n_targets": 1, "ar": ar, "ar_vsd": ar,
            "ar_mssd": ar,
            "ar_mspd": ar, "mean_adjustments": mean_adjustments, "mean_wall_time_s": None,
            "per_object": [{"obj_id": 2, "name": "nut"}]}


def _board_episode(agent: str, episode_id: str, ar: float, adjustments: int) -> dict[str, Any]:
    """An episode row as ``EpisodeScore.to_json`` gives it."""
    return {"agent": agent, "episode_id": episode_id, "log": f"{episode_id}.jsonl", "scene_id": 0, "im_id": 0,
            "target": "nut", "target_gt_id": 0, "obj_id": 2, "seed": 7, "submitted": True, "estimates": 1,
            "n_targets": 1, "ar": ar, "ar_vsd": ar, "ar_mssd": ar, "ar_mspd": ar, "adjustments": adjustments,
            "wall_time_s": 1.5, "target_distance_m": 0.3, "target_visib_fract": 0.9}


def _board() -> SimpleNamespace:
    """A leaderboard of two agents with one episode each, shaped like ``brave6d.evaluation.metrics.Leaderboard``."""
    agents = [_board_agent("baseline-active", 0.6, 4.0), _board_agent("baseline-static", 0.3, 0.0)]
    episodes = [_board_episode("baseline-active", "e-active", 0.6, 4),
                _board_episode("baseline-static", "e-static", 0.3, 0)]
    return SimpleNamespace(agents=[SimpleNamespace(to_json=lambda a=a: a) for a in agents],
                           episodes=[SimpleNamespace(to_json=lambda e=e: e) for e in episodes],
                           config=SimpleNamespace(metrics=("vsd", "mssd", "mspd")))


def _runs() -> AgentRuns:
    notes = {"e-active": {"found": True, "registration_method": "resting", "registration_score": 0.61}}
    return agent_runs_from_board(_board(), notes, "demo_tabletop", (320, 200))


def test_built_from_a_leaderboard() -> None:
    runs = _runs()
    assert runs.format == AGENT_RUNS_FORMAT and runs.image_size == (320, 200) and runs.bundle == "demo_tabletop"
    assert [(a.agent, a.ar, a.mean_adjustments) for a in runs.agents] == [("baseline-active", 0.6, 4.0),
                                                                          ("baseline-static", 0.3, 0.0)]
    active, static = runs.episodes
    assert (active.variant, active.object, active.gt_id, active.seed, active.adjustments) == ("active", "nut", 0, 7, 4)
    assert (active.found, active.registration_method, active.registration_score) == (True, "resting", 0.61)
    assert static.variant == "static" and static.found is None and static.registration_method is None


def test_round_trip(tmp_path: Path) -> None:
    runs = _runs()
    path = write_agent_runs(agent_runs_path(tmp_path), runs)
    assert path == tmp_path / "evaluation" / "baseline.json"
    assert read_agent_runs(path) == runs
    raw = json.loads(path.read_text())
    assert list(raw) == ["format", "mode", "bundle", "image_size", "metrics", "agents", "episodes"]
    assert raw["format"] == "brave6d-baseline/2" and raw["image_size"] == [320, 200]
    assert raw["mode"] == "scored" and raw["agents"][0]["mode"] == "scored"  # the agents' mode, carried
    assert "per_object" not in raw["agents"][0] and "log" not in raw["episodes"][0]  # board-only fields stay out
    assert [p.name for p in path.parent.iterdir()] == ["baseline.json"]  # no temporary file left behind


def _write_raw(tmp_path: Path, change: Any) -> Path:
    path = write_agent_runs(agent_runs_path(tmp_path), _runs())
    raw = json.loads(path.read_text())
    change(raw)
    path.write_text(json.dumps(raw))
    return path


@pytest.mark.parametrize(("change", "field", "says"), [
    (lambda r: r["episodes"][1].update(ar="high"), "episodes[1].ar", "valid number"),
    (lambda r: r["agents"][0].pop("mean_adjustments"), "agents[0].mean_adjustments", "Field required"),
    (lambda r: r["episodes"][0].update(AR=0.5), "episodes[0].AR", "Extra inputs are not permitted"),
    (lambda r: r.update(image_size=[320]), "image_size[1]", "Field required"),
    (lambda r: r.update(format="brave6d-baseline/3"), "format", "brave6d-baseline/3"),
    (lambda r: r.update(mode="evaluation"), "mode", "scored"),
    (lambda r: r.pop("format"), "format", "null"),
])
def test_a_malformed_file_is_refused_naming_the_file_and_field(tmp_path: Path, change: Any, field: str,
                                                               says: str) -> None:
    path = _write_raw(tmp_path, change)
    with pytest.raises(DataError) as err:
        read_agent_runs(path)
    assert str(err.value).startswith(f"{path}: field '{field}': ") and says in str(err.value)


@pytest.mark.parametrize(("text", "says"), [("[1, 2]", "must be a JSON object, got list"), ("{oops", "not valid JSON")])
def test_a_file_that_is_no_summary_is_refused_naming_it(tmp_path: Path, text: str, says: str) -> None:
    path = tmp_path / "baseline.json"
    path.write_text(text)
    with pytest.raises(DataError, match=f"^{path}: .*{says}"):
        read_agent_runs(path)


def test_nan_is_refused_before_writing() -> None:
    row = {k: v for k, v in _board_agent("a", 0.5, 1.0).items() if k != "per_object"}
    assert AgentRunsRow.model_validate(row).ar == 0.5
    with pytest.raises(ValidationError, match="ar"):
        AgentRunsRow.model_validate({**row, "ar": math.nan})

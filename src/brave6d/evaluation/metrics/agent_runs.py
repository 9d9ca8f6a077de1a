"""The agent-run summary ``<workdir>/evaluation/baseline.json``: the one owner of that file.

The demo's evaluation stage writes it (:func:`write_agent_runs`) from the leaderboard of the
agents' episodes; the report's baseline section reads it (:func:`read_agent_runs`). It holds the
leaderboard rows (``agents``, best AR first) and one row per episode (``episodes``), plus the
bundle, image size and metrics they were scored with.

The format is versioned by its ``format`` field (:data:`AGENT_RUNS_FORMAT`; version 2 adds the
mode the episodes ran in, per agent and for the run: a version-1 file reads as ``training``, the
only interface there was when it was written); a file of another version is refused, as is a field the schema does not know (``extra="forbid"``): the file has a
single writer, so an unknown field means another version of the format, never a note to skip.
Errors name the file and the field. NaN and inf are refused (they are not JSON).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, ValidationError

from brave6d.core.atomic import atomic_write_json, read_json
from brave6d.core.errors import DataError, validation_error_field

if TYPE_CHECKING:
    from brave6d.evaluation.metrics.episodes import Leaderboard

#: The ``format`` field of the files this module writes, and the formats it reads.
AGENT_RUNS_FORMAT = "brave6d-baseline/2"
READABLE_FORMATS = ("brave6d-baseline/1", AGENT_RUNS_FORMAT)
#: The episodes' mode in a version-1 file (written before the modes: its server served the truth).
VERSION_1_MODE = "training"


def agent_runs_path(workdir: Path | str) -> Path:
    """Where a demo work directory keeps the agent-run summary."""
    return Path(workdir) / "evaluation" / "baseline.json"


class _Row(BaseModel):
    """Immutable, unknown fields refused, NaN/inf refused."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class AgentRunsRow(_Row):
    """One agent's leaderboard row: BOP AR pooled over its episodes, per metric (None for a metric
    not evaluated), its mean adjustments and mean wall time (None when no episode timed itself)."""

    agent: str
    mode: Literal["scored", "training", "mixed"] = VERSION_1_MODE
    episodes: int
    submitted: int
    n_targets: int
    ar: float
    ar_vsd: float | None
    ar_mssd: float | None
    ar_mspd: float | None
    mean_adjustments: float
    mean_wall_time_s: float | None


class AgentRunsEpisode(_Row):
    """One episode: who, on which object instance from which seeded start, its own AR, its cost
    (adjustments, wall time) and how the agent's registration went (None: the agent kept no note)."""

    agent: str
    variant: Literal["active", "static"]
    object: str
    gt_id: int
    obj_id: int
    seed: int | None
    episode_id: str
    ar: float
    ar_vsd: float | None
    ar_mssd: float | None
    ar_mspd: float | None
    adjustments: int
    wall_time_s: float | None
    target_distance_m: float
    found: bool | None
    registration_method: str | None
    registration_score: float | None


class AgentRuns(_Row):
    """The whole file (field order is the file's key order)."""

    format: Literal["brave6d-baseline/1", "brave6d-baseline/2"] = AGENT_RUNS_FORMAT
    #: the mode the leaderboard ranked (version 1: training)
    mode: Literal["scored", "training", "mixed"] = VERSION_1_MODE
    bundle: str
    image_size: tuple[int, int]
    metrics: list[str]
    agents: list[AgentRunsRow]
    episodes: list[AgentRunsEpisode]


def agent_runs_from_board(board: Leaderboard, notes: Mapping[str, Mapping[str, Any]], bundle: str,
                          image_size: tuple[int, int]) -> AgentRuns:
    """The summary of a scored run: ``board``'s agent rows and episodes, each episode with the
    registration notes its agent kept (``notes`` by episode id; absent: None)."""
    agents = [AgentRunsRow.model_validate({k: v for k, v in a.to_json().items() if k != "per_object"})
              for a in board.agents]
    episodes = []
    for s in board.episodes:
        row = s.to_json()
        note = notes.get(row["episode_id"], {})
        episodes.append(AgentRunsEpisode(
            agent=row["agent"], variant="active" if row["agent"].endswith("active") else "static",
            object=row["target"], gt_id=row["target_gt_id"], obj_id=row["obj_id"], seed=row["seed"],
            episode_id=row["episode_id"], ar=row["ar"], ar_vsd=row["ar_vsd"], ar_mssd=row["ar_mssd"],
            ar_mspd=row["ar_mspd"], adjustments=row["adjustments"], wall_time_s=row["wall_time_s"],
            target_distance_m=row["target_distance_m"], found=note.get("found"),
            registration_method=note.get("registration_method"),
            registration_score=note.get("registration_score")))
    modes = {a.mode for a in agents}
    mode = getattr(board, "mode", None) or (modes.pop() if len(modes) == 1 else "mixed")
    return AgentRuns(mode=mode, bundle=bundle, image_size=image_size, metrics=list(board.config.metrics),
                     agents=agents, episodes=episodes)


def write_agent_runs(path: Path | str, runs: AgentRuns) -> Path:
    """Write ``runs`` to ``path`` atomically (indented JSON)."""
    return atomic_write_json(path, runs.model_dump(mode="json"))


def read_agent_runs(path: Path | str) -> AgentRuns:
    """Read and validate an agent-run summary; a missing, corrupt, other-version or malformed file
    raises :class:`DataError` naming the file (and the field)."""
    p = Path(path)
    data = read_json(p)
    if not isinstance(data, dict):
        raise DataError(f"{p}: an agent-run summary must be a JSON object, got {type(data).__name__}")
    if data.get("format") not in READABLE_FORMATS:
        raise DataError(f"{p}: field 'format': {json.dumps(data.get('format'))} is not supported "
                        f"(this reader reads {', '.join(map(repr, READABLE_FORMATS))})")
    try:
        return AgentRuns.model_validate(data)
    except ValidationError as exc:
        raise DataError(f"{p}: {_first_error(exc)}") from None


def _first_error(exc: ValidationError) -> str:
    """``field 'episodes[3].ar': message`` of the first error pydantic reported."""
    loc, msg = validation_error_field(exc.errors(include_url=False))
    return f"field '{loc or '<root>'}': {msg}"

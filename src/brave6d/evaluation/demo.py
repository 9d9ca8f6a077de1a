"""The demo's evaluation stage: both baselines on every demo object, scored like any agent.

``stage_evaluate`` serves the scene's bundle on a loopback port in a background thread (as the
serve stage does), in scored mode (no ground truth reaches the agents; every log signed), runs every
registered agent (:data:`brave6d.evaluation.agents.POLICIES`: the static and
the active baseline) on every object instance, :data:`EPISODES_PER_OBJECT` episodes each (all
agents from the same seeded starts), scores the episode logs
with :mod:`brave6d.evaluation.metrics.episodes` and writes, under ``<workdir>/evaluation/``:

* ``episodes/`` the episode logs and final depth images (cleared first);
* ``leaderboard.csv``/``.json``, ``episodes.csv``, ``per_object.csv`` (as ``brave6d evaluate``);
* ``baseline.json``: the agent-run summary (per agent and per episode AR and adjustments, what
  the accuracy-vs-time report plots), written through :func:`brave6d.evaluation.metrics.write_agent_runs`;
* ``ablation/``: with a learned model, the learned active agents' parts alone
  (:data:`brave6d.evaluation.agents.ABLATION_AGENTS`) from the first :data:`ABLATION_EPISODES_PER_OBJECT`
  starts: their logs and leaderboard (report section 10 pairs them with ``learned-static``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from brave6d.core.errors import BraveError

if TYPE_CHECKING:
    from brave6d.core.run_context import RunContext
    from brave6d.core.progress import StageResult
    from brave6d.evaluation.agents import AgentSetup, EpisodeOutcome
    from brave6d.evaluation.metrics import AgentRuns, Leaderboard

log = logging.getLogger(__name__)

#: Image size of the baseline episodes (the agent's pixel thresholds were chosen at this width).
IMAGE_WIDTH = 320
#: Episodes per object and variant in the full demo (seeded random starts; one in ``--quick``):
#: with one episode per object the AR of four objects swings by +-0.1 between seeds; the learned
#: agents' AR over 24 episodes has a standard error of about 0.04, over 48 about 0.03.
EPISODES_PER_OBJECT = 12
#: Episodes per object of each of the learned active agent's parts alone (``ABLATION_AGENTS``, from the
#: first of the same seeded starts as the other agents; report section 10 pairs them with learned-static):
#: about a minute for the six of them, resolving a part's gain to about +-0.04.
ABLATION_EPISODES_PER_OBJECT = 6
#: Where, under ``<workdir>/evaluation``, the ablation's logs and leaderboard go.
ABLATION_DIR = "ablation"


@dataclass
class BaselineRun:
    """The outcomes of the agents' episodes and their leaderboard."""

    outcomes: list[EpisodeOutcome]
    board: Leaderboard
    width: int
    height: int
    bundle: str


def clear_logs(folder: Path) -> None:
    """Remove the episode logs and final depth images a previous run left in ``folder``."""
    if not folder.is_dir():
        return
    for pattern in ("*.jsonl", "*_final_depth.png"):
        for p in folder.glob(pattern):
            p.unlink()


def run_baselines(bundle_dir: Path, out_dir: Path, device: str = "auto", seed: int = 0,
                  width: int = IMAGE_WIDTH, episodes_per_object: int = 1,
                  agents: Sequence[str] | None = None, learned_model: Path | None = None,
                  setup: AgentSetup | None = None) -> BaselineRun:
    """Serve ``bundle_dir`` on loopback, run the registered ``agents`` (default: every agent that can
    run, in registry order: the learned ones only with ``learned_model``) on every object,
    ``episodes_per_object`` times from seeded random starts (seed ``seed + gt_id + 1000 r`` for
    repeat ``r``: every agent starts alike), score the logs; writes nothing but the logs. ``setup``
    (default ``AgentSetup(learned_model)``) may give the learned agents a detector and pose estimator
    of the user's (:mod:`brave6d.evaluation.estimators`). The server
    runs in scored mode and the leaderboard ranks the scored episodes whose digest verifies."""
    from brave6d.evaluation.agents import LEARNED_AGENTS, AgentSetup, make_agent, run_episode, runnable_agents
    from brave6d.evaluation.metrics import models_from_bundle, read_episodes, score_episodes
    from brave6d.serve import SCORED, BraveClient, ServerThread, create_app, load_bundle

    bundle = load_bundle(bundle_dir)
    if not bundle.objects:
        raise BraveError(f"{bundle_dir}: the bundle has no objects to evaluate on")
    logs = out_dir / "episodes"
    clear_logs(logs)
    height = max(16, round(width * bundle.render.height / bundle.render.width))
    app = create_app(bundle, device=device, log_dir=logs, mode=SCORED)
    outcomes = []
    with ServerThread(app) as server, BraveClient(server.url) as client:
        setup = setup or AgentSetup(learned_model)
        if agents is None and not setup.has_estimators:
            log.info("no learned model given: the learned agents (%s) do not play", ", ".join(LEARNED_AGENTS))
        players = [make_agent(name, client, setup) for name in (agents if agents is not None else runnable_agents(setup))]
        for repeat in range(episodes_per_object):
            for obj in bundle.objects:
                for agent in players:
                    w, h = _image_size(agent, width, height, bundle)
                    outcomes.append(run_episode(client, agent, obj.gt_id, seed=seed + obj.gt_id + 1000 * repeat,
                                                width=w, height=h))
    episodes = read_episodes([logs])
    board = score_episodes(episodes, models_from_bundle(bundle, {o.obj_id for o in bundle.objects}), mode=SCORED)
    if board.not_ranked:  # every episode here ran scored on this server: one not ranked is a bug
        raise BraveError(f"{len(board.not_ranked)} of the agents' episodes cannot be ranked: "
                         + "; ".join(f"{n.episode.episode_id}: {n.reason}" for n in board.not_ranked[:3]))
    return BaselineRun(outcomes, board, width, height, bundle.name)


def learned_agent_scores(bundle_dir: Path, model: Path, out_dir: Path, episodes_per_object: int,
                         device: str = "cpu") -> dict[str, float]:
    """Each learned agent's AR and mean adjustments (key ``"<agent> adjustments"``) on ``bundle_dir``'s
    seeded episodes with the model in ``model`` (the benchmarks that price a learned setting)."""
    from brave6d.evaluation.agents import LEARNED_AGENTS

    run = run_baselines(bundle_dir, out_dir, device=device, episodes_per_object=episodes_per_object,
                        agents=list(LEARNED_AGENTS), learned_model=model)
    return {a.agent: a.ar for a in run.board.agents} | {f"{a.agent} adjustments": a.mean_adjustments
                                                         for a in run.board.agents}


def _image_size(agent: object, width: int, height: int, bundle: object) -> tuple[int, int]:
    """The episode images of ``agent``: its own ``image_width`` when it asks for one (the learned
    agents: the resolution their pose network was trained at), else ``width`` x ``height``."""
    own = getattr(agent, "image_width", None)
    if not own:
        return width, height
    render = bundle.render  # type: ignore[attr-defined]
    return int(own), max(16, round(int(own) * render.height / render.width))


def agent_runs_of(run: BaselineRun) -> AgentRuns:
    """The agent-run summary of ``run``: its leaderboard with each episode's registration notes."""
    from brave6d.evaluation.metrics import agent_runs_from_board

    return agent_runs_from_board(run.board, {o.episode_id: o.notes for o in run.outcomes}, run.bundle,
                                 (run.width, run.height))


def stage_evaluate(ctx: RunContext) -> StageResult:
    """Demo stage: run and score the registered agents on every demo object (see the module docstring)."""
    from brave6d.core.progress import StageResult
    from brave6d.evaluation.agents import ABLATION_AGENTS, ACTIVE_AGENT, LEARNED_ACTIVE_AGENT, LEARNED_STATIC_AGENT, \
        STATIC_AGENT
    from brave6d.evaluation.metrics import agent_runs_path, write_agent_runs, write_leaderboard

    from brave6d.serve import is_bundle

    bundle_dir = ctx.scene.bundle_dir
    if not is_bundle(bundle_dir):
        raise BraveError(f"{bundle_dir}: no bundle; run the export stage first")
    from brave6d.evaluation.learned.demo import demo_model_dir

    out = ctx.workdir / "evaluation"
    model = demo_model_dir(ctx.workdir)
    run = run_baselines(bundle_dir, out, device=ctx.device,
                        episodes_per_object=1 if ctx.quick else EPISODES_PER_OBJECT,
                        learned_model=model if (model / "model.pt").is_file() else None)
    write_leaderboard(run.board, out)
    write_agent_runs(agent_runs_path(ctx.workdir), agent_runs_of(run))
    log.info("baseline leaderboard:\n%s\n%s", run.board.table(), run.board.object_table())
    if (model / "model.pt").is_file():  # the learned active agent's parts alone, from the first starts
        ablation = run_baselines(bundle_dir, out / ABLATION_DIR, device=ctx.device,
                                 episodes_per_object=1 if ctx.quick else ABLATION_EPISODES_PER_OBJECT,
                                 agents=list(ABLATION_AGENTS), learned_model=model)
        write_leaderboard(ablation.board, out / ABLATION_DIR)
    scores = {a.agent: a for a in run.board.agents}
    active, static = scores.get(ACTIVE_AGENT), scores.get(STATIC_AGENT)
    l_active, l_static = scores.get(LEARNED_ACTIVE_AGENT), scores.get(LEARNED_STATIC_AGENT)
    paired = {d.active: d for d in run.board.paired}
    gain = paired.get(LEARNED_ACTIVE_AGENT)
    return StageResult("evaluate", figures={
        "mode": run.board.mode,
        "episodes": len(run.board.episodes),
        "AR active": active.ar if active else "n/a",
        "AR static": static.ar if static else "n/a",
        "mean adjustments": active.mean_adjustments if active else "n/a",
        "AR learned-active": l_active.ar if l_active else "n/a",
        "AR learned-static": l_static.ar if l_static else "n/a",
        "learned-active adjustments": l_active.mean_adjustments if l_active else "n/a",
        "learned active - static (paired)": f"{gain.mean:+.3f} +- {gain.se:.3f}" if gain else "n/a",
    })

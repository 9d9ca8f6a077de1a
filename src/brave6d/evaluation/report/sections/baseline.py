"""Report section 5: baseline Average Recall against camera adjustments.

Reads the agent-run summary ``<workdir>/evaluation/baseline.json`` through its schema
(:func:`brave6d.evaluation.metrics.read_agent_runs`): one point per episode (agent, AR, adjustments, wall
time, object) and the file's leaderboard rows, whose pooled AR and means the table shows, with the
mode the episodes ran in (``scored``: no ground truth reached the agents; a file older than the
modes: ``training``). A missing file, or one that does not match the schema, becomes a section note naming the file (and
the field), never an exception.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from brave6d.core.errors import DataError
from brave6d.core.progress import format_table
from brave6d.evaluation.metrics import AgentRuns, agent_runs_path, read_agent_runs
from brave6d.evaluation.report.measurements import Measurement, MeasurementStore, describe_machine, file_stamp, machine_info
from brave6d.evaluation.report.common import RenderedSection, finite, fmt, nan_note, num, provenance, unavailable
from brave6d.evaluation.report.protocol import MeasureInputs
from brave6d.evaluation.report.plots import legend, new_figure, plot_line, save_figure

NAME = "baseline"
PAGE = 5
TITLE = f"{PAGE}. Baseline agents: Average Recall against adjustments"
FIGURE = "baseline.png"


def collect_baseline(workdir: Path, store: MeasurementStore) -> Measurement:
    """The ``baseline`` measurement of the agent-run summary (missing or malformed file: a note)."""
    path = agent_runs_path(workdir)
    if (absent := store.require(NAME, [(path, "evaluation")])) is not None:
        return absent
    try:
        runs = read_agent_runs(path)
    except DataError as exc:
        return store.failed(NAME, str(exc))
    # reading is cheap: always collect afresh (the cached copy serves write_report)
    m = Measurement(name=NAME, key={"baseline": file_stamp(path)}, settings={"source": str(path)},
                    machine=machine_info("cpu"))
    m.points = [{"agent": e.agent, "ar": e.ar, "adjustments": float(e.adjustments), "wall_s": num(e.wall_time_s),
                 "object": e.object} for e in runs.episodes]
    m.summary = {"episodes": len(runs.episodes), "agents": agent_rows(runs), "mode": runs.mode,
                 "paired": paired_rows(runs)}
    m.status = "complete"
    store.save(m)
    return m


def agent_rows(runs: AgentRuns) -> list[dict[str, Any]]:
    """The file's leaderboard rows as the section's agent figures (AR, mean adjustments, mean wall time)."""
    return [{"agent": a.agent, "ar": a.ar, "adjustments": a.mean_adjustments, "wall_s": num(a.mean_wall_time_s),
             "episodes": a.episodes, "mode": a.mode} for a in runs.agents]


def paired_rows(runs: AgentRuns) -> list[dict[str, Any]]:
    """Each ``X-active`` agent minus ``X-static``, paired by start (``metrics.pairing``), with its verdict."""
    from brave6d.evaluation.metrics.pairing import paired_differences

    played = [(e.agent, (runs.bundle, e.gt_id, e.obj_id, e.seed), e.ar) for e in runs.episodes if e.seed is not None]
    return [{**d.to_json(), "verdict": d.verdict()} for d in paired_differences(played, [a.agent for a in runs.agents])]


# ----------------------------------------------------------------------------- rendering
def by_agent(points: list[dict[str, Any]], from_file: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """Per agent: episodes, AR, mean adjustments and mean wall time: the file's agent figures where it
    has them (``from_file``), else means over the agent's episodes (finite values only)."""
    given = {r["agent"]: r for r in from_file or []}
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for p in points:
        groups[str(p.get("agent"))].append(p)
    rows = []
    for agent, pts in sorted(groups.items()):
        row = {"agent": agent, "episodes": len(pts), "mode": given.get(agent, {}).get("mode", "n/a")}
        for k in ("ar", "adjustments", "wall_s"):
            values = finite([p.get(k) for p in pts])
            row[k] = float(values.mean()) if values.size else math.nan
            if agent in given and math.isfinite(num(given[agent].get(k))):
                row[k] = num(given[agent][k])
        rows.append(row)
    return rows


def render_baseline(m: Measurement | None, out_dir: Path) -> RenderedSection:
    """Section 5 from its measurement: scatter of episodes, agent means, table, advice."""
    if m is None or not m.usable or not m.points:
        return unavailable(TITLE, m, "Baseline episodes")
    rows = by_agent(m.points, m.summary.get("agents"))
    pooled = bool(m.summary.get("agents"))
    fig, (ax,) = new_figure(1, panel=(6.0, 3.6))
    dropped = 0
    for r in rows:
        pts = [p for p in m.points if str(p.get("agent")) == r["agent"]]
        dropped += plot_line(ax, [p.get("adjustments") for p in pts], [p.get("ar") for p in pts],
                             f"{r['agent']} (episodes)", fmt="o", alpha=0.5)
    dropped += plot_line(ax, [r["adjustments"] for r in rows], [r["ar"] for r in rows],
                         "agent (leaderboard AR)" if pooled else "agent mean", fmt="k*", ms=12)
    for r in rows:
        if math.isfinite(r["adjustments"]) and math.isfinite(r["ar"]):
            ax.annotate(r["agent"], (r["adjustments"], r["ar"]), textcoords="offset points", xytext=(8, -3), fontsize=8)
    ax.margins(x=0.2)  # room for the agent names
    ax.set_xlabel("camera position adjustments per episode")
    ax.set_ylabel("BOP Average Recall")
    legend(ax)
    png = save_figure(fig, out_dir / FIGURE, "Baseline agents: Average Recall against adjustments",
                      describe_machine(m.machine), f"source: {m.settings.get('source')}")
    table = [(r["agent"], r["mode"], r["episodes"], fmt(r["ar"], 3), fmt(r["adjustments"], 1), fmt(r["wall_s"], 1))
             for r in rows]
    ar_text = ("AR is the leaderboard's, pooled over each agent's episodes" if pooled
               else "AR is the mean over each agent's episodes")
    body = (f"From `{m.settings.get('source')}` ({m.summary.get('episodes')} episodes; {ar_text}). "
            + mode_sentence(m.summary.get("mode")) + "\n\n"
            f"![AR against adjustments]({png.name})\n\n"
            + format_table(["agent", "mode", "episodes", "AR", "mean adjustments", "wall s"], table)
            + "\n\n" + _paired_part(m.summary.get("paired") or [])
            + provenance(m) + "\n" + nan_note(dropped, "plotted episode values"))
    return RenderedSection(TITLE, body, advice_baseline(rows, m.summary.get("paired") or []), [png])


def _paired_part(paired: list[dict[str, Any]]) -> str:
    """The active agents minus their static twins, paired by start ("" when no agent has a twin)."""
    if not paired:
        return ""
    return ("Active minus static, **paired by start** (the same seeded starts; the starts' own difficulty "
            "cancels), beside the pooled AR above; resolved: at least two standard errors from zero:\n\n"
            + format_table(["active", "static", "paired starts", "active - static", "SE", "resolved?"],
                           [(r["active"], r["static"], r["pairs"], f"{num(r['mean']):+.3f}", fmt(r.get("se"), 3),
                             r.get("verdict", "")) for r in paired]) + "\n\n")


def mode_sentence(mode: Any) -> str:
    """What the run's mode means for its figures."""
    if mode == "scored":
        return ("The episodes ran in **scored** mode: no object pose, box or visible fraction reached the agents, "
                "and every log's keyed digest verified.")
    if mode == "training":
        return ("The episodes ran in **training** mode: the server gave the agents every object's ground truth, "
                "so these figures are not a benchmark result (the agents may not have read it).")
    return f"Mode: {mode or 'not recorded'}."


def advice_baseline(rows: list[dict[str, Any]], paired: Sequence[Mapping[str, Any]] = ()) -> str:
    """AR gained per extra adjustment: each active agent against its static counterpart (the same
    estimator from the start view: ``baseline-active`` / ``baseline-static``, ``learned-active-depth`` /
    ``learned-static-depth``), or, without such pairs, the agent with the most adjustments against the
    one with the fewest."""
    ok = [r for r in rows if math.isfinite(r["ar"]) and math.isfinite(r["adjustments"])]
    by_name = {r["agent"]: r for r in ok}
    pairs = [(by_name[r["agent"].replace("active", "static", 1)], r) for r in ok
             if "active" in r["agent"] and r["agent"].replace("active", "static", 1) in by_name]
    if not pairs:
        ordered = sorted(ok, key=lambda r: r["adjustments"])
        pairs = [(ordered[0], ordered[-1])] if len(ordered) >= 2 else []
    sentences = [text for lo, hi in pairs if (text := _motion_sentence(lo, hi))]
    sentences += [f"Paired by start, {r['active']} - {r['static']} = {num(r['mean']):+.3f} ± {fmt(r.get('se'), 3)} "
                  f"over {r['pairs']} starts ({r.get('verdict', '')})." for r in paired]
    return f"**Agent motion:** {' '.join(sentences)}" if sentences else ""


def _motion_sentence(lo: dict[str, Any], hi: dict[str, Any]) -> str:
    """What ``hi``'s extra adjustments over ``lo`` bought in AR ("" when it made none)."""
    extra = hi["adjustments"] - lo["adjustments"]
    gain = hi["ar"] - lo["ar"]
    if extra <= 0:
        return ""
    head = f"{hi['agent']} spends {fmt(extra, 1)} more adjustments per episode than {lo['agent']}"
    if gain > 0:
        return (f"{head} for {fmt(gain, 3)} more AR ({fmt(lo['ar'], 3)} -> {fmt(hi['ar'], 3)}: "
                f"{fmt(gain / extra, 3)} AR per adjustment).")
    return (f"{head} and scores {fmt(-gain, 3)} less AR ({fmt(lo['ar'], 3)} -> {fmt(hi['ar'], 3)}): on this scene "
            "the extra moves did not pay.")


class BaselineSection:
    """Section 5 behind the :class:`~brave6d.evaluation.report.protocol.Section` protocol (no settings:
    it reads the agent-run summary)."""

    name, page, title, figure = NAME, PAGE, TITLE, FIGURE

    def settings(self, quick: bool) -> None:
        return None

    def measure(self, inputs: MeasureInputs, settings: None) -> Measurement:
        return collect_baseline(inputs.workdir, inputs.store)

    def render(self, measurements: Mapping[str, Measurement | None], out_dir: Path) -> RenderedSection:
        return render_baseline(measurements.get(NAME), out_dir)


SECTION = BaselineSection()

"""Episode scoring: render-server episode logs -> BOP Average Recall and adjustments per agent.

Each episode is one BOP "image": its final view (the view current when the agent submitted) with
the ground truth the server logged at that moment (the log's ``submit`` record, read through
``brave6d.serve.read_episode_log``: the log schema is serve's, versioned). Image
ids are deterministic: agents sorted by name get ``scene_id`` 1, 2, ...; within an agent the
episodes sorted by (start time, episode id) get ``im_id`` 0, 1, ...

Targets (documented choices):

* By default only the episode's target instance is a target: the agent was asked for that one
  object. With ``all_objects`` every instance visible in the final view (``visib_fract >=
  visib_gt_min``) is a target as well.
* The episode's target always counts, whatever its visibility in the final view, so that an
  agent cannot dodge a hard target by looking away (its visible fraction is raised to the
  threshold for BOP's target filter; VSD uses the depth images, never ``visib_fract``).
* An episode that ended without a submission (closed, expired, log cut short) scores 0: its
  target counts, without estimates, at the last logged camera pose.

VSD's test depth is the final depth the server logged: the bundle's reference geometry at the
final pose (the geometry that the splat's training noise cannot move), or, for a bundle without
one, the splat's depth (``final_view.depth_source``; older logs: the splat). Every episode's
score says which (``test_depth``), the leaderboard lists the geometries it holds, and scoring
episodes of both together is logged as a warning: their VSD is not measured on the same thing.

Agent AR is BOP's AR over the agent's episodes (one call of :func:`evaluate_bop19` per episode,
summed exactly: recall is matched targets / targets, so per-episode true-positive counts add up).
The same exact sums give each agent's AR per scene (episodes of one served scene: the log's
``scene``, else its bundle's name) and per object category (the targets whose object belongs to
the category, from the ``categories`` map ``obj_id -> category`` the bundles give).

Modes and digests (docs/SECURITY.md): every episode carries the mode its server ran in
(``scored``: no ground truth reached the agent; ``training``; a log older than the modes counts as
training, since its server served the truth) and what its keyed digest says (``verified``,
``unsigned``, ``unknown key``; a log changed after the server wrote it is refused, naming the
episode). With ``mode`` given, :func:`score_episodes` ranks only the episodes of that mode (scored:
only those whose digest verifies, :func:`rank_episodes`) and lists the others apart, each with why.
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import read_png
from brave6d.core.errors import DataError
from brave6d.evaluation.metrics.recall import METRICS, BopScores, EvalConfig, Estimate, GTInstance, ObjectModel, evaluate_bop19
from brave6d.evaluation.metrics.depth_renderer import DepthRenderer
from brave6d.evaluation.metrics.pairing import PairedDifference, paired_differences, paired_table, played_of_scores
from brave6d.serve import (
    SCORED,
    TRAINING,
    ActionRecord,
    CloseRecord,
    DigestRecord,
    LoggedEstimate,
    LogKey,
    ObjectState,
    ResetRecord,
    SubmitRecord,
    check_log_digest,
    evaluation_log_key,
    read_episode_log,
)

log = logging.getLogger(__name__)

UNKNOWN_AGENT = "unknown"
UNKNOWN_SCENE = "unknown"
UNKNOWN_CATEGORY = "uncategorised"


# ----------------------------------------------------------------------------- reading logs
@dataclass(frozen=True)
class EpisodeRecord:
    """What scoring needs from one episode log (read through serve's versioned log schema)."""

    episode_id: str
    path: Path
    agent: str
    bundle: str | None
    bundle_root: str | None
    scene: str  # the served scene's name (version-1 logs: the bundle's name)
    scene_id: int | None
    target: ObjectState
    submitted: bool
    adjustments: int
    steps: int
    refusals: int
    wall_time_s: float | None
    started: str
    seed: int | None
    K: NDArray[np.float64]
    width: int
    height: int
    objects: tuple[ObjectState, ...]
    estimates: tuple[LoggedEstimate, ...]
    depth_path: Path | None
    #: the geometry of the test depth: "reference" or "splat" (None: not submitted, no depth scored)
    test_depth: str | None = None
    #: the server's mode (logs older than the modes: training) and what the log's digest says
    mode: str = TRAINING
    digest: str = "unsigned"
    key_id: str | None = None


def find_episode_logs(paths: Iterable[Path | str]) -> list[Path]:
    """The ``*.jsonl`` logs of the given files and folders (folders: sorted, not recursive)."""
    out: list[Path] = []
    for item in paths:
        p = Path(item)
        if p.is_dir():
            out.extend(sorted(p.glob("*.jsonl")))
        elif p.is_file():
            out.append(p)
        else:
            raise DataError(f"{p}: episode log file or folder not found")
    if not out:
        raise DataError(f"no episode logs (*.jsonl) in {', '.join(str(p) for p in paths)}")
    return list(dict.fromkeys(out))


def _seconds_between(a: str | None, b: str | None) -> float | None:
    try:
        t0 = _dt.datetime.fromisoformat(str(a))
        t1 = _dt.datetime.fromisoformat(str(b))
    except ValueError:
        return None
    return max(0.0, (t1 - t0).total_seconds())


#: ``read_episode``'s ``log_key`` default: the default key file's key when this machine has one.
DEFAULT_KEY = "default"


def read_episode(path: Path | str, log_key: LogKey | str | None = DEFAULT_KEY) -> EpisodeRecord:
    """One episode log (JSONL written by the render server) -> :class:`EpisodeRecord`, its digest
    checked with ``log_key`` (default: :func:`brave6d.serve.evaluation_log_key`; None: no key, a signed
    log reads as ``unknown key``). A log (or final depth image) changed after the server wrote it is
    a :class:`DataError` naming the file and the episode."""
    p = Path(path)
    key = evaluation_log_key() if log_key == DEFAULT_KEY else log_key
    records = read_episode_log(p)
    reset = records[0]
    assert isinstance(reset, ResetRecord)  # read_episode_log refuses a log that does not start with one
    target_gt_id = reset.target.gt_id
    submit = next((r for r in records if isinstance(r, SubmitRecord)), None)
    signed = records[-1].signed() if isinstance(records[-1], DigestRecord) else None
    depth = p.with_name(submit.final_view.depth_file) if submit is not None and submit.final_view.depth_file else None
    check = check_log_digest(p, key if isinstance(key, LogKey) else None, reset.episode_id, signed, depth,
                             submit.final_view.depth_sha256 if submit is not None else None)
    agent = str((submit.agent if submit is not None else None) or reset.agent or UNKNOWN_AGENT)
    common = {"episode_id": reset.episode_id, "path": p, "agent": agent, "bundle": reset.bundle,
              "scene": reset.scene or reset.bundle or UNKNOWN_SCENE, "scene_id": reset.scene_id,
              "started": reset.time, "seed": reset.seed, "mode": reset.mode or TRAINING, "digest": check.status,
              "key_id": check.key_id}
    if submit is not None:
        view = submit.final_view
        target = next((o for o in submit.objects if o.gt_id == target_gt_id), None)
        if target is None:
            raise DataError(f"{p}: submit: the target (gt_id {target_gt_id}) is not among 'objects'")
        wall = submit.elapsed_s if submit.elapsed_s is not None else _seconds_between(reset.time, submit.time)
        return EpisodeRecord(
            **common, bundle_root=submit.bundle_root, target=target, submitted=True,
            adjustments=submit.adjustments, steps=submit.steps, refusals=submit.refusals, wall_time_s=wall,
            K=view.K, width=view.width, height=view.height, objects=tuple(submit.objects),
            estimates=tuple(submit.estimates),
            depth_path=p.with_name(view.depth_file) if view.depth_file else None,
            test_depth=view.depth_source or "splat")
    # No submission: the target counts with no estimate, at the last logged pose.
    last = next((r for r in reversed(records)
                 if isinstance(r, (ResetRecord, ActionRecord)) and r.target_cam_T_obj is not None), None)
    if last is None:
        raise DataError(f"{p}: reset: field 'target_cam_T_obj' is missing (needed to score an unsubmitted episode)")
    target = ObjectState(gt_id=target_gt_id, obj_id=reset.target.obj_id, name=reset.target.name, is_target=True,
                         cam_T_obj=last.target_cam_T_obj, visib_fract=last.target_visib_fract)
    actions = [r for r in records if isinstance(r, ActionRecord)]
    adjustments = max((r.adjustments for r in records if isinstance(r, (ActionRecord, CloseRecord))), default=0)
    return EpisodeRecord(
        **common, bundle_root=None, target=target, submitted=False, adjustments=max(adjustments, 0),
        steps=len(actions), refusals=sum(1 for r in actions if r.refusal and not r.accepted),
        wall_time_s=_seconds_between(reset.time, records[-1].time),
        K=reset.K, width=reset.width, height=reset.height, objects=(target,), estimates=(), depth_path=None)


def read_episodes(paths: Iterable[Path | str], log_key: LogKey | str | None = DEFAULT_KEY) -> list[EpisodeRecord]:
    """Every episode of the given log files and folders (see :func:`find_episode_logs`), digests
    checked with ``log_key`` (see :func:`read_episode`)."""
    key = evaluation_log_key() if log_key == DEFAULT_KEY else log_key
    return [read_episode(p, key) for p in find_episode_logs(paths)]


@dataclass(frozen=True)
class NotRanked:
    """An episode a leaderboard lists apart, and why."""

    episode: EpisodeRecord
    reason: str

    def to_json(self) -> dict[str, Any]:
        e = self.episode
        return {"agent": e.agent, "episode_id": e.episode_id, "log": e.path.name, "mode": e.mode,
                "digest": e.digest, "reason": self.reason}


def rank_episodes(episodes: Sequence[EpisodeRecord], mode: str = SCORED
                  ) -> tuple[list[EpisodeRecord], list[NotRanked]]:
    """The episodes a ``mode`` leaderboard ranks, and the others with why: a scored board ranks the
    scored episodes whose digest verifies; a training board the training episodes (a development
    board: unsigned logs count)."""
    ranked: list[EpisodeRecord] = []
    apart: list[NotRanked] = []
    for e in episodes:
        if e.mode != mode:
            why = ("training mode: the server gave the agent the ground truth" if e.mode == TRAINING
                   else f"{e.mode} mode")
            apart.append(NotRanked(e, why))
        elif mode == SCORED and e.digest == "unknown key":
            apart.append(NotRanked(e, f"signed with key {e.key_id}, which this machine does not hold (pass the "
                                      "server's key: --log-key FILE)"))
        elif mode == SCORED and e.digest != "verified":
            apart.append(NotRanked(e, "no digest: the server did not close the episode (stopped first), so its "
                                      "log cannot be checked"))
        else:
            ranked.append(e)
    return ranked, apart


# ----------------------------------------------------------------------------- BOP inputs
def assign_image_ids(episodes: Sequence[EpisodeRecord]) -> dict[str, tuple[int, int]]:
    """``episode_id -> (scene_id, im_id)``: agents by name -> scene 1, 2, ...; episodes by
    (start time, id) -> image 0, 1, ... within their agent."""
    agents = sorted({e.agent for e in episodes})
    out: dict[str, tuple[int, int]] = {}
    for scene_id, agent in enumerate(agents, start=1):
        mine = sorted((e for e in episodes if e.agent == agent), key=lambda e: (e.started, e.episode_id))
        for im_id, e in enumerate(mine):
            if e.episode_id in out:
                raise DataError(f"{e.path}: episode {e.episode_id} appears twice")
            out[e.episode_id] = (scene_id, im_id)
    return out


def _depth_loader(path: Path | None, episode: EpisodeRecord) -> Any:
    def load() -> NDArray[np.float64]:
        if path is None:
            raise DataError(f"{episode.path}: no final depth image was logged (VSD needs it)")
        depth = read_png(path, expect="depth")
        if depth.shape != (episode.height, episode.width):
            raise DataError(f"{path}: depth is {depth.shape[1]}x{depth.shape[0]}, the episode's view is "
                            f"{episode.width}x{episode.height}")
        return depth.astype(np.float64)  # uint16 mm

    return load


def episode_to_bop(episode: EpisodeRecord, scene_id: int, im_id: int, visib_gt_min: float = 0.1,
                   all_objects: bool = False) -> tuple[list[GTInstance], list[Estimate]]:
    """The BOP ground truth and estimates of one episode (BOP units: mm); see the module docstring."""
    loader = _depth_loader(episode.depth_path, episode)
    gts = []
    for o in episode.objects:
        if o.is_target:
            visib = max(o.visib_fract or 0.0, visib_gt_min)
        elif all_objects:
            visib = o.visib_fract or 0.0
        else:
            continue
        gts.append(GTInstance(scene_id, im_id, o.obj_id, o.cam_T_obj[:3, :3], o.cam_T_obj[:3, 3] * 1000.0, visib,
                              episode.K, (episode.width, episode.height), loader))
    run_time = episode.wall_time_s if episode.wall_time_s is not None else -1.0
    ests = [Estimate(scene_id, im_id, e.obj_id, e.score, e.R, e.t_m * 1000.0, run_time) for e in episode.estimates]
    return gts, ests


def models_from_bundle(bundle: Any, obj_ids: Iterable[int] | None = None) -> dict[int, ObjectModel]:
    """BOP object models (mm, faces, diameter, symmetries) of a loaded ``brave6d.serve.bundle.Bundle``."""
    from brave6d.evaluation.metrics.bop_results import load_ply_mesh

    wanted = None if obj_ids is None else {int(i) for i in obj_ids}
    out: dict[int, ObjectModel] = {}
    for o in bundle.objects:
        if o.obj_id in out or (wanted is not None and o.obj_id not in wanted):
            continue
        vertices, faces = load_ply_mesh(bundle.model_path(o))
        out[o.obj_id] = ObjectModel(o.obj_id, vertices, o.diameter_mm, faces, o.symmetries_discrete_mm,
                                    o.symmetries_continuous)
    return out


# ----------------------------------------------------------------------------- scores
@dataclass
class EpisodeScore:
    """One episode's scores (its own BOP AR) and costs."""

    episode: EpisodeRecord
    scene_id: int
    im_id: int
    scores: BopScores

    def to_json(self) -> dict[str, Any]:
        e = self.episode
        return {"agent": e.agent, "episode_id": e.episode_id, "log": e.path.name, "scene": e.scene,
                "served_scene_id": e.scene_id, "scene_id": self.scene_id,
                "im_id": self.im_id, "target": e.target.name, "target_gt_id": e.target.gt_id,
                "obj_id": e.target.obj_id, "seed": e.seed, "submitted": e.submitted, "estimates": len(e.estimates),
                "n_targets": self.scores.n_targets, "ar": self.scores.ar, "ar_vsd": self.scores.ar_vsd,
                "ar_mssd": self.scores.ar_mssd, "ar_mspd": self.scores.ar_mspd,
                "adjustments": e.adjustments, "wall_time_s": e.wall_time_s, "test_depth": e.test_depth,
                "mode": e.mode, "digest": e.digest,
                "target_distance_m": float(np.linalg.norm(e.target.cam_T_obj[:3, 3])),
                "target_visib_fract": e.target.visib_fract}


@dataclass
class AgentScore:
    """An agent's BOP AR over its episodes, per metric and per object, and its mean costs."""

    agent: str
    episodes: int
    submitted: int
    n_targets: int
    ar: float
    ar_per_metric: dict[str, float]
    mean_adjustments: float
    mean_wall_time_s: float | None
    per_object: dict[int, dict[str, Any]] = field(default_factory=dict)
    #: the mode of the agent's episodes ("mixed" when they ran in both)
    mode: str = TRAINING

    def to_json(self) -> dict[str, Any]:
        return {"agent": self.agent, "mode": self.mode, "episodes": self.episodes, "submitted": self.submitted,
                "n_targets": self.n_targets, "ar": self.ar,
                **{f"ar_{m}": self.ar_per_metric.get(m) for m in METRICS},
                "mean_adjustments": self.mean_adjustments, "mean_wall_time_s": self.mean_wall_time_s,
                "per_object": [self.per_object[k] for k in sorted(self.per_object)]}


@dataclass(frozen=True)
class GroupScore:
    """An agent's exact BOP AR over one group of its targets: a scene's, or an object category's."""

    agent: str
    group: str
    episodes: int
    n_targets: int
    ar: float
    ar_per_metric: dict[str, float]
    mean_adjustments: float

    def to_json(self, key: str) -> dict[str, Any]:
        return {"agent": self.agent, key: self.group, "episodes": self.episodes, "n_targets": self.n_targets,
                "ar": self.ar, **{f"ar_{m}": self.ar_per_metric.get(m) for m in METRICS},
                "mean_adjustments": self.mean_adjustments}


@dataclass
class Leaderboard:
    """Agents ranked by AR (then name), with every episode's scores, and each agent's AR per
    served scene and per object category."""

    agents: list[AgentScore]
    episodes: list[EpisodeScore]
    config: EvalConfig
    all_objects: bool = False
    scenes: list[GroupScore] = field(default_factory=list)
    categories: list[GroupScore] = field(default_factory=list)
    #: the mode ranked (None: every episode given, whatever its mode) and the episodes listed apart
    mode: str | None = None
    not_ranked: list[NotRanked] = field(default_factory=list)

    @property
    def paired(self) -> list[PairedDifference]:
        """Each ``X-active`` agent minus its ``X-static`` twin, paired by start (``metrics.pairing``)."""
        return paired_differences(played_of_scores(self.episodes), [a.agent for a in self.agents])

    def paired_table(self) -> str:
        """The paired differences as a table with their verdicts; "" when no agent has a static twin."""
        return paired_table(self.paired) if self.paired else ""

    def group_table(self, kind: str) -> str:
        """The per-scene (``kind="scene"``) or per-category (``"category"``) table."""
        from brave6d.core.progress import format_table

        groups = self.scenes if kind == "scene" else self.categories
        rows = [[g.agent, g.group, g.episodes, g.n_targets, g.ar, *(_cell(g.ar_per_metric.get(m)) for m in METRICS),
                 g.mean_adjustments] for g in groups]
        return format_table(["agent", kind, "episodes", "targets", "AR", "AR_VSD", "AR_MSSD", "AR_MSPD",
                             "mean adjustments"], rows)

    def table(self) -> str:
        from brave6d.core.progress import format_table

        rows = [[a.agent, a.mode, a.episodes, a.ar, *(_cell(a.ar_per_metric.get(m)) for m in METRICS),
                 a.mean_adjustments, _cell(a.mean_wall_time_s)] for a in self.agents]
        return format_table(["agent", "mode", "episodes", "AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "mean adjustments",
                             "wall time s"], rows)

    def not_ranked_table(self) -> str:
        """The episodes listed apart (agent, episode, mode, digest, why); "" when there are none."""
        from brave6d.core.progress import format_table

        if not self.not_ranked:
            return ""
        return format_table(["agent", "episode", "mode", "digest", "not ranked because"],
                            [[n.episode.agent, n.episode.episode_id, n.episode.mode, n.episode.digest, n.reason]
                             for n in self.not_ranked])

    def object_table(self) -> str:
        from brave6d.core.progress import format_table

        rows = [[a.agent, o["obj_id"], o["name"], o["n_targets"], o["ar"],
                 *(_cell(o.get(f"ar_{m}")) for m in METRICS), o["mean_adjustments"]]
                for a in self.agents for o in (a.per_object[k] for k in sorted(a.per_object))]
        return format_table(["agent", "obj_id", "object", "targets", "AR", "AR_VSD", "AR_MSSD", "AR_MSPD",
                             "mean adjustments"], rows)

    def to_json(self) -> dict[str, Any]:
        return {"format": "brave6d-leaderboard/1", "mode": self.mode, "metrics": list(self.config.metrics),
                "targets": "every visible instance" if self.all_objects else "the episode's target",
                "visib_gt_min": self.config.visib_gt_min, "test_depth": test_depth_geometries(self.episodes),
                "agents": [a.to_json() for a in self.agents],
                "per_scene": [g.to_json("scene") for g in self.scenes],
                "per_category": [g.to_json("category") for g in self.categories],
                "episodes": [e.to_json() for e in self.episodes],
                "not_ranked": [n.to_json() for n in self.not_ranked],
                "paired": [d.to_json() for d in self.paired]}


def test_depth_geometries(scored: Sequence[EpisodeScore]) -> list[str]:
    """The geometries the scored episodes' test depths come from ("reference", "splat"), sorted."""
    return sorted({s.episode.test_depth for s in scored if s.episode.test_depth is not None})


def _cell(value: float | None) -> Any:
    return "n/a" if value is None else value


def _weighted(pairs: Sequence[tuple[int, float]]) -> float:
    total = sum(n for n, _ in pairs)
    return float(sum(n * v for n, v in pairs) / total) if total > 0 else 0.0


def _mean_or_none(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def _agent_score(agent: str, scored: Sequence[EpisodeScore], metrics: Sequence[str]) -> AgentScore:
    """Exact BOP AR over the agent's episodes from per-episode true-positive counts."""
    n_targets = sum(s.scores.n_targets for s in scored)
    per_metric = _exact_ar(scored, metrics)
    per_object: dict[int, dict[str, Any]] = {}
    for obj_id in sorted({o for s in scored for o in s.scores.per_object}):
        mine = [s for s in scored if obj_id in s.scores.per_object]
        objs = [s.scores.per_object[obj_id] for s in mine]
        name = next((o.name for s in mine for o in s.episode.objects if o.obj_id == obj_id), "")
        row: dict[str, Any] = {"obj_id": obj_id, "name": name, "episodes": len(mine),
                               "n_targets": sum(o.n_targets for o in objs)}
        for m in metrics:
            row[f"ar_{m}"] = _weighted([(o.n_targets, o.ar_per_metric[m]) for o in objs])
        row["ar"] = float(np.mean([row[f"ar_{m}"] for m in metrics]))
        row["mean_adjustments"] = float(np.mean([s.episode.adjustments for s in mine]))
        per_object[obj_id] = row
    modes = {s.episode.mode for s in scored}
    return AgentScore(agent, len(scored), sum(1 for s in scored if s.episode.submitted), n_targets,
                      float(np.mean(list(per_metric.values()))), per_metric,
                      float(np.mean([s.episode.adjustments for s in scored])) if scored else 0.0,
                      _mean_or_none([s.episode.wall_time_s for s in scored]), per_object,
                      modes.pop() if len(modes) == 1 else "mixed")


def _exact_ar(scored: Sequence[EpisodeScore], metrics: Sequence[str]) -> dict[str, float]:
    """AR per metric over ``scored`` from the per-episode true-positive counts (exact, not an average of ARs)."""
    n_targets = sum(s.scores.n_targets for s in scored)
    out = {}
    for m in metrics:
        counts = [np.asarray(s.scores.metrics[m].tp_counts, dtype=np.float64) for s in scored]
        tp = np.sum(counts, axis=0) if counts else np.zeros(1)
        out[m] = float(np.mean(tp / n_targets)) if n_targets > 0 else 0.0
    return out


def _scene_scores(agent: str, scored: Sequence[EpisodeScore], metrics: Sequence[str]) -> list[GroupScore]:
    out = []
    for scene in sorted({s.episode.scene for s in scored}):
        mine = [s for s in scored if s.episode.scene == scene]
        per_metric = _exact_ar(mine, metrics)
        out.append(GroupScore(agent, scene, len(mine), sum(s.scores.n_targets for s in mine),
                              float(np.mean(list(per_metric.values()))), per_metric,
                              float(np.mean([s.episode.adjustments for s in mine]))))
    return out


def _category_scores(agent: str, scored: Sequence[EpisodeScore], metrics: Sequence[str],
                     categories: Mapping[int, str]) -> list[GroupScore]:
    """Per category: the targets of its objects (per-object recalls weighted by their target counts,
    which is exact: every object's recall is its true positives over its targets)."""
    def category(obj_id: int) -> str:
        return categories.get(obj_id) or UNKNOWN_CATEGORY

    out = []
    for cat in sorted({category(o) for s in scored for o in s.scores.per_object}):
        objs = [o for s in scored for k, o in s.scores.per_object.items() if category(k) == cat]
        per_metric = {m: _weighted([(o.n_targets, o.ar_per_metric[m]) for o in objs]) for m in metrics}
        mine = [s for s in scored if category(s.episode.target.obj_id) == cat]
        out.append(GroupScore(agent, cat, len(mine), sum(o.n_targets for o in objs),
                              float(np.mean(list(per_metric.values()))), per_metric,
                              float(np.mean([s.episode.adjustments for s in mine])) if mine else 0.0))
    return out


def score_episodes(episodes: Sequence[EpisodeRecord], models: Mapping[int, ObjectModel],
                   config: EvalConfig | None = None, all_objects: bool = False,
                   renderer: DepthRenderer | None = None, categories: Mapping[int, str] | None = None,
                   mode: str | None = None) -> Leaderboard:
    """BOP AR per episode and per agent, and each agent's AR per scene and per object category
    (``categories``: ``obj_id -> category``; objects not in it count as uncategorised); see the
    module docstring. ``models`` in mm. ``mode``: rank only the episodes :func:`rank_episodes` ranks
    for it and list the others apart (None: score every episode given)."""
    apart: list[NotRanked] = []
    if mode is not None:
        episodes, apart = rank_episodes(episodes, mode)
    cfg = config or EvalConfig()
    ids = assign_image_ids(episodes)
    used = {e.test_depth for e in episodes if e.test_depth is not None}
    if len(used) > 1:
        n_splat = sum(1 for e in episodes if e.test_depth == "splat")
        log.warning("%d of %d submitted episodes were scored on the splat's depth (bundles without a reference "
                    "geometry), the others on the reference geometry: their VSD is not measured on the same "
                    "surface (see each episode's test_depth)", n_splat,
                    sum(1 for e in episodes if e.test_depth is not None))
    ren = renderer if renderer is not None else (DepthRenderer() if "vsd" in cfg.metrics else None)
    scored = []
    for e in sorted(episodes, key=lambda e: ids[e.episode_id]):
        scene_id, im_id = ids[e.episode_id]
        gts, ests = episode_to_bop(e, scene_id, im_id, cfg.visib_gt_min, all_objects)
        try:
            scores = evaluate_bop19(gts, ests, models, cfg, renderer=ren, keep_errors=False)
        except DataError as exc:
            raise DataError(f"{e.path}: {exc}") from None
        scored.append(EpisodeScore(e, scene_id, im_id, scores))
    agents = [_agent_score(a, [s for s in scored if s.episode.agent == a], cfg.metrics)
              for a in sorted({e.agent for e in episodes})]
    for a in agents:
        if not all(math.isfinite(v) for v in (a.ar, *a.ar_per_metric.values())):
            raise DataError(f"agent {a.agent}: a score is not finite (this is a bug)")
    agents.sort(key=lambda a: (-a.ar, a.agent))
    scenes, cats = [], []
    for a in agents:
        mine = [s for s in scored if s.episode.agent == a.agent]
        scenes += _scene_scores(a.agent, mine, cfg.metrics)
        cats += _category_scores(a.agent, mine, cfg.metrics, categories or {})
    return Leaderboard(agents, scored, cfg, all_objects, scenes, cats, mode, apart)


# ----------------------------------------------------------------------------- files
LEADERBOARD_COLUMNS = ("agent", "mode", "episodes", "submitted", "n_targets", "ar", "ar_vsd", "ar_mssd", "ar_mspd",
                       "mean_adjustments", "mean_wall_time_s")
EPISODE_COLUMNS = ("agent", "episode_id", "scene", "served_scene_id", "scene_id", "im_id", "target", "obj_id", "seed", "submitted", "estimates",
                   "ar", "ar_vsd", "ar_mssd", "ar_mspd", "adjustments", "wall_time_s", "target_distance_m", "test_depth",
                   "mode", "digest")
NOT_RANKED_COLUMNS = ("agent", "episode_id", "log", "mode", "digest", "reason")
PAIRED_COLUMNS = ("active", "static", "pairs", "mean", "se", "active_ar", "static_ar", "resolved", "pairs_to_resolve")
GROUP_COLUMNS = ("episodes", "n_targets", "ar", "ar_vsd", "ar_mssd", "ar_mspd", "mean_adjustments")
OBJECT_COLUMNS = ("agent", "obj_id", "name", "episodes", "n_targets", "ar", "ar_vsd", "ar_mssd", "ar_mspd",
                  "mean_adjustments")


def _csv_text(columns: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> str:
    import csv
    import io

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in columns})
    return buf.getvalue()


def write_leaderboard(board: Leaderboard, out_dir: Path | str) -> list[Path]:
    """Write ``leaderboard.csv``/``.json``, ``episodes.csv``, ``per_object.csv``, ``per_scene.csv``,
    ``per_category.csv``, ``not_ranked.csv`` (the episodes listed apart) and ``paired.csv`` (active minus
    static, paired by start; atomic)."""
    from brave6d.core.atomic import atomic_write_json, atomic_write_text

    out = Path(out_dir)
    agents = [a.to_json() for a in board.agents]
    objects = [{"agent": a.agent, **row} for a in board.agents for row in a.to_json()["per_object"]]
    return [
        atomic_write_text(out / "leaderboard.csv", _csv_text(LEADERBOARD_COLUMNS, agents)),
        atomic_write_json(out / "leaderboard.json", board.to_json()),
        atomic_write_text(out / "episodes.csv", _csv_text(EPISODE_COLUMNS, (e.to_json() for e in board.episodes))),
        atomic_write_text(out / "per_object.csv", _csv_text(OBJECT_COLUMNS, objects)),
        atomic_write_text(out / "per_scene.csv", _csv_text(("agent", "scene", *GROUP_COLUMNS),
                                                          (g.to_json("scene") for g in board.scenes))),
        atomic_write_text(out / "per_category.csv", _csv_text(("agent", "category", *GROUP_COLUMNS),
                                                             (g.to_json("category") for g in board.categories))),
        atomic_write_text(out / "not_ranked.csv", _csv_text(NOT_RANKED_COLUMNS, (n.to_json() for n in board.not_ranked))),
        atomic_write_text(out / "paired.csv", _csv_text(PAIRED_COLUMNS, (d.to_json() for d in board.paired))),
    ]

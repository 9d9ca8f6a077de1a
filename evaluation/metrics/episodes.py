"""Episode scoring: render-server episode logs -> BOP Average Recall and adjustments per agent.

Each episode is one BOP "image": its final view (the view current when the agent submitted) with
the ground truth the server logged at that moment (``serve.episodes.submission_record``). Image
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

Agent AR is BOP's AR over the agent's episodes (one call of :func:`evaluate_bop19` per episode,
summed exactly: recall is matched targets / targets, so per-episode true-positive counts add up).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.atomic import read_png
from brave6d.errors import DataError
from evaluation.metrics.recall import METRICS, BopScores, EvalConfig, Estimate, GTInstance, ObjectModel, evaluate_bop19
from evaluation.metrics.depth_renderer import DepthRenderer
from serve.client import ObjectGT

UNKNOWN_AGENT = "unknown"


# ----------------------------------------------------------------------------- reading logs
@dataclass(frozen=True)
class LoggedEstimate:
    """One submitted estimate (``R`` 3x3, ``t_m`` metres, camera frame of the final view)."""

    obj_id: int
    R: NDArray[np.float64]
    t_m: NDArray[np.float64]
    score: float


@dataclass(frozen=True)
class EpisodeRecord:
    """What scoring needs from one episode log."""

    episode_id: str
    path: Path
    agent: str
    bundle: str | None
    bundle_root: str | None
    target: ObjectGT
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
    objects: tuple[ObjectGT, ...]
    estimates: tuple[LoggedEstimate, ...]
    depth_path: Path | None


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


def _read_records(path: Path) -> list[dict[str, Any]]:
    records = []
    lines = path.read_text(encoding="utf-8").splitlines()
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as exc:
            if n == len(lines):  # a partial last line: the server was stopped mid-write
                break
            raise DataError(f"{path}:{n}: not valid JSON ({exc.msg})") from None
        if not isinstance(rec, dict):
            raise DataError(f"{path}:{n}: a record must be a JSON object")
        records.append(rec)
    return records


def _get(rec: dict[str, Any], key: str, where: str) -> Any:
    if key not in rec:
        raise DataError(f"{where}: field '{key}' is missing")
    return rec[key]


def _matrix(value: Any, shape: tuple[int, ...], where: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: must be numbers of shape {shape}") from None
    if arr.size != int(np.prod(shape)) or not np.all(np.isfinite(arr)):
        raise DataError(f"{where}: must be {int(np.prod(shape))} finite numbers, got {arr.size}")
    return arr.reshape(shape)


def _fraction(value: Any, where: str) -> float | None:
    if value is None:
        return None
    v = float(value)
    if not math.isfinite(v):
        raise DataError(f"{where}: must be finite or null, got {value}")
    return v


def _objects(raw: Any, target_gt_id: int, where: str) -> tuple[ObjectGT, ...]:
    if not isinstance(raw, list):
        raise DataError(f"{where}: field 'objects' must be a list")
    out = []
    for i, o in enumerate(raw):
        w = f"{where}: objects[{i}]"
        gt_id = int(_get(o, "gt_id", w))
        out.append(ObjectGT(gt_id, int(_get(o, "obj_id", w)), str(o.get("name", "")),
                            bool(o.get("is_target", gt_id == target_gt_id)),
                            _matrix(_get(o, "cam_T_obj", w), (4, 4), f"{w}.cam_T_obj"),
                            _fraction(o.get("visib_fract"), f"{w}.visib_fract"), o.get("px_count_visib"),
                            o.get("px_count_all"), o.get("bbox_visib")))
    return tuple(out)


def _estimates(raw: Any, where: str) -> tuple[LoggedEstimate, ...]:
    if not isinstance(raw, list):
        raise DataError(f"{where}: field 'estimates' must be a list")
    out = []
    for i, e in enumerate(raw):
        w = f"{where}: estimates[{i}]"
        score = float(e.get("score", 1.0))
        if not math.isfinite(score):
            raise DataError(f"{w}.score: must be finite")
        out.append(LoggedEstimate(int(_get(e, "obj_id", w)), _matrix(_get(e, "R", w), (3, 3), f"{w}.R"),
                                  _matrix(_get(e, "t_m", w), (3,), f"{w}.t_m"), score))
    return tuple(out)


def _seconds_between(a: str | None, b: str | None) -> float | None:
    try:
        t0 = _dt.datetime.fromisoformat(str(a))
        t1 = _dt.datetime.fromisoformat(str(b))
    except ValueError:
        return None
    return max(0.0, (t1 - t0).total_seconds())


def read_episode(path: Path | str) -> EpisodeRecord:
    """One episode log (JSONL written by the render server) -> :class:`EpisodeRecord`."""
    p = Path(path)
    records = _read_records(p)
    if not records or records[0].get("event") != "reset":
        raise DataError(f"{p}: not an episode log (the first record must be a 'reset' event)")
    reset = records[0]
    where = f"{p}: reset"
    tgt = _get(reset, "target", where)
    target_gt_id = int(_get(tgt, "gt_id", f"{where}.target"))
    submit = next((r for r in records if r.get("event") == "submit"), None)
    agent = str((submit or {}).get("agent") or reset.get("agent") or UNKNOWN_AGENT)
    common = {"episode_id": str(_get(reset, "episode_id", where)), "path": p, "agent": agent,
              "bundle": reset.get("bundle"), "started": str(reset.get("time", "")),
              "seed": reset.get("seed")}
    if submit is not None:
        w = f"{p}: submit"
        view = _get(submit, "final_view", w)
        objects = _objects(_get(submit, "objects", w), target_gt_id, w)
        target = next((o for o in objects if o.gt_id == target_gt_id), None)
        if target is None:
            raise DataError(f"{w}: the target (gt_id {target_gt_id}) is not among 'objects'")
        depth_file = view.get("depth_file")
        elapsed = submit.get("elapsed_s")
        wall = float(elapsed) if elapsed is not None else _seconds_between(reset.get("time"), submit.get("time"))
        return EpisodeRecord(
            **common, bundle_root=submit.get("bundle_root"), target=target, submitted=True,
            adjustments=int(_get(submit, "adjustments", w)), steps=int(submit.get("steps", 0)),
            refusals=int(submit.get("refusals", 0)), wall_time_s=wall,
            K=_matrix(_get(view, "K", f"{w}.final_view"), (3, 3), f"{w}.final_view.K"),
            width=int(_get(view, "width", f"{w}.final_view")), height=int(_get(view, "height", f"{w}.final_view")),
            objects=objects, estimates=_estimates(_get(submit, "estimates", w), w),
            depth_path=p.with_name(str(depth_file)) if depth_file else None)
    # No submission: the target counts with no estimate, at the last logged pose.
    last = next((r for r in reversed(records) if "target_cam_T_obj" in r), reset)
    if "target_cam_T_obj" not in last:
        raise DataError(f"{where}: field 'target_cam_T_obj' is missing (needed to score an unsubmitted episode)")
    target = ObjectGT(target_gt_id, int(_get(tgt, "obj_id", f"{where}.target")), str(tgt.get("name", "")), True,
                      _matrix(last["target_cam_T_obj"], (4, 4), f"{p}: target_cam_T_obj"),
                      _fraction(last.get("target_visib_fract"), f"{p}: target_visib_fract"), None, None, None)
    adjustments = max((int(r.get("adjustments", 0)) for r in records), default=0)
    return EpisodeRecord(
        **common, bundle_root=None, target=target, submitted=False, adjustments=adjustments,
        steps=sum(1 for r in records if r.get("event") in ("set_pose", "move")),
        refusals=sum(1 for r in records if r.get("refusal") and not r.get("accepted", True)),
        wall_time_s=_seconds_between(reset.get("time"), records[-1].get("time")),
        K=_matrix(_get(reset, "K", where), (3, 3), f"{where}.K"), width=int(_get(reset, "width", where)),
        height=int(_get(reset, "height", where)), objects=(target,), estimates=(), depth_path=None)


def read_episodes(paths: Iterable[Path | str]) -> list[EpisodeRecord]:
    """Every episode of the given log files and folders (see :func:`find_episode_logs`)."""
    return [read_episode(p) for p in find_episode_logs(paths)]


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
    """BOP object models (mm, faces, diameter, symmetries) of a loaded ``serve.bundle.Bundle``."""
    from evaluation.metrics.bop_results import load_ply_mesh

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
        return {"agent": e.agent, "episode_id": e.episode_id, "log": e.path.name, "scene_id": self.scene_id,
                "im_id": self.im_id, "target": e.target.name, "target_gt_id": e.target.gt_id,
                "obj_id": e.target.obj_id, "seed": e.seed, "submitted": e.submitted, "estimates": len(e.estimates),
                "n_targets": self.scores.n_targets, "ar": self.scores.ar, "ar_vsd": self.scores.ar_vsd,
                "ar_mssd": self.scores.ar_mssd, "ar_mspd": self.scores.ar_mspd,
                "adjustments": e.adjustments, "wall_time_s": e.wall_time_s,
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

    def to_json(self) -> dict[str, Any]:
        return {"agent": self.agent, "episodes": self.episodes, "submitted": self.submitted,
                "n_targets": self.n_targets, "ar": self.ar,
                **{f"ar_{m}": self.ar_per_metric.get(m) for m in METRICS},
                "mean_adjustments": self.mean_adjustments, "mean_wall_time_s": self.mean_wall_time_s,
                "per_object": [self.per_object[k] for k in sorted(self.per_object)]}


@dataclass
class Leaderboard:
    """Agents ranked by AR (then name), with every episode's scores."""

    agents: list[AgentScore]
    episodes: list[EpisodeScore]
    config: EvalConfig
    all_objects: bool = False

    def table(self) -> str:
        from brave6d.progress import format_table

        rows = [[a.agent, a.episodes, a.ar, *(_cell(a.ar_per_metric.get(m)) for m in METRICS),
                 a.mean_adjustments, _cell(a.mean_wall_time_s)] for a in self.agents]
        return format_table(["agent", "episodes", "AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "mean adjustments",
                             "wall time s"], rows)

    def object_table(self) -> str:
        from brave6d.progress import format_table

        rows = [[a.agent, o["obj_id"], o["name"], o["n_targets"], o["ar"],
                 *(_cell(o.get(f"ar_{m}")) for m in METRICS), o["mean_adjustments"]]
                for a in self.agents for o in (a.per_object[k] for k in sorted(a.per_object))]
        return format_table(["agent", "obj_id", "object", "targets", "AR", "AR_VSD", "AR_MSSD", "AR_MSPD",
                             "mean adjustments"], rows)

    def to_json(self) -> dict[str, Any]:
        return {"format": "brave6d-leaderboard/1", "metrics": list(self.config.metrics),
                "targets": "every visible instance" if self.all_objects else "the episode's target",
                "visib_gt_min": self.config.visib_gt_min,
                "agents": [a.to_json() for a in self.agents], "episodes": [e.to_json() for e in self.episodes]}


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
    per_metric = {}
    for m in metrics:
        counts = [np.asarray(s.scores.metrics[m].tp_counts, dtype=np.float64) for s in scored]
        tp = np.sum(counts, axis=0) if counts else np.zeros(1)
        per_metric[m] = float(np.mean(tp / n_targets)) if n_targets > 0 else 0.0
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
    return AgentScore(agent, len(scored), sum(1 for s in scored if s.episode.submitted), n_targets,
                      float(np.mean(list(per_metric.values()))), per_metric,
                      float(np.mean([s.episode.adjustments for s in scored])) if scored else 0.0,
                      _mean_or_none([s.episode.wall_time_s for s in scored]), per_object)


def score_episodes(episodes: Sequence[EpisodeRecord], models: Mapping[int, ObjectModel],
                   config: EvalConfig | None = None, all_objects: bool = False,
                   renderer: DepthRenderer | None = None) -> Leaderboard:
    """BOP AR per episode and per agent (see the module docstring); ``models`` in mm."""
    cfg = config or EvalConfig()
    ids = assign_image_ids(episodes)
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
    return Leaderboard(agents, scored, cfg, all_objects)


# ----------------------------------------------------------------------------- files
LEADERBOARD_COLUMNS = ("agent", "episodes", "submitted", "n_targets", "ar", "ar_vsd", "ar_mssd", "ar_mspd",
                       "mean_adjustments", "mean_wall_time_s")
EPISODE_COLUMNS = ("agent", "episode_id", "scene_id", "im_id", "target", "obj_id", "seed", "submitted", "estimates",
                   "ar", "ar_vsd", "ar_mssd", "ar_mspd", "adjustments", "wall_time_s", "target_distance_m")
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
    """Write ``leaderboard.csv``/``.json``, ``episodes.csv`` and ``per_object.csv`` (atomic)."""
    from brave6d.atomic import atomic_write_json, atomic_write_text

    out = Path(out_dir)
    agents = [a.to_json() for a in board.agents]
    objects = [{"agent": a.agent, **row} for a in board.agents for row in a.to_json()["per_object"]]
    return [
        atomic_write_text(out / "leaderboard.csv", _csv_text(LEADERBOARD_COLUMNS, agents)),
        atomic_write_json(out / "leaderboard.json", board.to_json()),
        atomic_write_text(out / "episodes.csv", _csv_text(EPISODE_COLUMNS, (e.to_json() for e in board.episodes))),
        atomic_write_text(out / "per_object.csv", _csv_text(OBJECT_COLUMNS, objects)),
    ]

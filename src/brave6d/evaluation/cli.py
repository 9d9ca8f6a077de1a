"""``brave6d evaluate EPISODE_LOGS... [--bundle BUNDLE] [--out DIR]``: score agent episodes; or
``brave6d evaluate RESULTS.csv... --split DATA/test --models DATA/models``: score BOP results CSVs
(``brave6d estimate bop``'s, or any method's in BOP's format) against a BOP split's ground truth.

Reads the render server's episode logs (JSONL files or folders of them), scores every episode
with BOP's Average Recall against the ground truth the server logged with the submission, and
prints a leaderboard (agent, episodes, AR, AR_VSD, AR_MSSD, AR_MSPD, mean position adjustments,
mean wall time per episode). Writes ``leaderboard.csv``/``.json``, ``episodes.csv``,
``per_object.csv``, ``per_scene.csv`` and ``per_category.csv`` to ``--out`` (default: ``evaluation/`` inside the first log folder).

The object models (and categories) come from the bundles: ``--bundle``, else every bundle the
server recorded in the logs (one per scene of a served release), else a ``bundle`` folder beside
the log folder (the server's default layout). Besides the agents' table it prints and writes each
agent's AR per scene (``per_scene.csv``) and per object category (``per_category.csv``).

Ranking (docs/SECURITY.md): by default (``--mode scored``) only episodes of a scored server whose
keyed digest verifies with this machine's key (``--log-key``, else ``$BRAVE6D_LOG_KEY``, else
``~/.config/brave6d/episode-log.key``) are ranked; training-mode episodes, unsigned logs and logs
signed with another key are listed apart, each named with why (``not_ranked.csv``). A log edited
after the server wrote it (an estimate, a pose, a count, its depth image) is refused, naming the
episode. ``--mode training`` ranks training-mode episodes instead (a development board).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from brave6d.core.errors import DataError
from brave6d.evaluation.metrics import EpisodeRecord


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("episode_logs", nargs="+", type=Path, metavar="EPISODE_LOGS",
                        help="episode logs (*.jsonl) or folders holding them; or BOP results CSV files "
                             "(scene_id,im_id,obj_id,score,R,t,time) with --split and --models")
    parser.add_argument("--split", type=Path, default=None,
                        help="for BOP results CSVs: the BOP split folder (scene folders with scene_gt.json)")
    parser.add_argument("--models", type=Path, default=None,
                        help="for BOP results CSVs: the models folder (models_info.json, obj_XXXXXX.ply in mm)")
    parser.add_argument("--bundle", type=Path, default=None,
                        help="the bundle the episodes ran on (default: recorded in the logs, or 'bundle' "
                             "beside the log folder)")
    parser.add_argument("--out", type=Path, default=None,
                        help="output folder (default: <first log folder>/evaluation)")
    parser.add_argument("--all-objects", action="store_true",
                        help="score every visible instance of the final views, not only each episode's target")
    parser.add_argument("--metrics", nargs="+", choices=["vsd", "mssd", "mspd"], default=["vsd", "mssd", "mspd"],
                        help="metrics to evaluate (default: all three, BOP's AR)")
    parser.add_argument("--mode", choices=["scored", "training"], default="scored",
                        help="which episodes are ranked: 'scored' (default: episodes of a scored server whose "
                             "digest verifies) or 'training' (episodes of a --training server: a development "
                             "board); the others are listed apart, named")
    parser.add_argument("--log-key", type=Path, default=None, metavar="FILE",
                        help="the server's log key, to check the episodes' digests (default: $BRAVE6D_LOG_KEY, "
                             "else ~/.config/brave6d/episode-log.key when it exists)")


def resolve_bundles(episodes: Sequence[EpisodeRecord], log_paths: Sequence[Path], explicit: Path | None) -> list[Path]:
    """The bundle folders the episodes ran on: ``explicit``, else every one recorded in the logs
    (a server of a release records one per scene), else ``<log folder>/../bundle``."""
    from brave6d.core.layout import SceneDir
    from brave6d.serve import is_bundle

    if explicit is not None:
        return [explicit]
    recorded = [Path(r) for r in sorted({e.bundle_root for e in episodes if e.bundle_root}) if is_bundle(r)]
    if recorded:
        return recorded
    for p in log_paths:
        folder = p if p.is_dir() else p.parent
        candidate = SceneDir(folder.resolve().parent).bundle_dir  # the server's default: <scene>/episodes
        if is_bundle(candidate):
            return [candidate]
    raise DataError("cannot find the bundle the episodes ran on; pass --bundle BUNDLE")


def check_bundle_name(episodes: Sequence[EpisodeRecord], name: str) -> None:
    """Refuse episodes that were served from a bundle of another scene."""
    for e in episodes:
        if e.bundle is not None and e.bundle != name:
            raise DataError(f"{e.path}: the episode ran on bundle {e.bundle!r}, not on {name!r} (check --bundle)")


def library_of(bundles: Sequence[Any]) -> tuple[dict[int, Any], dict[int, str]]:
    """The object models (mm) and categories of every bundle, by ``obj_id``; one obj_id naming two
    different objects in two bundles is refused (a dataset keeps one obj_id per object)."""
    from brave6d.evaluation.metrics import models_from_bundle

    models: dict[int, Any] = {}
    names: dict[int, tuple[str, Path]] = {}
    categories: dict[int, str] = {}
    for b in bundles:
        for o in b.objects:
            seen = names.setdefault(o.obj_id, (o.name, b.root))
            if seen[0] != o.name:
                raise DataError(f"{b.root}: obj_id {o.obj_id} is {o.name!r}, but {seen[0]!r} in {seen[1]}: "
                                "episodes of different datasets cannot be scored together")
            if o.class_name:
                categories.setdefault(o.obj_id, o.class_name)
        models.update({k: v for k, v in models_from_bundle(b).items() if k not in models})
    return models, categories


def default_out(log_paths: Sequence[Path]) -> Path:
    first = log_paths[0]
    return (first if first.is_dir() else first.parent) / "evaluation"


def run(args: argparse.Namespace) -> int:
    from brave6d.evaluation.metrics import EvalConfig, rank_episodes, read_episodes, score_episodes, write_leaderboard
    from brave6d.serve import evaluation_log_key, load_bundle

    paths = list(args.episode_logs)
    if any(p.suffix.lower() == ".csv" for p in paths):
        return score_csvs(paths, args.split, args.models)
    episodes = read_episodes(paths, evaluation_log_key(args.log_key))  # an edited log is refused here
    ranked, apart = rank_episodes(episodes, args.mode)
    if not ranked:
        raise DataError(f"none of the {len(episodes)} episodes can be ranked on a {args.mode} leaderboard: "
                        + "; ".join(f"{n.episode.episode_id} ({n.episode.agent}): {n.reason}" for n in apart[:5])
                        + (f"; and {len(apart) - 5} more" if len(apart) > 5 else "")
                        + ("" if args.mode == "training" else " (score training runs with --mode training)"))
    bundles = [load_bundle(p) for p in resolve_bundles(episodes, paths, args.bundle)]
    if args.bundle is not None:
        check_bundle_name(episodes, bundles[0].name)
    models, categories = library_of(bundles)
    board = score_episodes(episodes, models, EvalConfig(metrics=tuple(args.metrics)), all_objects=args.all_objects,
                           categories=categories, mode=args.mode)
    out = args.out if args.out is not None else default_out(paths)
    written = write_leaderboard(board, out)
    print(board.table())
    if board.paired:
        print(f"\nActive minus static, paired by start (paired.csv; resolved: at least 2 SE from zero):")
        print(board.paired_table())
    for table in (board.group_table("scene"), board.group_table("category"), board.object_table()):
        print()
        print(table)
    if board.not_ranked:
        print(f"\nNot ranked on this {args.mode} leaderboard ({len(board.not_ranked)} episodes, not_ranked.csv):")
        print(board.not_ranked_table())
    scenes = sorted({e.scene for e in ranked})
    print(f"\n{len(ranked)} {args.mode} episodes ranked on {len(scenes)} scene(s) ({', '.join(scenes)}), "
          f"{len(apart)} listed apart; written: " + ", ".join(str(p) for p in written))
    return 0


def score_csvs(paths: Sequence[Path], split: Path | None, models: Path | None) -> int:
    """One AR line per BOP results CSV, against ``split``'s ground truth with ``models``."""
    from brave6d.evaluation.estimate_bop import score_results_csv

    if not all(p.suffix.lower() == ".csv" for p in paths):
        raise DataError("give either episode logs or BOP results CSV files, not both: "
                        + ", ".join(str(p) for p in paths))
    if split is None or models is None:
        raise DataError(f"{paths[0]}: a BOP results CSV is scored against a BOP split: pass --split DATA/test "
                        "and --models DATA/models")
    for p in paths:
        print(f"{p}: {score_results_csv(p, split, models)}")
    return 0

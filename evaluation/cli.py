"""``brave6d evaluate EPISODE_LOGS... [--bundle BUNDLE] [--out DIR]``: score agent episodes.

Reads the render server's episode logs (JSONL files or folders of them), scores every episode
with BOP's Average Recall against the ground truth the server logged with the submission, and
prints a leaderboard (agent, episodes, AR, AR_VSD, AR_MSSD, AR_MSPD, mean position adjustments,
mean wall time per episode). Writes ``leaderboard.csv``/``.json``, ``episodes.csv`` and
``per_object.csv`` to ``--out`` (default: ``evaluation/`` inside the first log folder).

The object models come from the bundle: ``--bundle``, else the bundle the server recorded in
the logs, else a ``bundle`` folder beside the log folder (the server's default layout).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from brave6d.errors import DataError
from evaluation.metrics import EpisodeRecord


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("episode_logs", nargs="+", type=Path, metavar="EPISODE_LOGS",
                        help="episode logs (*.jsonl) or folders holding them")
    parser.add_argument("--bundle", type=Path, default=None,
                        help="the bundle the episodes ran on (default: recorded in the logs, or 'bundle' "
                             "beside the log folder)")
    parser.add_argument("--out", type=Path, default=None,
                        help="output folder (default: <first log folder>/evaluation)")
    parser.add_argument("--all-objects", action="store_true",
                        help="score every visible instance of the final views, not only each episode's target")
    parser.add_argument("--metrics", nargs="+", choices=["vsd", "mssd", "mspd"], default=["vsd", "mssd", "mspd"],
                        help="metrics to evaluate (default: all three, BOP's AR)")


def resolve_bundle(episodes: Sequence[EpisodeRecord], log_paths: Sequence[Path], explicit: Path | None) -> Path:
    """The bundle folder: ``explicit``, else the one recorded in the logs, else ``<log folder>/../bundle``."""
    if explicit is not None:
        return explicit
    recorded = {e.bundle_root for e in episodes if e.bundle_root}
    for root in sorted(recorded):
        if (Path(root) / "manifest.json").is_file():
            return Path(root)
    for p in log_paths:
        folder = p if p.is_dir() else p.parent
        candidate = folder.resolve().parent / "bundle"
        if (candidate / "manifest.json").is_file():
            return candidate
    raise DataError("cannot find the bundle the episodes ran on; pass --bundle BUNDLE")


def check_bundle_name(episodes: Sequence[EpisodeRecord], name: str) -> None:
    """Refuse episodes that were served from a bundle of another scene."""
    for e in episodes:
        if e.bundle is not None and e.bundle != name:
            raise DataError(f"{e.path}: the episode ran on bundle {e.bundle!r}, not on {name!r} (check --bundle)")


def default_out(log_paths: Sequence[Path]) -> Path:
    first = log_paths[0]
    return (first if first.is_dir() else first.parent) / "evaluation"


def run(args: argparse.Namespace) -> int:
    from evaluation.metrics import EvalConfig, models_from_bundle, read_episodes, score_episodes, write_leaderboard
    from serve import load_bundle

    paths = list(args.episode_logs)
    episodes = read_episodes(paths)
    bundle = load_bundle(resolve_bundle(episodes, paths, args.bundle))
    check_bundle_name(episodes, bundle.name)
    models = models_from_bundle(bundle, {o.obj_id for e in episodes for o in e.objects})
    board = score_episodes(episodes, models, EvalConfig(metrics=tuple(args.metrics)), all_objects=args.all_objects)
    out = args.out if args.out is not None else default_out(paths)
    written = write_leaderboard(board, out)
    print(board.table())
    print()
    print(board.object_table())
    print(f"\n{len(episodes)} episodes from bundle {bundle.name!r}; written: "
          + ", ".join(str(p) for p in written))
    return 0

"""Scoring a submitted episode the way ``brave6d evaluate`` does: the server's episode log, read
with :func:`brave6d.evaluation.metrics.read_episode` and scored with BOP's Average Recall
(:func:`brave6d.evaluation.metrics.score_episodes`) against the bundle's object models. The bridge
returns the score to the agent at once; nothing here re-implements a metric."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class EpisodeScore:
    """One episode's BOP Average Recall (per metric None when that metric was not evaluated)."""

    ar: float
    ar_vsd: float | None
    ar_mssd: float | None
    ar_mspd: float | None
    n_targets: int


class EpisodeScorer:
    """Scores episode logs of one or more bundles; the object models are loaded once per bundle."""

    def __init__(self, metrics: tuple[str, ...] = ("vsd", "mssd", "mspd"), all_objects: bool = False) -> None:
        from brave6d.evaluation.metrics import EvalConfig

        self.config = EvalConfig(metrics=tuple(metrics))
        self.all_objects = all_objects
        self._models: dict[str, dict[int, Any]] = {}
        self._lock = threading.Lock()

    def _models_of(self, bundle: Any) -> dict[int, Any]:
        from brave6d.evaluation.metrics import models_from_bundle

        key = str(Path(bundle.root).resolve())
        with self._lock:
            if key not in self._models:
                self._models[key] = models_from_bundle(bundle)
            return self._models[key]

    def score(self, log_path: Path | str, bundle: Any) -> EpisodeScore:
        """The AR of the episode logged at ``log_path`` (submitted on ``bundle``, a ``brave6d.serve.Bundle``)."""
        from brave6d.evaluation.metrics import read_episode, score_episodes

        record = read_episode(log_path)
        board = score_episodes([record], self._models_of(bundle), self.config, all_objects=self.all_objects)
        s = board.episodes[0].scores
        return EpisodeScore(float(s.ar), s.ar_vsd, s.ar_mssd, s.ar_mspd, int(s.n_targets))

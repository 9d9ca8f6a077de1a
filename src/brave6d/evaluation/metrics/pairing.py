"""Active minus static, paired by start: what coming closer buys, with the error it is known to.

Two agents that played the same seeded starts (scene, target, seed) are compared start by start:
the mean of the per-start AR differences and its standard error (the spread of those differences
over the square root of their count). Paired, the starts' own difficulty cancels: the standard error
is a fraction of what two independent means would give. An ``X-active`` agent is paired with
``X-static`` (the registry's names, and any user's agents named that way).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: A difference counts as resolved when it is at least this many paired standard errors from zero.
RESOLVED_SE = 2.0


def paired_standard_error(differences: Sequence[float]) -> float:
    """Standard error of the mean of paired differences (NaN and inf dropped; NaN with fewer than two)."""
    d = np.asarray([x for x in differences if math.isfinite(x)], dtype=np.float64)
    return float(np.std(d, ddof=1) / math.sqrt(len(d))) if len(d) >= 2 else math.nan


@dataclass(frozen=True)
class PairedDifference:
    """``active`` minus ``static`` over the ``pairs`` starts both played: the mean difference, its
    standard error, and each agent's mean AR over those starts."""

    active: str
    static: str
    pairs: int
    mean: float
    se: float
    active_ar: float
    static_ar: float

    @property
    def resolved(self) -> bool:
        """Whether the difference is at least :data:`RESOLVED_SE` standard errors from zero."""
        return _resolves(self.mean, self.se)

    def pairs_to_resolve(self, difference: float | None = None) -> int | None:
        """About how many paired starts would resolve ``difference`` (default: the measured one) at
        :data:`RESOLVED_SE` standard errors, the spread of the differences staying as measured (None
        when it cannot be told: no spread measured, or a zero difference)."""
        d = abs(self.mean if difference is None else difference)
        if not (math.isfinite(self.se) and self.se > 0 and d > 0 and self.pairs >= 2):
            return None
        sd = self.se * math.sqrt(self.pairs)
        return int(math.ceil((RESOLVED_SE * sd / d) ** 2))

    def verdict(self, claimed: float | None = None) -> str:
        """Whether the starts resolve the measured difference (or that it reaches ``claimed``): "resolved
        (k SE)", or "not resolved" with about how many starts would, or "too few starts"."""
        if self.pairs < 2 or not math.isfinite(self.se):
            return "too few starts to tell its error"
        if _resolves(self.mean, self.se) and (claimed is None or self.mean >= claimed):
            return f"resolved ({abs(self.mean) / self.se:.1f} SE)" if self.se > _NO_SPREAD else "resolved (no spread)"
        need = self.pairs_to_resolve(claimed)
        target = abs(self.mean if claimed is None else claimed)
        return f"not resolved: about {need} paired starts would resolve {target:.3f}" if need else "not resolved"

    def to_json(self) -> dict[str, Any]:
        return {"active": self.active, "static": self.static, "pairs": self.pairs, "mean": self.mean,
                "se": None if not math.isfinite(self.se) else self.se, "active_ar": self.active_ar,
                "static_ar": self.static_ar, "resolved": self.resolved,
                "pairs_to_resolve": self.pairs_to_resolve()}


#: A standard error this small is rounding, not spread (every start gave the same difference).
_NO_SPREAD = 1e-12


def _resolves(mean: float, se: float) -> bool:
    if not (math.isfinite(mean) and math.isfinite(se)):
        return False
    return abs(mean) > _NO_SPREAD if se <= _NO_SPREAD else abs(mean) >= RESOLVED_SE * se


#: One played episode as pairing sees it: (agent, start, AR); a start is (scene, target gt_id, obj_id, seed).
Played = tuple[str, tuple[Any, ...], float]


def played_of_scores(scores: Sequence[Any]) -> list[Played]:
    """:data:`Played` of scored episodes (``EpisodeScore``: ``.episode``, ``.scores.ar``); episodes without a
    seed (not from a seeded start) cannot be paired and are left out."""
    return [(s.episode.agent, (s.episode.scene, s.episode.target.gt_id, s.episode.target.obj_id, s.episode.seed),
             float(s.scores.ar)) for s in scores if s.episode.seed is not None]


def played_of_rows(rows: Sequence[Mapping[str, Any]]) -> list[Played]:
    """:data:`Played` of a leaderboard's ``episodes`` rows (``leaderboard.json``, ``EpisodeScore.to_json``)."""
    return [(str(r["agent"]), (r.get("scene"), r.get("target_gt_id"), r.get("obj_id"), r["seed"]), float(r["ar"]))
            for r in rows if r.get("seed") is not None and r.get("ar") is not None and "agent" in r]


def paired_difference(played: Sequence[Played], active: str, static: str) -> PairedDifference | None:
    """``active`` minus ``static`` over the starts both played; None when they share no start. An agent
    that played a start twice counts its mean there."""
    per_agent: dict[str, dict[tuple[Any, ...], list[float]]] = {active: {}, static: {}}
    for agent, start, ar in played:
        if agent in per_agent:
            per_agent[agent].setdefault(start, []).append(ar)
    common = sorted(set(per_agent[active]) & set(per_agent[static]), key=repr)
    if not common:
        return None
    a = np.array([np.mean(per_agent[active][k]) for k in common])
    b = np.array([np.mean(per_agent[static][k]) for k in common])
    return PairedDifference(active, static, len(common), float(np.mean(a - b)), paired_standard_error(list(a - b)),
                            float(np.mean(a)), float(np.mean(b)))


def active_static_pairs(agents: Sequence[str]) -> list[tuple[str, str]]:
    """``(X-active, X-static)`` for every agent name with ``active`` in it whose ``static`` twin played too."""
    names = set(agents)
    return [(a, a.replace("active", "static")) for a in agents if "active" in a and a.replace("active", "static") in names]


def paired_differences(played: Sequence[Played], agents: Sequence[str]) -> list[PairedDifference]:
    """:func:`paired_difference` of every :func:`active_static_pairs` pair of ``agents``."""
    out = [paired_difference(played, a, s) for a, s in active_static_pairs(agents)]
    return [d for d in out if d is not None]


def paired_table(differences: Sequence[PairedDifference], claimed: Mapping[str, float] | None = None) -> str:
    """The differences as a text table, one verdict per pair (``claimed``: per active agent, the
    difference the figures claim, whose resolution is judged instead of the measured one's)."""
    from brave6d.core.progress import format_table

    rows = []
    for d in differences:
        rows.append([d.active, d.static, d.pairs, d.active_ar, d.static_ar, round(d.mean, 4),
                     round(d.se, 4) if math.isfinite(d.se) else "n/a", d.verdict((claimed or {}).get(d.active))])
    return format_table(["active", "static", "paired starts", "active AR", "static AR", "active - static", "SE",
                         "resolved?"], rows)

"""Active minus static, paired by start: the mean and standard error of per-start differences, whether
the starts resolve it, and how many would."""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from brave6d.evaluation.metrics.pairing import RESOLVED_SE, active_static_pairs, paired_difference, \
    paired_differences, paired_standard_error, played_of_rows, played_of_scores


@dataclass
class _Scored:
    """What pairing reads of a scored episode (``EpisodeScore``'s ``.episode`` and ``.scores.ar``)."""

    episode: SimpleNamespace
    scores: SimpleNamespace


def _scored(agent: str, seed: int, ar: float, gt_id: int = 0, scene: str = "s") -> _Scored:
    target = SimpleNamespace(gt_id=gt_id, obj_id=gt_id + 1)
    return _Scored(SimpleNamespace(agent=agent, seed=seed, scene=scene, target=target), SimpleNamespace(ar=ar))


def _played(*scored: _Scored):  # type: ignore[no-untyped-def]
    return played_of_scores(scored)


def test_pairs_by_start_and_the_starts_difficulty_cancels() -> None:
    # every start's difficulty differs a lot, the active agent is always 0.1 better: the paired SE is 0
    rng = np.random.default_rng(0)
    base = rng.uniform(0.1, 0.8, size=24)
    episodes = [_scored("x-static", i, float(b)) for i, b in enumerate(base)]
    episodes += [_scored("x-active", i, float(b) + 0.1) for i, b in enumerate(base)]
    episodes += [_scored("x-active", 99, 1.0)]  # a start only one agent played is not paired
    d = paired_difference(_played(*episodes), "x-active", "x-static")
    assert d is not None and d.pairs == 24 and d.mean == pytest.approx(0.1) and d.se == pytest.approx(0.0, abs=1e-12)
    assert d.resolved and d.verdict().startswith("resolved")
    # the unpaired SE of the two means would be far larger than the paired one
    assert np.std(base, ddof=1) / math.sqrt(24) > 0.03


def test_an_unresolved_difference_says_how_many_starts_would_resolve_it() -> None:
    rng = np.random.default_rng(1)
    diffs = rng.normal(0.02, 0.4, size=12)
    episodes = [_scored("a-static", i, 0.5) for i in range(12)] + [_scored("a-active", i, 0.5 + d) for i, d in enumerate(diffs)]
    d = paired_difference(_played(*episodes), "a-active", "a-static")
    assert d is not None and not d.resolved
    need = d.pairs_to_resolve(0.1)
    assert need is not None and need > 12
    # at that many starts, with the same spread, 0.1 would sit at RESOLVED_SE standard errors
    sd = d.se * math.sqrt(d.pairs)
    assert sd / math.sqrt(need) * RESOLVED_SE <= 0.1 + 1e-9 < sd / math.sqrt(need - 1) * RESOLVED_SE
    assert "not resolved" in d.verdict(0.1) and str(need) in d.verdict(0.1)
    # a claimed difference larger than the measured mean is not confirmed even when the mean is resolved
    strong = paired_difference(_played(*[_scored("b-static", i, 0.5) for i in range(10)],
                                       *[_scored("b-active", i, 0.55 + 0.01 * (i % 2)) for i in range(10)]),
                               "b-active", "b-static")
    assert strong is not None and strong.resolved and "not resolved" in strong.verdict(0.1)


def test_agents_pair_by_name_and_lone_ones_do_not() -> None:
    agents = ["baseline-static", "baseline-active", "learned-active", "learned-static", "learned-active-depth",
              "learned-static-depth", "mine-active"]
    assert active_static_pairs(agents) == [("baseline-active", "baseline-static"), ("learned-active", "learned-static"),
                                           ("learned-active-depth", "learned-static-depth")]
    assert paired_differences([], agents) == []


@given(st.lists(st.one_of(st.floats(0, 1), st.just(0.5)), min_size=0, max_size=30),
       st.floats(-1, 1, allow_nan=False))
def test_no_nan_or_inf_from_any_episodes(static_ar: list[float], shift: float) -> None:
    # constant differences (SE 0), one start (no SE), none at all: finite figures or a clear "cannot tell"
    episodes = [_scored("z-static", i, a) for i, a in enumerate(static_ar)]
    episodes += [_scored("z-active", i, min(max(a + shift, 0.0), 1.0)) for i, a in enumerate(static_ar)]
    d = paired_difference(_played(*episodes), "z-active", "z-static")
    if not static_ar:
        assert d is None
        return
    assert d is not None and math.isfinite(d.mean) and math.isfinite(d.active_ar) and math.isfinite(d.static_ar)
    if len(static_ar) < 2:
        assert math.isnan(d.se) and not d.resolved and "too few" in d.verdict()
    else:
        assert math.isfinite(d.se) and d.se >= 0
    json = d.to_json()
    assert json["se"] is None or math.isfinite(json["se"])
    assert paired_standard_error([]) != paired_standard_error([])  # NaN: nothing to tell


def test_leaderboard_rows_pair_as_the_scored_episodes_do() -> None:
    # the report pairs the rows of leaderboard.json; they must give what the scored episodes give
    episodes = [_scored("q-static", i, 0.1 * i, gt_id=i % 2) for i in range(8)]
    episodes += [_scored("q-active", i, 0.1 * i + 0.05 * (i % 3), gt_id=i % 2) for i in range(8)]
    episodes += [_scored("q-active", 5, 0.9, gt_id=1, scene="other")]  # another scene's start: not paired
    rows = [{"agent": e.episode.agent, "scene": e.episode.scene, "target_gt_id": e.episode.target.gt_id,
             "obj_id": e.episode.target.obj_id, "seed": e.episode.seed, "ar": e.scores.ar} for e in episodes]
    rows.append({"agent": "q-active", "scene": "s", "target_gt_id": 0, "obj_id": 1, "seed": None, "ar": 1.0})
    a, b = paired_difference(_played(*episodes), "q-active", "q-static"), paired_difference(played_of_rows(rows),
                                                                                             "q-active", "q-static")
    assert a is not None and a == b and a.pairs == 8

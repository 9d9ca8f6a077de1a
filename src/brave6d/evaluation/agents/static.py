"""The static policy: estimate from the start view, never move."""

from __future__ import annotations

from brave6d.evaluation.agents.policy import EpisodeState, PolicyPlan


class StaticPolicy:
    """Never moves: the estimate is the start view's own registration."""

    def explore(self, episode: EpisodeState) -> PolicyPlan:
        yield from ()
        return episode.views[0]

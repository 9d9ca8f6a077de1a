"""The learned active agent with one of its parts alone: what coming closer, choosing among views and
fusing views each buy over the static agent (report section 10 plays them from the demo's starts and
gives each one's gain over ``learned-static`` paired by start).

- ``closeness``: it comes closer and submits the nearest view's estimate (moved into the start
  view's frame, as the full agent does); no looks from the sides, no fusion;
- ``selection``: it stays at the start distance, looks from the sides and submits the best-ranked
  view's estimate; no approach, no fusion;
- ``fusion``: it stays at the start distance, looks from the sides and fuses every view into the
  start view's estimate (RGB-only: the position triangulated from the views' rays; with depth: ICP
  over their depth); no approach, no choice of view.

The registry names them ``learned-active-<part>`` and ``learned-active-depth-<part>``
(:data:`brave6d.evaluation.agents.ABLATION_AGENTS`).
"""

from __future__ import annotations

from brave6d.evaluation.agents.learned.agent import LearnedAgentOptions

#: part -> the active agent's options with only that part at work.
ABLATIONS: dict[str, LearnedAgentOptions] = {
    "closeness": LearnedAgentOptions(orbit_deg=(), view_choice="nearest", fuse_views=False),
    "selection": LearnedAgentOptions(approach=False, view_choice="best", fuse_views=False),
    "fusion": LearnedAgentOptions(approach=False, view_choice="start", fuse_views=True),
}

"""brave6d.training.strategy against gsplat 1.5.3's DefaultStrategy, the third-party reference it follows.

The same random training history (parameters, Adam moments, 2D-mean gradients, visibility) is
run through both; every parameter, optimiser moment and running statistic must come out
bit-identical. gsplat skips the opacity reset (a precedence bug, see training/strategy.py), so
the reference applies gsplat's own ``reset_opa`` at Inria's reset steps.
"""

from __future__ import annotations

from typing import Any

import pytest
import torch

import brave6d.training.strategy as strategy_module
from brave6d.training.presets import Densification
from brave6d.training.strategy import DensifyStrategy

gsplat_strategy = pytest.importorskip("gsplat.strategy")  # the `test` extra installs gsplat
gsplat_ops = pytest.importorskip("gsplat.strategy.ops")

SCHEDULE = {"refine_start_iter": 2, "refine_every": 3, "reset_every": 9, "refine_stop_iter": 20}  # gsplat's names
#: gsplat's names of the schedule -> ours (the rest are the same)
OURS = {"refine_start_iter": "refine_start", "refine_stop_iter": "refine_stop"}


def ours(**options: Any) -> DensifyStrategy:
    """Our strategy with gsplat-named options."""
    return DensifyStrategy(Densification(**{OURS.get(k, k): v for k, v in options.items()}))
STEPS = 24
WIDTH, HEIGHT, CAMERAS = 100, 80, 2


class GsplatReference:
    """gsplat's DefaultStrategy plus the opacity reset gsplat 1.5.3 never performs."""

    def __init__(self, **fields: Any) -> None:
        self.inner = gsplat_strategy.DefaultStrategy(**fields)

    def initialize_state(self, scene_scale: float) -> dict[str, Any]:
        return self.inner.initialize_state(scene_scale=scene_scale)

    def step_post_backward(self, params, optimizers, state, step, info) -> None:  # noqa: ANN001
        self.inner.step_post_backward(params, optimizers, state, step, info, packed=False)
        if 0 < step < self.inner.refine_stop_iter and step % self.inner.reset_every == 0:
            gsplat_ops.reset_opa(params=params, optimizers=optimizers, state=state,
                                 value=self.inner.prune_opa * 2.0)


def simulate(strategy: Any, seed: int = 0) -> tuple[torch.nn.ParameterDict, dict, dict]:
    """A random training history of ``STEPS`` steps; returns (params, optimizers, state)."""
    gen = torch.Generator().manual_seed(seed)
    n = 300
    params = torch.nn.ParameterDict({
        "means": torch.randn(n, 3, generator=gen) * 0.3,
        "scales": torch.log(torch.rand(n, 3, generator=gen) * 0.2 + 1e-3),  # some small, some large
        "quats": torch.randn(n, 4, generator=gen),
        "opacities": torch.randn(n, generator=gen) * 3.0,  # some below prune_opa
        "sh0": torch.rand(n, 1, 3, generator=gen),
        "shN": torch.zeros(n, 3, 3),
    })
    optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": 1e-3, "name": k}], eps=1e-15, fused=True)
                  for k in params}
    state = strategy.initialize_state(scene_scale=1.0)
    for step in range(STEPS):
        n = len(params["means"])
        for p in params.values():
            p.grad = torch.randn(p.shape, generator=gen) * 1e-2
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        means2d = torch.zeros(CAMERAS, n, 2, requires_grad=True)
        means2d.grad = torch.randn(CAMERAS, n, 2, generator=gen) * 4e-6  # around grow_grad2d once normalised
        info = {"means2d": means2d, "radii": torch.randint(0, 4, (CAMERAS, n, 2), generator=gen, dtype=torch.int32),
                "width": WIDTH, "height": HEIGHT, "n_cameras": CAMERAS, "gaussian_ids": None}
        torch.manual_seed(1000 + step)  # split draws its samples from torch's global generator
        strategy.step_post_backward(params, optimizers, state, step, info)
    return params, optimizers, state


def assert_identical(ours: tuple, reference: tuple) -> None:
    (p1, o1, s1), (p2, o2, s2) = ours, reference
    assert list(p1) == list(p2)
    for name in p1:
        assert torch.equal(p1[name], p2[name]), name
        m1, m2 = o1[name].state[p1[name]], o2[name].state[p2[name]]
        assert set(m1) == set(m2) == {"step", "exp_avg", "exp_avg_sq"}, name
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(m1[key], m2[key]), (name, key)
        assert o1[name].param_groups[0]["params"][0] is p1[name]
    for key in ("grad2d", "count"):
        assert torch.equal(s1[key], s2[key]), key


@pytest.mark.parametrize("max_gaussians", [None, 10**6])  # a cap that never binds changes nothing
def test_densification_matches_gsplat_bit_for_bit(max_gaussians: int | None,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    calls: dict[str, int] = {}
    for op in ("duplicate", "split", "remove", "reset_opacities"):
        original = getattr(strategy_module, op)

        def counted(*args: Any, _op: str = op, _original: Any = original, **kwargs: Any) -> None:
            calls[_op] = calls.get(_op, 0) + 1
            _original(*args, **kwargs)

        monkeypatch.setattr(strategy_module, op, counted)
    mine = simulate(ours(max_gaussians=max_gaussians, **SCHEDULE))
    reference = simulate(GsplatReference(**SCHEDULE))
    # the history exercised every operation, so the comparison covers them all
    assert calls["duplicate"] > 0 and calls["split"] > 0 and calls["remove"] > 0
    assert calls["reset_opacities"] == 2  # steps 9 and 18; none from step 20, where refinement stops
    assert len(mine[0]["means"]) != 300
    assert_identical(mine, reference)


def test_a_binding_cap_stops_growth_at_the_cap() -> None:
    no_pruning = {"prune_opa": 1e-9, "prune_scale3d": 100.0, **SCHEDULE}
    params, _, _ = simulate(ours(max_gaussians=310, **no_pruning))
    free, _, _ = simulate(ours(**no_pruning))
    assert len(free["means"]) > 310  # without the cap the same history grows past it
    assert len(params["means"]) == 310

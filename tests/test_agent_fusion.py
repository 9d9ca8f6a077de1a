"""How the baseline weighs its views when it fuses them (pure numpy, fast)."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from brave6d.evaluation.agents import view_weights


def test_view_weights_trust_views_by_their_own_fit() -> None:
    np.testing.assert_allclose(view_weights([0.8, 0.2, -0.3]), [0.8, 0.2, 0.0])
    np.testing.assert_allclose(view_weights([-0.1, 0.0]), [0.5, 0.5])  # none fits: alike
    np.testing.assert_allclose(view_weights([float("nan"), 0.5]), [0.0, 1.0])
    np.testing.assert_allclose(view_weights([1e308, 1e308]), [0.5, 0.5])  # no overflow


@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=1, max_size=12))
def test_view_weights_are_always_a_distribution(scores: list[float]) -> None:
    w = view_weights(scores)
    assert w.shape == (len(scores),) and np.all(np.isfinite(w)) and np.all(w >= 0)
    assert abs(float(w.sum()) - 1.0) < 1e-9

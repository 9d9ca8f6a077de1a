"""The learned trainer's batches made ahead (``learned/batches.py``): the same batches and generator
states as drawn in line, errors raised where the trainer takes its batch, and a prompt stop."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.evaluation.learned.batches import BatchSource


def draw(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A batch that uses the generator as the real ones do (several calls of several kinds)."""
    picks = rng.choice(50, size=4, replace=False)
    return {"x": rng.normal(size=(4, 3)).astype(np.float32) + picks[:, None], "k": picks.astype(np.int64)}


@settings(max_examples=25, deadline=None)
@given(count=st.integers(0, 12), ahead=st.integers(0, 4), taken=st.integers(0, 12), seed=st.integers(0, 2**16))
def test_batches_made_ahead_are_the_ones_drawn_in_line(count: int, ahead: int, taken: int, seed: int) -> None:
    taken = min(taken, count)
    reference = np.random.default_rng(seed)
    source = BatchSource(draw, np.random.default_rng(seed), count, "cpu", ahead)
    try:
        for _ in range(taken):
            batch, state = source.next()
            expected = draw(reference)
            assert all(np.array_equal(batch[k].numpy(), expected[k]) for k in expected)
            assert state == reference.bit_generator.state  # the state to checkpoint: after this batch
    finally:
        source.close()
    if taken == count:
        with pytest.raises(RuntimeError, match="every batch was taken"):
            source.next()


def test_an_error_while_drawing_is_raised_where_the_batch_is_taken() -> None:
    calls = []

    def failing(rng: np.random.Generator) -> dict[str, np.ndarray]:
        calls.append(1)
        if len(calls) == 3:
            raise ValueError("crop outside the image")
        return draw(rng)

    source = BatchSource(failing, np.random.default_rng(0), 5, "cpu", ahead=2)
    try:
        source.next(), source.next()
        with pytest.raises(ValueError, match="crop outside the image"):
            source.next()
    finally:
        source.close()


def test_close_stops_a_thread_waiting_on_a_full_queue() -> None:
    source = BatchSource(draw, np.random.default_rng(0), 1000, "cpu", ahead=2)
    source.next()
    time.sleep(0.2)  # the thread fills the queue and waits
    t0 = time.perf_counter()
    source.close()
    assert time.perf_counter() - t0 < 2.0 and source._thread is not None and not source._thread.is_alive()

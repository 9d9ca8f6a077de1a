"""A training phase's batches in the order its generator draws them, made ahead on a GPU.

On a GPU a step of the small networks waits on its batch, cut and augmented on the host (9-32 ms on
one core: the H200's figures in docs/BENCHMARKS.md), so :class:`BatchSource` draws the next batches in
a background thread while the device trains, into pinned memory for asynchronous copies. One
thread draws them from the phase's own generator in the order a synchronous run does, so the
batches, and a CPU's weights, are the same with or without it. Each batch carries the generator's
state after it: a checkpoint records the state after the last batch trained, not after those made
ahead, so a resumed run draws the next untrained batch.
"""

from __future__ import annotations

import queue
import threading
from typing import Any, Callable

import numpy as np

#: batches made ahead on a GPU (none on a CPU, whose cores already train both networks)
GPU_AHEAD = 3


class BatchSource:
    """``draw(rng)`` called ``count`` times, in order; ``ahead`` > 0 makes them in a thread that
    runs up to ``ahead`` batches ahead of the trainer. ``next()`` returns the batch as tensors on
    ``device`` and the generator's state after it."""

    def __init__(self, draw: Callable[[np.random.Generator], dict[str, Any]], rng: np.random.Generator, count: int,
                 device: Any, ahead: int = 0) -> None:
        import torch

        self._draw, self._rng, self._device = draw, rng, torch.device(device)
        self._count = self._left = max(0, count)
        self._pin = ahead > 0 and self._device.type == "cuda"
        self._queue: queue.Queue[tuple[dict[str, Any], dict[str, Any]] | BaseException] = queue.Queue(max(1, ahead))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if ahead > 0 and self._left > 0:
            self._thread = threading.Thread(target=self._produce, name="learn-batches", daemon=True)
            self._thread.start()

    def _make(self) -> tuple[dict[str, Any], dict[str, Any]]:
        import torch

        batch = {k: torch.from_numpy(v) for k, v in self._draw(self._rng).items()}
        if self._pin:
            batch = {k: v.pin_memory() for k, v in batch.items()}
        return batch, self._rng.bit_generator.state

    def _produce(self) -> None:
        try:
            for _ in range(self._count):
                item = self._make()
                while not self._stop.is_set():
                    try:
                        self._queue.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if self._stop.is_set():
                    return
        except BaseException as err:  # noqa: BLE001 - the trainer raises it at its next batch
            self._queue.put(err)

    def next(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """The next batch (tensors on the device) and the generator's state after drawing it."""
        if self._left <= 0:
            raise RuntimeError("BatchSource: every batch was taken")
        self._left -= 1
        item = self._queue.get() if self._thread is not None else self._make()
        if isinstance(item, BaseException):
            raise item
        batch, state = item
        return {k: v.to(self._device, non_blocking=self._pin) for k, v in batch.items()}, state

    def close(self) -> None:
        """Stop making batches (those made ahead are dropped; the generator's state to keep is the
        one :meth:`next` returned last)."""
        self._stop.set()
        if self._thread is not None:
            while self._thread.is_alive():
                try:
                    self._queue.get(timeout=0.05)
                except queue.Empty:
                    pass
            self._thread.join()

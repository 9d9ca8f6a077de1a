"""A process-wide library setting held at one value while sections of code run, safely when the
sections overlap (threads of one server, nested calls): the first section in saves the setting and
sets the value, the last one out restores what was saved, under a lock, so one section's exit never
undoes another's. Used for the libraries' thread counts (Open3D, OpenCV) that make sums repeatable
only on one thread."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any


class HeldSetting:
    """``get`` / ``set`` of one process-wide setting; :meth:`held` keeps it at ``value`` meanwhile."""

    def __init__(self, get: Callable[[], Any], set: Callable[[Any], Any], value: Any) -> None:
        self._get, self._set, self._value = get, set, value
        self._lock = threading.Lock()
        self._holders = 0
        self._before: Any = None

    @contextmanager
    def held(self) -> Iterator[None]:
        """The setting at the value for the duration; the count from before comes back when the last
        overlapping section leaves (also on an error)."""
        with self._lock:
            if self._holders == 0:
                self._before = self._get()
                self._set(self._value)
            self._holders += 1
        try:
            yield
        finally:
            with self._lock:
                self._holders -= 1
                if self._holders == 0:
                    self._set(self._before)
                    self._before = None

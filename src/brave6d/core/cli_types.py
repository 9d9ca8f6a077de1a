"""Bounded numbers: a setting outside its range is refused at start, from a flag or from Python.

``type=float_in(0, 3600, low_open=True)`` makes ``--request-timeout nan`` (or ``inf``, ``-1``)
end the command before it does anything, with argparse's one-line error naming the flag
(``argument --request-timeout: must be a finite number in (0, 3600], got nan``), exit status 2.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from brave6d.core.errors import BraveError

T = TypeVar("T", int, float)


def _interval(low: float | None, high: float | None, low_open: bool, high_open: bool) -> str:
    left = "(" if low_open or low is None else "["
    right = ")" if high_open or high is None else "]"
    return f"{left}{'-inf' if low is None else _number(low)}, {'inf' if high is None else _number(high)}{right}"


def _number(value: float) -> str:
    """An integer bound in full (``1000000``, not ``1e+06``); a float bound in its short form."""
    return str(value) if isinstance(value, int) else f"{value:g}"


def float_in(low: float | None = None, high: float | None = None, *, low_open: bool = False,
             high_open: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite float within ``low .. high`` (None: unbounded on that side)."""
    return _bounded(float, "a finite number", low, high, low_open, high_open)


def int_in(low: int | None = None, high: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer within ``low .. high`` inclusive (None: unbounded on that side)."""
    return _bounded(int, "an integer", low, high, False, False)


def _bounded(convert: Callable[[str], T], what: str, low: float | None, high: float | None, low_open: bool,
             high_open: bool) -> Callable[[str], T]:
    where = _interval(low, high, low_open, high_open)

    def parse(text: str) -> T:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what} in {where}, got {text!r}") from None
        if (isinstance(value, float) and not math.isfinite(value)) or \
                (low is not None and (value <= low if low_open else value < low)) or \
                (high is not None and (value >= high if high_open else value > high)):
            raise argparse.ArgumentTypeError(f"must be {what} in {where}, got {text}")
        return value

    parse.__name__ = convert.__name__  # argparse names the type in its own messages
    return parse


@dataclass(frozen=True)
class Bound:
    """The range of one setting: ``low .. high`` (``low_open``: ``low`` itself excluded), integers
    only when ``integer``. The one place a setting's range is written: its flag parses with
    :meth:`arg_type` (argparse refuses a value outside, naming the flag) and the Python options
    object checks the same range with :meth:`check`."""

    low: float
    high: float
    integer: bool = False
    low_open: bool = False

    def describe(self) -> str:
        return f"{'an integer' if self.integer else 'a finite number'} in " + \
            _interval(self.low, self.high, self.low_open, False)

    def check(self, value: object, name: str, error: type[BraveError] = BraveError) -> None:
        """``error`` naming ``name`` when ``value`` is not a number (an ``int`` when ``integer``) inside the bound."""
        kind_ok = isinstance(value, int) if self.integer else isinstance(value, (int, float))
        if isinstance(value, bool) or not kind_ok or (isinstance(value, float) and not math.isfinite(value)) \
                or value > self.high or (value <= self.low if self.low_open else value < self.low):  # type: ignore[operator]
            raise error(f"{name} must be {self.describe()}, got {value!r}")

    def arg_type(self) -> Callable[[str], Any]:
        """The argparse ``type=`` of a flag with this bound."""
        if self.integer:
            return int_in(int(self.low), int(self.high))
        return float_in(self.low, self.high, low_open=self.low_open)

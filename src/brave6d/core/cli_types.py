"""Bounded number types for ``argparse``: a flag outside its range is refused at start.

``type=float_in(0, 3600, low_open=True)`` makes ``--request-timeout nan`` (or ``inf``, ``-1``)
end the command before it does anything, with argparse's one-line error naming the flag
(``argument --request-timeout: must be a finite number in (0, 3600], got nan``), exit status 2.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TypeVar

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

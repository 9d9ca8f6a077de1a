"""Scriptable faults of the emulated controller, written as short strings (``--fault``).

========================  ==================================================================
``pstop@t=SECONDS``        protective stop at a controller time
``pstop@move=N``           protective stop half way through the N-th move (1 = the first)
``pstop@box=X0,Y0,Z0,X1,Y1,Z1``  protective stop when the TCP enters that box (base frame, m),
                           e.g. the arm touching something that stands there
``drop@t=SECONDS``         every RTDE connection dropped (the client sees a network failure)
``drop@move=N``            the same, half way through the N-th move
``program-stop@t=S``       the program stopped from the teach pendant (``@move=N`` too)
``refuse=N``               the first N RTDE connections are refused (closed at once)
``remote-off``             the pendant is in local control (ur-rtde refuses to connect)
``slow=SECONDS``           every command is answered that much later (wall-clock seconds)
========================  ==================================================================

Timed faults fire once. Parsing refuses anything else with a one-line error naming the text.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from brave6d.core.errors import BraveError

TRIGGERED = ("pstop", "drop", "program-stop")
STATIC = ("refuse", "remote-off", "slow")


class FaultSpecError(BraveError, ValueError):
    """A ``--fault`` text the emulator does not understand."""


@dataclass(frozen=True)
class Fault:
    """One fault: what happens and when (exactly one trigger for the timed kinds)."""

    kind: str
    at_time: float | None = None
    at_move: int | None = None
    box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    count: int = 0
    seconds: float = 0.0

    def __str__(self) -> str:
        if self.at_time is not None:
            return f"{self.kind}@t={self.at_time:g}"
        if self.at_move is not None:
            return f"{self.kind}@move={self.at_move}"
        if self.box is not None:
            return f"{self.kind}@box=" + ",".join(f"{v:g}" for v in (*self.box[0], *self.box[1]))
        if self.kind == "refuse":
            return f"refuse={self.count}"
        if self.kind == "slow":
            return f"slow={self.seconds:g}"
        return self.kind


def _number(text: str, what: str, spec: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise FaultSpecError(f"--fault {spec!r}: {what} {text!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise FaultSpecError(f"--fault {spec!r}: {what} must be a finite number >= 0, got {text}")
    return value


def parse_fault(spec: str) -> Fault:
    """A :class:`Fault` from its text (see the module docstring)."""
    text = spec.strip()
    if len(text) > 200:
        raise FaultSpecError(f"--fault {text[:40]!r}...: longer than 200 characters")
    if text == "remote-off":
        return Fault("remote-off")
    for kind in ("refuse", "slow"):
        if text.startswith(kind + "="):
            value = _number(text[len(kind) + 1:], "the value", spec)
            if kind == "refuse":
                if value != int(value) or value > 1000:
                    raise FaultSpecError(f"--fault {spec!r}: refuse=N needs a whole number 0..1000")
                return Fault("refuse", count=int(value))
            if value > 600:
                raise FaultSpecError(f"--fault {spec!r}: slow=SECONDS must be at most 600")
            return Fault("slow", seconds=value)
    kind, sep, trigger = text.partition("@")
    if kind not in TRIGGERED or not sep:
        raise FaultSpecError(f"--fault {spec!r}: expected one of pstop@..., drop@..., program-stop@... "
                             "(t=SECONDS, move=N or, for pstop, box=X0,Y0,Z0,X1,Y1,Z1), refuse=N, slow=SECONDS "
                             "or remote-off")
    key, eq, value = trigger.partition("=")
    if not eq:
        raise FaultSpecError(f"--fault {spec!r}: the trigger needs a value (e.g. {kind}@t=3)")
    if key == "t":
        return Fault(kind, at_time=_number(value, "the time", spec))
    if key == "move":
        n = _number(value, "the move number", spec)
        if n != int(n) or n < 1:
            raise FaultSpecError(f"--fault {spec!r}: move=N needs a whole number >= 1")
        return Fault(kind, at_move=int(n))
    if key == "box" and kind == "pstop":
        parts = value.split(",")
        if len(parts) != 6:
            raise FaultSpecError(f"--fault {spec!r}: box needs six numbers X0,Y0,Z0,X1,Y1,Z1")
        nums = []
        for p in parts:
            try:
                v = float(p)
            except ValueError:
                raise FaultSpecError(f"--fault {spec!r}: {p!r} is not a number") from None
            if not math.isfinite(v):
                raise FaultSpecError(f"--fault {spec!r}: box coordinates must be finite")
            nums.append(v)
        lo, hi = tuple(nums[:3]), tuple(nums[3:])
        if any(a >= b for a, b in zip(lo, hi)):
            raise FaultSpecError(f"--fault {spec!r}: each box minimum must be below its maximum")
        return Fault(kind, box=(lo, hi))  # type: ignore[arg-type]
    raise FaultSpecError(f"--fault {spec!r}: unknown trigger {key!r} (t=, move=" +
                         (" or box=" if kind == "pstop" else "") + ")")

"""``brave6d.core.cli_types``: a bounded flag either parses to a finite value inside its bounds or is
refused with argparse's one-line error naming the flag; never NaN, inf or an overflow traceback."""

from __future__ import annotations

import argparse
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from brave6d.core.cli_types import float_in, int_in

texts = st.one_of(st.text(max_size=30), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                  st.integers(-(10 ** 500), 10 ** 500).map(str), st.sampled_from(["nan", "-inf", "1e400", "0x10"]))


@given(texts)
def test_a_float_flag_is_finite_and_inside_or_refused(text: str) -> None:
    parse = float_in(0, 3600, low_open=True)
    try:
        value = parse(text)
    except argparse.ArgumentTypeError as exc:
        assert "in (0, 3600]" in str(exc)
    else:
        assert math.isfinite(value) and 0 < value <= 3600


@given(texts)
def test_an_int_flag_is_inside_or_refused(text: str) -> None:
    parse = int_in(1, 1_000_000)
    try:
        value = parse(text)
    except argparse.ArgumentTypeError as exc:
        assert "in [1, 1000000]" in str(exc)  # integer bounds in full, not 1e+06
    else:
        assert isinstance(value, int) and 1 <= value <= 1_000_000


def test_the_error_names_the_flag_and_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="brave6d serve")
    parser.add_argument("--request-timeout", type=float_in(0, 3600, low_open=True))
    assert parser.parse_args(["--request-timeout", "2.5"]).request_timeout == 2.5
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args(["--request-timeout", "nan"])
    assert exit_.value.code == 2
    assert "argument --request-timeout: must be a finite number in (0, 3600], got nan" in capsys.readouterr().err


def test_a_bound_checks_python_values_with_the_same_range_as_its_flag() -> None:
    """``Bound``: one range for a flag (``arg_type``) and for the options object (``check``); a huge
    integer is refused like any other out-of-range value, not with an OverflowError."""
    from brave6d.core.cli_types import Bound
    from brave6d.core.errors import BraveError

    bound = Bound(1, 10_000, integer=True)
    assert bound.arg_type()("42") == 42
    bound.check(42, "--max-episodes")
    for bad in (0, 10_001, 10 ** 400, 2.0, True, "3"):
        with pytest.raises(BraveError, match=r"--max-episodes must be an integer in \[1, 10000\]"):
            bound.check(bad, "--max-episodes")
    timeout = Bound(0, 3600, low_open=True)
    for bad in (0, float("nan"), float("inf"), 3600.5):
        with pytest.raises(BraveError, match=r"must be a finite number in \(0, 3600\]"):
            timeout.check(bad, "--request-timeout")

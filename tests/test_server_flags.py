"""Every number the servers take is bounded when it is given (issue #32 item 6): the flags of
``brave6d serve``, ``ros1`` and ``ros2`` refuse NaN, inf, negative and too-large values at parse
time with exit status 2 and a line naming the flag (nothing starts), and :class:`ServerLimits`
refuses them in the API, naming the field."""

from __future__ import annotations

import importlib
import math
from dataclasses import fields
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from brave6d.cli import COMMANDS as CLI_COMMANDS
from brave6d.cli import main
from brave6d.serve import LimitError, ServerLimits
from brave6d.serve.limits import BOUNDS

COMMANDS = {c.name: c.module for c in CLI_COMMANDS if c.name in ("serve", "ros1", "ros2")}

BAD = [
    ("serve", "--request-timeout", "nan"), ("serve", "--request-timeout", "inf"), ("serve", "--request-timeout", "0"),
    ("serve", "--request-timeout", "1e9"), ("serve", "--idle-timeout", "-1"), ("serve", "--idle-timeout", "nan"),
    ("serve", "--max-episodes", "0"), ("serve", "--max-episodes", "10000000"), ("serve", "--max-body-bytes", "10"),
    ("serve", "--max-body-bytes", str(2**40)), ("serve", "--max-memory-mb", "-5"),
    ("serve", "--max-memory-mb", "nan"), ("serve", "--max-loaded-scenes", "0"), ("serve", "--port", "70000"),
    ("serve", "--port", "-1"), ("serve", "--header-timeout", "0"), ("serve", "--header-timeout", "inf"),
    ("serve", "--body-timeout", "-1"), ("serve", "--body-timeout", "nan"), ("serve", "--max-client-connections", "0"),
    ("serve", "--max-client-connections", "100000"), ("serve", "--max-episodes", "1.5"),
    ("ros1", "--idle-timeout", "-1"), ("ros1", "--idle-timeout", "nan"), ("ros1", "--width", "20000"),
    ("ros1", "--height", "0"), ("ros1", "--twist-duration", "inf"), ("ros1", "--twist-duration", "0"),
    ("ros2", "--idle-timeout", "nan"), ("ros2", "--width", "-3"), ("ros2", "--height", "99999"),
    ("ros2", "--twist-duration", "nan"), ("ros2", "--twist-duration", "1e6"), ("ros2", "--domain-id", "233"),
    ("ros2", "--domain-id", "-1"),
]


@pytest.fixture
def started(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Replaces each command's ``run`` by one that records its arguments (so nothing starts)."""
    calls: dict[str, Any] = {}
    for name, module in COMMANDS.items():
        monkeypatch.setattr(importlib.import_module(module), "run",
                            lambda args, name=name: calls.setdefault(name, args) and 0)
    return calls


@pytest.mark.parametrize("command,flag,value", BAD, ids=[f"{c} {f} {v}" for c, f, v in BAD])
def test_out_of_range_flags_end_the_command_naming_the_flag(command: str, flag: str, value: str,
                                                            started: dict[str, Any],
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([command, "some/bundle", f"{flag}={value}"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()  # argparse's usage, then one line naming the flag
    assert err[-1].startswith(f"brave6d {command}: error: argument {flag}: must be") and value in err[-1], err
    assert sum("error" in line for line in err) == 1, err
    assert command not in started


def test_good_values_reach_the_server(started: dict[str, Any]) -> None:
    assert main(["serve", "b", "--request-timeout", "2.5", "--idle-timeout", "60", "--header-timeout", "3",
                 "--body-timeout", "4", "--max-client-connections", "8", "--max-body-bytes", "2048",
                 "--port", "0", "--max-memory-mb", "512", "--max-loaded-scenes", "2", "--max-episodes", "5"]) == 0
    args = started["serve"]
    assert (args.request_timeout, args.idle_timeout, args.header_timeout, args.body_timeout) == (2.5, 60, 3, 4)
    assert (args.max_client_connections, args.max_body_bytes, args.port, args.max_memory_mb) == (8, 2048, 0, 512)
    assert main(["ros2", "b", "--width", "64", "--height", "48", "--twist-duration", "0.2", "--domain-id", "7"]) == 0
    assert (started["ros2"].width, started["ros2"].twist_duration, started["ros2"].domain_id) == (64, 0.2, 7)


def test_serve_defaults_are_the_server_limits_defaults(started: dict[str, Any]) -> None:
    main(["serve", "b"])
    args, d = started["serve"], ServerLimits()
    assert (args.request_timeout, args.idle_timeout, args.max_episodes, args.max_body_bytes, args.header_timeout,
            args.body_timeout, args.max_client_connections) == (
        d.request_timeout_s, d.idle_timeout_s, d.max_episodes, d.max_body_bytes, d.header_timeout_s,
        d.body_timeout_s, d.max_connections_per_client)


LIMIT_FIELDS = [f.name for f in fields(ServerLimits)]


@given(st.sampled_from(LIMIT_FIELDS), st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                                                 st.integers(-(2**40), 2**40), st.booleans()))
def test_server_limits_accept_exactly_their_bounds(name: str, value: Any) -> None:
    bound = BOUNDS[name]
    inside = (not isinstance(value, bool) and (isinstance(value, int) or not bound.integer)
              and math.isfinite(value) and value <= bound.high
              and (value > bound.low if bound.low_open else value >= bound.low))
    if inside:
        assert getattr(ServerLimits(**{name: value}), name) == value
    else:
        with pytest.raises(LimitError, match=f"ServerLimits.{name} must be"):
            ServerLimits(**{name: value})


def test_a_nan_timeout_cannot_build_a_server() -> None:
    for name in ("request_timeout_s", "idle_timeout_s", "header_timeout_s", "body_timeout_s"):
        with pytest.raises(LimitError, match=name):
            ServerLimits(**{name: math.nan})

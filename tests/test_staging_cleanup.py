"""Staged folders (issue 32, item 12): the staging folder that a killed process left beside its
target is removed by the next staging of that target, never one whose owner still runs (on this
machine: its pid; on another: its heartbeat), nor another target's."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import pytest
from lock_holder import kill_holder, spawn_holder
from test_locks import dead_process, write_lock

from brave6d.core.atomic import staged_folder
from brave6d.core.locks import STALE_S, Process

ORPHAN_STAGING_S = 24 * 3600.0  # brave6d.core.atomic.ORPHAN_STAGING_S


def _leftover(parent: Path, name: str, owner: Process | None, heartbeat: float | None = None) -> Path:
    staging = parent / name
    staging.mkdir()
    (staging / "half.zip").write_bytes(b"PK half")
    if owner is not None:
        write_lock(parent / f"{name}.owner", owner, heartbeat)
    return staging


def test_staging_cleans_what_dead_owners_left_and_keeps_a_live_ones(tmp_path: Path,
                                                                    caplog: pytest.LogCaptureFixture) -> None:
    target = tmp_path / "out"
    dead = _leftover(tmp_path, ".out.tmp-deadbeef", dead_process())
    far = _leftover(tmp_path, ".out.tmp-farfresh", Process("node-elsewhere", 4242, "boot-b", 1))
    gone_far = _leftover(tmp_path, ".out.tmp-farstale", Process("node-elsewhere", 4243, "boot-b", 1),
                         heartbeat=time.time() - STALE_S - 5)
    ownerless_old = _leftover(tmp_path, ".out.tmp-oldolder", None)
    old = time.time() - ORPHAN_STAGING_S - 60
    os.utime(ownerless_old, (old, old))
    ownerless_new = _leftover(tmp_path, ".out.tmp-newnewer", None)
    other_target = _leftover(tmp_path, ".other.tmp-deadbeef", dead_process())
    live_staging = tmp_path / ".out.tmp-livelive"
    live_staging.mkdir()
    proc, _ = spawn_holder(tmp_path / ".out.tmp-livelive.owner")
    try:
        with caplog.at_level(logging.WARNING, logger="brave6d.core.atomic"):
            with staged_folder(target) as stage:
                (stage / "a.txt").write_text("new")
        assert (target / "a.txt").read_text() == "new"
        assert not dead.exists() and not (tmp_path / ".out.tmp-deadbeef.owner").exists()
        assert not gone_far.exists() and not ownerless_old.exists()
        assert far.exists() and ownerless_new.exists() and other_target.exists() and live_staging.exists()
        assert f"removed {dead}, the staging folder of {dead_process().describe()}, which is gone" in caplog.text
    finally:
        kill_holder(proc)
    from brave6d.core.atomic import clean_stagings

    assert clean_stagings(target) == [live_staging] and not live_staging.exists()
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([".other.tmp-deadbeef", ".other.tmp-deadbeef.owner", ".out.tmp-farfresh",
                           ".out.tmp-farfresh.owner", ".out.tmp-newnewer", "out"])

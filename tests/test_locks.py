"""``brave6d.core.locks`` (issue 32, items 11 and 12): a lock names its holder, refuses while that runs,
is taken over once it is gone (dead pid, reused pid, zombie, stale heartbeat of another machine,
requeued Slurm job), and concurrent takers get exactly one owner."""

from __future__ import annotations

import functools
import json
import logging
import multiprocessing
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lock_holder import kill_holder, spawn_holder

from brave6d.core.locks import STALE_S, FileLock, Holder, LockHeld, Process, read_holder


@functools.cache
def dead_process() -> Process:
    """A process of this machine that has exited (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "import os, sys; print(open(f'/proc/{os.getpid()}/stat').read())"],
                            stdout=subprocess.PIPE, text=True)
    out, _ = proc.communicate()
    me = Process.current()
    ticks = int(out[out.rfind(")") + 2:].split()[19])
    return Process(me.host, proc.pid, me.boot_id, ticks)


def write_lock(path: Path, process: Process, heartbeat: float | None = None) -> Holder:
    now = time.time()
    holder = Holder(process, "f" * 32, "test", now, now if heartbeat is None else heartbeat)
    path.write_text(json.dumps(holder.to_json()))
    return holder


def test_a_live_holder_is_named_and_a_killed_one_is_taken_over(tmp_path: Path,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "scene.lock"
    proc, holder = spawn_holder(path)
    try:
        with pytest.raises(LockHeld, match=rf"held by {socket.gethostname()} \(pid {holder.pid}\) since .*still running"):
            FileLock(path).acquire()
        assert read_holder(path).process == holder  # untouched
    finally:
        kill_holder(proc)
    lock = FileLock(path, "second")
    with caplog.at_level(logging.WARNING, logger="brave6d.core.locks"):
        taken = lock.acquire()
    try:
        assert taken is not None and taken.process == holder
        assert f"took over the lock of {holder.host} (pid {holder.pid}), which is gone (pid {holder.pid} is not running)" \
            in caplog.text
        assert read_holder(path).process.pid == os.getpid() and read_holder(path).purpose == "second"
    finally:
        lock.release()
    assert not path.exists()


def test_a_reused_pid_or_a_zombie_is_not_the_holder(tmp_path: Path) -> None:
    me = Process.current()
    assert me.start_ticks is not None
    reused = Process(me.host, me.pid, me.boot_id, me.start_ticks + 1)  # our pid, started at another time
    assert reused.gone() == f"pid {me.pid} is another process now"
    assert me.gone() is None
    zombie = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        deadline = time.monotonic() + 60
        while Process(me.host, zombie.pid).gone() is None and time.monotonic() < deadline:
            time.sleep(0.01)  # exits, but is not reaped: a zombie
        assert Process(me.host, zombie.pid).gone() == f"pid {zombie.pid} has exited"
    finally:
        zombie.wait()
    assert Process(me.host, zombie.pid).gone() == f"pid {zombie.pid} is not running"


def test_a_holder_on_another_machine_lives_by_its_heartbeat(tmp_path: Path) -> None:
    path = tmp_path / "scene.lock"
    elsewhere = Process("node-elsewhere", 4242, "another-boot", 1, job="77", restarts=0)
    write_lock(path, elsewhere)  # fresh heartbeat: alive, whatever its pid does here
    with pytest.raises(LockHeld, match=r"node-elsewhere \(pid 4242\) since .*; its heartbeat is \d+ s old"):
        FileLock(path).acquire()
    write_lock(path, elsewhere, heartbeat=time.time() - STALE_S - 5)
    lock = FileLock(path)
    taken = lock.acquire()
    lock.release()
    assert taken is not None and taken.process == elsewhere
    assert "heartbeat is" in (taken.dead_because() or "")


def test_a_requeued_slurm_job_takes_its_own_lock_over(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "scene.lock"
    write_lock(path, Process("node-a", 4242, "boot-a", 1, job="77", restarts=0))
    monkeypatch.setenv("SLURM_JOB_ID", "77")
    monkeypatch.setenv("SLURM_RESTART_COUNT", "0")
    with pytest.raises(LockHeld):  # the same incarnation (e.g. a shell inside the allocation)
        FileLock(path).acquire()
    monkeypatch.setenv("SLURM_RESTART_COUNT", "1")
    lock = FileLock(path)
    assert lock.acquire() is not None
    lock.release()


def test_heartbeat_and_release_touch_only_our_own_lock(tmp_path: Path) -> None:
    path = tmp_path / "scene.lock"
    lock = FileLock(path, heartbeat_s=3600)
    lock.acquire()
    first = read_holder(path)
    assert first is not None
    lock.refresh()
    second = read_holder(path)
    assert second is not None and second.token == first.token and second.heartbeat >= first.heartbeat
    other = write_lock(path, Process("node-b", 9, "boot-b", 1))  # taken over while we looked dead
    lock.refresh()
    assert lock.lost is not None and "taken over by node-b (pid 9)" in lock.lost and not lock.held
    lock.release()
    assert read_holder(path) == other  # not removed: it is not ours


def test_a_lock_file_that_is_not_one_is_kept_while_fresh(tmp_path: Path) -> None:
    path = tmp_path / "scene.lock"
    path.write_text("{not json")
    with pytest.raises(LockHeld, match="an unreadable lock file, changed at"):
        FileLock(path).acquire()
    old = time.time() - STALE_S - 5
    os.utime(path, (old, old))
    lock = FileLock(path)
    assert lock.acquire() is not None
    assert read_holder(path).process.pid == os.getpid()
    lock.release()


@settings(max_examples=12)
@given(takers=st.integers(2, 12), dead_first=st.booleans())
def test_concurrent_takers_get_exactly_one_owner(tmp_path_factory: pytest.TempPathFactory, takers: int,
                                                 dead_first: bool) -> None:
    path = tmp_path_factory.mktemp("race") / "scene.lock"
    if dead_first:
        write_lock(path, dead_process())
    barrier = threading.Barrier(takers)
    owners: list[FileLock] = []
    refused: list[str] = []
    guard = threading.Lock()

    def take() -> None:
        lock = FileLock(path, heartbeat_s=3600)
        barrier.wait()
        try:
            lock.acquire()
        except LockHeld as exc:
            with guard:
                refused.append(exc.holder.token)
            return
        with guard:
            owners.append(lock)

    threads = [threading.Thread(target=take) for _ in range(takers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    try:
        assert len(owners) == 1 and len(refused) == takers - 1
        holder = read_holder(path)
        assert holder is not None and holder.process.pid == os.getpid()
    finally:
        for lock in owners:
            lock.release()


def _contend(path: str, barrier: object, results: object, done: object) -> None:
    lock = FileLock(path, heartbeat_s=3600)
    barrier.wait()  # type: ignore[attr-defined]
    try:
        lock.acquire()
    except LockHeld:
        results.put("refused")  # type: ignore[attr-defined]
        return
    results.put(f"owner {os.getpid()}")  # type: ignore[attr-defined]
    done.wait(120)  # type: ignore[attr-defined]
    lock.release()


@pytest.mark.slow
@pytest.mark.parametrize("dead_first", [False, True])
def test_concurrent_processes_get_exactly_one_owner(tmp_path: Path, dead_first: bool) -> None:
    path = tmp_path / "scene.lock"
    if dead_first:
        write_lock(path, dead_process())
    ctx = multiprocessing.get_context("spawn")
    n = 6
    barrier, results, done = ctx.Barrier(n), ctx.Queue(), ctx.Event()
    procs = [ctx.Process(target=_contend, args=(str(path), barrier, results, done)) for _ in range(n)]
    for p in procs:
        p.start()
    outcomes = [results.get(timeout=120) for _ in range(n)]
    owner = read_holder(path)
    done.set()
    for p in procs:
        p.join(120)
    assert owner is not None and sorted(outcomes) == sorted([f"owner {owner.process.pid}", *["refused"] * (n - 1)])
    assert not path.exists()

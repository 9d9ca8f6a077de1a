"""Locks that name their holder: one owner at a time, taken over once the holder is gone.

A lock is a small JSON file (format :data:`FORMAT`) saying who holds it: host, pid, the kernel's
boot id and the process's start time (from ``/proc/<pid>/stat``, against pid reuse), the Slurm
job id and restart count when there are any, when it was taken, and a heartbeat time stamp that a
daemon thread of the holder rewrites every :data:`HEARTBEAT_S` seconds.

The holder is alive when:

- it ran on this machine (same host name and boot id): its pid still runs, as the same process
  (same start time), and is not a zombie;
- it ran on another machine, whose pids cannot be checked from here: its heartbeat is younger
  than :data:`STALE_S`, unless this process is the same Slurm job requeued (a higher
  ``SLURM_RESTART_COUNT``: Slurm runs one incarnation of a job at a time).

Taking a free lock creates the file whole with ``link(2)``, which fails when the file exists
(atomic on local file systems and on NFS). Taking over a dead holder's lock, refreshing the
heartbeat and releasing run under a kernel record lock (``fcntl.lockf``) on ``<lock>.guard``
(and a thread lock inside this process); the kernel drops it when its process dies, so it never
goes stale, and two processes never both take over the same dead lock.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import secrets
import socket
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from brave6d.core.errors import BraveError

log = logging.getLogger(__name__)

FORMAT = "brave6d-lock/1"
#: Seconds between two heartbeats of a lock's holder.
HEARTBEAT_S = 30.0
#: A holder on another machine whose heartbeat is older than this is taken for dead: 20 missed
#: heartbeats, so that a loaded node, a slow shared file system or clocks a little apart never
#: lose a live job its lock; what it costs is the wait before a crashed node's scene runs again.
STALE_S = 600.0
#: Seconds to wait for the guard (held for milliseconds by whoever has it) before giving up.
GUARD_WAIT_S = 30.0
#: errno values of a file system that has no POSIX record locks (the guard is then skipped).
_NO_LOCKS = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}
#: errno values of a file system that has no hard links (the lock is then created with O_EXCL).
_NO_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOSYS, errno.EXDEV}


class LockError(BraveError):
    """A lock could not be taken or kept (the message names the lock file)."""


class LockHeld(LockError):
    """The lock is held by a live process, named in the message (``holder``)."""

    def __init__(self, path: Path, holder: Holder) -> None:
        self.path, self.holder = path, holder
        if holder.process.pid > 0 and holder.process.on_this_machine():
            why = f"held by {holder.describe()} since {holder.since_text()}, which is still running"
        elif holder.process.pid > 0:
            why = (f"held by {holder.describe()} since {holder.since_text()}; its heartbeat is "
                   f"{max(0.0, time.time() - holder.heartbeat):.0f} s old (a holder on another machine is taken "
                   f"for dead after {STALE_S:.0f} s without one)")
        else:
            why = (f"{holder.describe()}, changed at {holder.since_text()}; it is taken over {STALE_S:.0f} s after "
                   "that (or remove it if nothing is running)")
        super().__init__(f"{path}: {why}")


@dataclass(frozen=True)
class Process:
    """Who a process is, with what it takes to tell later whether it still runs."""

    host: str
    pid: int
    boot_id: str | None = None
    start_ticks: int | None = None
    job: str | None = None
    restarts: int = 0

    @classmethod
    def current(cls) -> Process:
        pid = os.getpid()
        stat = _proc_stat(pid)
        return cls(socket.gethostname(), pid, _boot_id(), stat[1] if stat else None,
                   os.environ.get("SLURM_JOB_ID") or None, _int(os.environ.get("SLURM_RESTART_COUNT")))

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Process:
        """Read the fields :meth:`to_json` writes; missing or odd ones become unknown."""
        ticks = data.get("start_ticks")
        return cls(str(data.get("host", "?")), _int(data.get("pid")), _str_or_none(data.get("boot_id")),
                   ticks if isinstance(ticks, int) else None, _str_or_none(data.get("job")),
                   _int(data.get("restarts")))

    def to_json(self) -> dict[str, Any]:
        return {"host": self.host, "pid": self.pid, "boot_id": self.boot_id, "start_ticks": self.start_ticks,
                "job": self.job, "restarts": self.restarts}

    def describe(self) -> str:
        return f"{self.host} (pid {self.pid})" if self.pid > 0 else self.host

    def on_this_machine(self) -> bool:
        """True when the process ran on this machine since its last boot (its pid can be checked here)."""
        if self.host != socket.gethostname() or self.pid <= 0:
            return False
        here = _boot_id()
        return self.boot_id is None or here is None or self.boot_id == here

    def gone(self) -> str | None:
        """Why this process of this machine no longer runs, or None while it does (see
        :meth:`on_this_machine`; a process of another machine is never found gone here)."""
        if not self.on_this_machine():
            return None
        stat = _proc_stat(self.pid)
        if stat is None:
            try:
                os.kill(self.pid, 0)
            except ProcessLookupError:
                return f"pid {self.pid} is not running"
            except PermissionError:  # another user's process (hidden from /proc by hidepid)
                return None
            return None
        state, ticks = stat
        if state in ("Z", "X"):
            return f"pid {self.pid} has exited"
        if self.start_ticks is not None and ticks != self.start_ticks:
            return f"pid {self.pid} is another process now"
        return None


@dataclass(frozen=True)
class Holder:
    """What a lock file says: the holding process, its token, purpose and time stamps (Unix seconds)."""

    process: Process
    token: str
    purpose: str
    since: float
    heartbeat: float

    def describe(self) -> str:
        return self.process.describe()

    def since_text(self) -> str:
        return time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(self.since))

    def dead_because(self, me: Process | None = None, now: float | None = None) -> str | None:
        """Why the holder is gone (the lock may then be taken over), or None while it is alive."""
        p = self.process
        if p.on_this_machine():
            return p.gone()
        me = me or Process.current()
        if p.job is not None and p.job == me.job and p.restarts < me.restarts:
            return f"Slurm job {p.job} was requeued (restart {me.restarts})"
        age = (time.time() if now is None else now) - self.heartbeat
        if age > STALE_S:
            return f"its heartbeat is {age:.0f} s old (a holder on another machine is dead after {STALE_S:.0f} s)"
        return None

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, **self.process.to_json(), "token": self.token, "purpose": self.purpose,
                "since": self.since, "heartbeat": self.heartbeat,
                "since_text": self.since_text()}


def read_holder(path: Path | str) -> Holder | None:
    """The holder named by lock file ``path``, or None when there is no lock.

    A lock file that is not one (empty, edited, cut short) stands for an unknown holder on no
    machine with the file's modification time as its heartbeat: it is taken over once that is
    older than :data:`STALE_S`.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
        st = p.stat()
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError):
        text, st = "", None
    try:
        data = json.loads(text)
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ValueError(FORMAT)
        return Holder(Process.from_json(data), str(data["token"]), str(data.get("purpose", "")),
                      float(data["since"]), float(data["heartbeat"]))
    except (ValueError, KeyError, TypeError):
        mtime = st.st_mtime if st is not None else time.time()
        stamp = f"unreadable:{st.st_ino if st else 0}:{st.st_mtime_ns if st else 0}"
        return Holder(Process("an unreadable lock file", 0), stamp, "", mtime, mtime)


class FileLock:
    """A lock file naming its holder (module docstring); ``with lock:`` holds it for the block.

    ``guarded=False`` is for a lock nobody takes over (a unique name, e.g. the owner of a staging
    folder): it makes no ``.guard`` file, and a held lock is refused whether its holder is alive
    or not.
    """

    def __init__(self, path: Path | str, purpose: str = "", *, guarded: bool = True,
                 heartbeat_s: float = HEARTBEAT_S) -> None:
        self.path, self.purpose, self.guarded, self.heartbeat_s = Path(path), purpose, guarded, heartbeat_s
        self.lost: str | None = None
        self._holder: Holder | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def held(self) -> bool:
        return self._holder is not None and self.lost is None

    def acquire(self) -> Holder | None:
        """Take the lock: None when it was free, the dead holder's record when it was taken over.

        Raises :class:`LockHeld` naming the holder while that is alive.
        """
        if self._holder is not None:
            raise LockError(f"{self.path}: already held by this lock object")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        me, now = Process.current(), time.time()
        mine = Holder(me, secrets.token_hex(16), self.purpose, now, now)
        for _ in range(100):  # each round ends, or sees another process change the lock
            if _create(self.path, mine):
                return self._took(mine, None)
            holder = read_holder(self.path)
            if holder is None:
                continue  # released in between
            why = holder.dead_because(me) if self.guarded else None
            if why is None:
                raise LockHeld(self.path, holder)
            with _guard(self.path):
                if read_holder(self.path) != holder:
                    continue  # refreshed, released or taken over in between: look again
                _write(self.path, mine)
            log.warning("%s: took over the lock of %s, which is gone (%s)", self.path, holder.describe(), why)
            return self._took(mine, holder)
        raise LockError(f"{self.path}: the lock changed hands 100 times while taking it; try again")

    def _took(self, mine: Holder, dead: Holder | None) -> Holder | None:
        self._holder, self.lost = mine, None
        self._stop.clear()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat {self.path.name}", daemon=True)
        self._thread.start()
        return dead

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_s):
            try:
                self.refresh()
            except (OSError, LockError) as exc:  # a file system hiccup: try again at the next beat
                log.warning("%s: heartbeat not written (%s)", self.path, exc)
            if self.lost is not None:
                return

    def refresh(self) -> None:
        """Write a new heartbeat; notes in :attr:`lost` (and logs) when the lock is no longer ours."""
        mine = self._holder
        if mine is None or self.lost is not None:
            return
        with self._maybe_guard():
            current = read_holder(self.path)
            if current is None or current.token != mine.token:
                self.lost = (f"{self.path}: the lock was taken over by {current.describe()}" if current is not None
                             else f"{self.path}: the lock file was removed")
                log.error("%s", self.lost)
                return
            mine = Holder(mine.process, mine.token, mine.purpose, mine.since, time.time())
            _write(self.path, mine)
            self._holder = mine

    def release(self) -> None:
        """Stop the heartbeat and remove the lock file if it is still ours."""
        mine, self._holder = self._holder, None
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=GUARD_WAIT_S + 5)
        self._thread = None
        if mine is None:
            return
        try:
            with self._maybe_guard():
                current = read_holder(self.path)
                if current is not None and current.token == mine.token:
                    self.path.unlink(missing_ok=True)
        except (OSError, LockError) as exc:  # left behind: taken over once this process is gone
            log.warning("%s: lock not removed (%s)", self.path, exc)

    def _maybe_guard(self) -> Any:
        return _guard(self.path) if self.guarded else suppress()

    def __enter__(self) -> FileLock:
        if self._holder is None:
            self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


# ----------------------------------------------------------------------------- file operations
def _create(path: Path, holder: Holder) -> bool:
    """Create ``path`` holding ``holder`` if it does not exist: True when this call made it."""
    tmp = _write_tmp(path, holder)
    try:
        try:
            os.link(tmp, path)
            return True
        except FileExistsError:
            return False
        except OSError as exc:
            if exc.errno in _NO_LINKS:
                return _create_excl(path, holder)
            with suppress(OSError):  # NFS: the link may have been made and its reply lost
                if os.stat(tmp).st_nlink == 2:
                    return True
            raise
    finally:
        with suppress(OSError):
            os.unlink(tmp)


def _create_excl(path: Path, holder: Holder) -> bool:
    """:func:`_create` without hard links: ``O_CREAT | O_EXCL`` (readers may see it empty for a moment)."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        handle.write(json.dumps(holder.to_json()) + "\n")
        handle.flush()
        os.fsync(handle.fileno())
    return True


def _write(path: Path, holder: Holder) -> None:
    """Replace ``path`` with a file holding ``holder`` in one rename."""
    tmp = _write_tmp(path, holder)
    try:
        os.replace(tmp, path)
    except BaseException:
        with suppress(OSError):
            os.unlink(tmp)
        raise


def _write_tmp(path: Path, holder: Holder) -> Path:
    tmp = path.with_name(f".{path.name}.{holder.token[:8]}-{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(json.dumps(holder.to_json()) + "\n")
            handle.flush()
            os.fsync(handle.fileno())
    except BaseException:
        with suppress(OSError):
            os.unlink(tmp)
        raise
    return tmp


_THREAD_GUARDS: dict[str, threading.Lock] = {}
_THREAD_GUARDS_LOCK = threading.Lock()
_warned_no_locks: set[str] = set()


@contextmanager
def _guard(path: Path) -> Iterator[None]:
    """Hold ``<path>.guard``: a thread lock in this process and a kernel record lock across processes."""
    import fcntl

    guard = path.with_name(path.name + ".guard")
    with _THREAD_GUARDS_LOCK:
        local = _THREAD_GUARDS.setdefault(str(guard.resolve()), threading.Lock())
    if not local.acquire(timeout=GUARD_WAIT_S):
        raise LockError(f"{guard}: busy for {GUARD_WAIT_S:.0f} s in this process")
    try:
        fd = os.open(guard, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            deadline = time.monotonic() + GUARD_WAIT_S
            while True:
                try:
                    fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as exc:
                    if exc.errno in _NO_LOCKS:
                        if str(guard.parent) not in _warned_no_locks:
                            _warned_no_locks.add(str(guard.parent))
                            log.warning("%s: the file system has no record locks (%s); lock take-overs there are "
                                        "not serialised", guard.parent, exc.strerror)
                        break
                    if exc.errno not in (errno.EAGAIN, errno.EACCES) or time.monotonic() > deadline:
                        raise LockError(f"{guard}: cannot lock it ({exc.strerror})") from None
                    time.sleep(0.02)
            yield
        finally:
            os.close(fd)  # drops the record lock
    finally:
        local.release()


# ----------------------------------------------------------------------------- /proc
def _proc_stat(pid: int) -> tuple[str, int] | None:
    """``(state, start time in clock ticks since boot)`` of ``pid`` from ``/proc``, or None."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except (OSError, ValueError):
        return None
    fields = text[text.rfind(")") + 2:].split()  # the command name may hold spaces and parentheses
    try:
        return fields[0], int(fields[19])
    except (IndexError, ValueError):
        return None


def _boot_id() -> str | None:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip() or None
    except OSError:
        return None


def _int(value: Any) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        return 0


def _str_or_none(value: Any) -> str | None:
    return None if value is None else str(value)

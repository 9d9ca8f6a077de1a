"""ur-rtde in a process of its own, so that nothing it does can end the capture without a message.

ur-rtde 1.6.5 has paths that take the whole Python process down: after the RTDE socket drops,
``RTDEControlInterface``'s automatic reconnect loops and then segfaults; its constructors hold the
GIL while they wait. A capture that loaded it in-process would die at the first network blip with
a half-written frame. Here the library lives in a child process that this module starts and talks
to over a pipe (one JSON line per call); the parent never loads librtde.

* A call that does not answer within its timeout (a wedged call) kills the child and raises
  :class:`RobotClientError`; so does a child that dies (a segfault: the error names the signal and
  the last line ur-rtde printed). Later calls raise at once; reconnecting starts a new child.
* ur-rtde's own console output (it prints to stdout and stderr) goes to a log file, never to the
  terminal, so a failure is one line. The file's path is in :attr:`RTDEWorker.log_path`.
* The child ignores Ctrl-C and runs in its own session: the terminal's SIGINT reaches only the
  capture, which then stops the arm through the child (stopJ/stopL) before it exits.

The child is :mod:`brave6d.capture.ur_worker_child`, run as a script: it imports nothing of
brave6d (only the standard library and ur-rtde), so it starts in a few tens of milliseconds.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from brave6d.capture.protocols import RobotError

#: How long the child may take to connect (ur-rtde waits up to 5 s for synchronisation and 5 s for
#: its control script to start; a retry loop sits above this).
CONNECT_TIMEOUT_S = 30.0
#: Default answer time of one call (ur-rtde waits up to 3 s for the controller to be ready).
CALL_TIMEOUT_S = 10.0
MAX_REPLY = 1 << 20
CHILD = Path(__file__).resolve().with_name("ur_worker_child.py")


class RobotClientError(RobotError):
    """ur-rtde's process died, hung or refused a call; the message says which and what it last printed."""


class RTDEWorker:
    """A child process holding ur-rtde's ``RTDEReceiveInterface`` and ``RTDEControlInterface`` to ``host``."""

    def __init__(self, host: str, *, connect_timeout_s: float = CONNECT_TIMEOUT_S,
                 call_timeout_s: float = CALL_TIMEOUT_S) -> None:
        self.host = host
        self.call_timeout_s = call_timeout_s
        fd, name = tempfile.mkstemp(prefix="brave6d-ur-rtde-", suffix=".log")
        self.log_path = Path(name)
        reply_r, reply_w = os.pipe()
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-s", str(CHILD), str(reply_w)],
                stdin=subprocess.PIPE, stdout=fd, stderr=fd, pass_fds=(reply_w,), start_new_session=True,
                close_fds=True)
        finally:
            os.close(reply_w)
            os.close(fd)
        self._reply = reply_r
        self._buf = b""
        self._next_id = 0
        self._dead: str | None = None
        try:
            self.call("worker", "connect", host, timeout=connect_timeout_s)
        except BaseException as exc:
            self._kill()  # a failed connection leaves no process behind
            self.close()
            if isinstance(exc, RuntimeError) and not isinstance(exc, RobotClientError):
                self.log_path.unlink(missing_ok=True)  # ur-rtde answered: its error says it all
            raise

    # -------------------------------------------------------------- calls
    def call(self, target: str, method: str, *args: Any, timeout: float | None = None) -> Any:
        """``target.method(*args)`` in the child (``target``: control, receive or worker)."""
        if self._dead is not None:
            raise RobotClientError(self._dead)
        self._next_id += 1
        ident = self._next_id
        request = json.dumps({"id": ident, "target": target, "method": method, "args": list(args)})
        what = f"{target}.{method}"
        try:
            assert self._proc.stdin is not None
            self._proc.stdin.write(request.encode("ascii") + b"\n")
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            self._fail(what)
        deadline = time.monotonic() + (self.call_timeout_s if timeout is None else timeout)
        while True:
            reply = self._read_reply(what, deadline)
            if reply.get("id") == ident:
                break  # older ids: answers to calls a Ctrl-C abandoned
        if "error" in reply:
            raise RuntimeError(str(reply["error"]))
        return reply.get("ok")

    def _read_reply(self, what: str, deadline: float) -> dict[str, Any]:
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                self._kill()
                self._dead = (f"ur-rtde did not answer {what} within the time allowed; its process was stopped "
                              f"({self._last_words()})")
                raise RobotClientError(self._dead)
            ready, _, _ = select.select([self._reply], [], [], min(left, 0.5))
            if ready:
                chunk = os.read(self._reply, 65536)
                if not chunk:
                    self._fail(what)
                self._buf += chunk
                if len(self._buf) > MAX_REPLY:
                    self._kill()
                    self._dead = f"ur-rtde's process sent an oversized answer to {what}; it was stopped"
                    raise RobotClientError(self._dead)
            elif self._proc.poll() is not None:
                self._fail(what)
        line, self._buf = self._buf.split(b"\n", 1)
        return json.loads(line)

    def _fail(self, what: str) -> None:
        try:
            code = self._proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self._kill()
            code = self._proc.returncode
        how = f"was killed by {signal.Signals(-code).name}" if code is not None and code < 0 else \
            f"exited with status {code}"
        self._dead = f"ur-rtde's process {how} during {what} ({self._last_words()})"
        raise RobotClientError(self._dead)

    def _last_words(self) -> str:
        try:
            with open(self.log_path, "rb") as fh:
                fh.seek(max(0, os.path.getsize(self.log_path) - 4096))
                lines = [x.strip() for x in fh.read().decode("utf-8", "replace").splitlines() if x.strip()]
        except OSError:
            lines = []
        last = lines[-1][:200] if lines else ""
        return f"its last message: {last!r}; log {self.log_path}" if last else f"log {self.log_path}"

    def _kill(self) -> None:
        if self._proc.poll() is None:
            self._proc.kill()
            try:
                self._proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                pass

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self._proc.pid

    @property
    def alive(self) -> bool:
        return self._dead is None and self._proc.poll() is None

    def close(self) -> None:
        """Disconnect and end the child (killed if it does not end within 5 s); safe to call twice."""
        if self._dead is None and self._proc.poll() is None:
            try:
                self.call("worker", "close", timeout=5.0)
            except (RobotClientError, RuntimeError):
                pass
        self._dead = self._dead or "the ur-rtde connection is closed"
        try:
            if self._proc.stdin is not None:
                self._proc.stdin.close()
        except OSError:
            pass
        try:
            self._proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self._kill()
        try:
            os.close(self._reply)
        except OSError:
            pass
        if self._proc.returncode == 0:
            self.log_path.unlink(missing_ok=True)

    def __del__(self) -> None:  # a forgotten worker must not outlive its owner
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None:
            proc.kill()


class WorkerInterface:
    """One of ur-rtde's interfaces (``control`` or ``receive``) as the parent sees it: any method
    call goes to the child."""

    def __init__(self, worker: RTDEWorker, target: str) -> None:
        self._worker = worker
        self._target = target

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args: self._worker.call(self._target, name, *args)

    @property
    def worker(self) -> RTDEWorker:
        """The child process behind this interface."""
        return self._worker

    def release_client(self) -> None:
        """End the child process (both interfaces)."""
        self._worker.close()


def isolated_interfaces(host: str, *,
                        call_timeout_s: float = CALL_TIMEOUT_S) -> tuple[WorkerInterface, WorkerInterface]:
    """ur-rtde's control and receive interfaces to ``host``, in a child process."""
    worker = RTDEWorker(host, call_timeout_s=call_timeout_s)
    return WorkerInterface(worker, "control"), WorkerInterface(worker, "receive")

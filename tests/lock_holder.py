"""A process that holds a lock until it is killed, for the lock tests.

``python tests/lock_holder.py LOCK`` prints one JSON line (its :class:`brave6d.core.locks.Process`) once
it holds the lock, then sleeps; :func:`spawn_holder` starts it and waits for that line.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from brave6d.core.locks import FileLock, Process

ROOT = Path(__file__).resolve().parent.parent


def spawn_holder(lock: Path) -> tuple[subprocess.Popen[str], Process]:
    """Start a process holding ``lock``; returns it and who it is (as the lock records it)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, __file__, str(lock)], stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line, f"the lock holder exited ({proc.wait()}) without taking {lock}"
    return proc, Process.from_json(json.loads(line))


def kill_holder(proc: subprocess.Popen[str]) -> None:
    """SIGKILL the holder and reap it (no zombie left): its lock stays behind, its pid is gone."""
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


def main() -> None:
    FileLock(sys.argv[1], "test holder").acquire()
    print(json.dumps(Process.current().to_json()), flush=True)
    while True:
        time.sleep(60)


if __name__ == "__main__":
    main()

"""A ROS 1 master on loopback for a run, a test or a benchmark: ``rosmaster --core -p PORT`` in its
own process group (so that stopping it leaves nothing behind), with ``ROS_IP=127.0.0.1``."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
import xmlrpc.client
from pathlib import Path

from brave6d.core.errors import BraveError
from brave6d.ros_interface.ros1.ros_env import ROSMASTER, loopback_environment


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def master_is_up(uri: str, timeout: float = 1.0) -> bool:
    """True when a ROS master answers ``getSystemState`` at ``uri``."""
    old = socket.getdefaulttimeout()
    socket.setdefaulttimeout(timeout)
    try:
        code, _, _ = xmlrpc.client.ServerProxy(uri).getSystemState("/brave6d_probe")
        return int(code) == 1
    except (OSError, xmlrpc.client.Error):
        return False
    finally:
        socket.setdefaulttimeout(old)


def stop_group(proc: subprocess.Popen, timeout: float = 10.0) -> None:
    """SIGINT, then SIGKILL, to the process group of ``proc`` (started with ``start_new_session``)."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGINT)
            proc.wait(timeout=timeout)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(timeout=timeout)


class RosMaster:
    """``with RosMaster() as m:`` a master on ``m.uri`` (127.0.0.1, a free port unless ``port``)."""

    def __init__(self, port: int | None = None, log_file: Path | None = None, start_timeout: float = 20.0) -> None:
        self.port = port or free_port()
        self.uri = f"http://127.0.0.1:{self.port}"
        self.log_file = log_file
        self.start_timeout = start_timeout
        self.proc: subprocess.Popen | None = None

    def start(self) -> RosMaster:
        if not os.path.exists(ROSMASTER):
            raise BraveError(f"{ROSMASTER} not found: apt-get install python3-rosmaster")
        if master_is_up(self.uri):
            raise BraveError(f"a ROS master already answers at {self.uri}")
        env = loopback_environment(self.uri)
        env["ROS_LOG_DIR"] = env.get("ROS_LOG_DIR") or str(Path(self.log_file).parent if self.log_file else "/tmp")
        out = open(self.log_file, "ab") if self.log_file else subprocess.DEVNULL
        self.proc = subprocess.Popen([ROSMASTER, "--core", "-p", str(self.port)], env=env, stdout=out,
                                     stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + self.start_timeout
        while not master_is_up(self.uri):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise BraveError(f"rosmaster did not start on {self.uri} (see {self.log_file or 'its output'})")
            time.sleep(0.1)
        return self

    def stop(self) -> None:
        if self.proc is not None:
            stop_group(self.proc)
            self.proc = None

    def __enter__(self) -> RosMaster:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

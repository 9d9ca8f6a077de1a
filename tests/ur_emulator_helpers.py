"""Starting ``brave6d ur-emulator`` processes for tests: each on its own loopback address (ur-rtde's
ports are fixed), its event log in a file, stopped with SIGTERM when the test ends."""

from __future__ import annotations

import itertools
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from brave6d.capture.ur_emulator import EmulatorLink, probe

# a block of 127/8 of this session's own (parallel test sessions on one machine pick different ones)
_BLOCK = random.Random(os.getpid()).randrange(64, 250)
_ADDRESSES = (f"127.{_BLOCK}.{a}.{b}" for a, b in itertools.product(range(1, 250), range(2, 250)))


class Emulator:
    """A running emulator: its address, side-channel link and event log."""

    def __init__(self, proc: subprocess.Popen, address: str, log_path: Path) -> None:
        self.proc, self.address, self.log_path = proc, address, log_path
        self.link = EmulatorLink(address)

    def events(self) -> list[str]:
        return [text for _, _, text in self.link.events()]

    def log_text(self) -> str:
        return self.log_path.read_text()

    def stop(self) -> None:
        self.link.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def start_emulator(tmp_path: Path, *args: str, time_scale: float = 20.0) -> Emulator:
    """An emulator started with ``args`` (faults, --spec, ...), ready to serve (a fresh address each call)."""
    for _ in range(20):
        address = next(_ADDRESSES)
        log_path = tmp_path / f"emulator-{address}.log"
        with open(log_path, "wb") as log:
            proc = subprocess.Popen([sys.executable, "-m", "brave6d.cli", "ur-emulator", "--address", address,
                                     "--time-scale", str(time_scale), "--unlock-delay", "0.2", *args],
                                    stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                break  # the address was taken (or the arguments refused): the log says which
            if probe(address, timeout_s=0.5):
                return Emulator(proc, address, log_path)
            time.sleep(0.1)
        if proc.poll() is None:
            proc.kill()
            raise RuntimeError(f"the emulator at {address} did not come up: {log_path.read_text()[-2000:]}")
        if "cannot listen" not in log_path.read_text():
            raise RuntimeError(f"the emulator refused to start: {log_path.read_text()[-2000:]}")
    raise RuntimeError("no free loopback address for an emulator")


@contextmanager
def emulator(tmp_path: Path, *args: str, time_scale: float = 20.0) -> Iterator[Emulator]:
    emu = start_emulator(tmp_path, *args, time_scale=time_scale)
    try:
        yield emu
    finally:
        emu.stop()

"""The client of the emulator's side channel: what only an emulator can tell (see :mod:`.servers`).

The rehearsal pair's simulated camera asks it for the controller's clock and the flange's TRUE
pose at the image time; tests read the event log and the uploaded script and inject faults.
Replies are bounded (1 MiB a line: the control script is about 42 kB) and every call has a timeout.
"""

from __future__ import annotations

import json
import socket
import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import BraveError
from brave6d.capture.ur_emulator.servers import SIDE_PORT

MAX_REPLY = 1 << 20


class EmulatorLinkError(BraveError):
    """The emulator's side channel did not answer (or answered with an error)."""


class EmulatorLink:
    """One connection to an emulator's side channel (thread-safe; reconnects after a failure)."""

    def __init__(self, address: str, port: int = SIDE_PORT, timeout_s: float = 5.0) -> None:
        self.address, self.port, self.timeout_s = address, port, timeout_s
        self._sock: socket.socket | None = None
        self._buf = b""
        self._lock = threading.Lock()

    def _connect(self) -> socket.socket:
        try:
            sock = socket.create_connection((self.address, self.port), timeout=self.timeout_s)
        except OSError as exc:
            raise EmulatorLinkError(f"no brave6d UR emulator answers at {self.address}:{self.port} "
                                    f"({exc.strerror or exc})") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def request(self, op: str, **fields: Any) -> dict[str, Any]:
        with self._lock:
            for attempt in (1, 2):
                try:
                    if self._sock is None:
                        self._sock, self._buf = self._connect(), b""
                    self._sock.sendall(json.dumps({"op": op, **fields}).encode("ascii") + b"\n")
                    reply = json.loads(self._read_line())
                    break
                except (OSError, ValueError) as exc:
                    self._close_locked()
                    if attempt == 2:
                        raise EmulatorLinkError(f"the UR emulator at {self.address} did not answer {op!r}: "
                                                f"{exc}") from None
            if not isinstance(reply, dict):
                raise EmulatorLinkError(f"the UR emulator at {self.address} answered {op!r} with a non-object")
            if "error" in reply:
                raise EmulatorLinkError(f"the UR emulator at {self.address} refused {op!r}: {reply['error']}")
            return reply

    def _read_line(self) -> bytes:
        assert self._sock is not None
        while b"\n" not in self._buf:
            chunk = self._sock.recv(65536)
            if not chunk:
                raise ConnectionError("the emulator closed the side channel")
            self._buf += chunk
            if len(self._buf) > MAX_REPLY:
                raise ValueError(f"reply longer than {MAX_REPLY} bytes")
        line, self._buf = self._buf.split(b"\n", 1)
        return line

    def _close_locked(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
        self._sock = None

    def close(self) -> None:
        with self._lock:
            self._close_locked()

    # ------------------------------------------------------------------ what it tells
    def now(self) -> float:
        """The controller's clock (s): the clock ur-rtde's getTimestamp reports."""
        return float(self.request("now")["t"])

    def true_base_T_flange(self, t: float | None = None) -> NDArray[np.float64]:
        """Where the flange actually is at controller time ``t`` (default: now)."""
        reply = self.request("pose", t=t)
        T = np.asarray(reply["base_T_flange"], dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise EmulatorLinkError(f"the UR emulator at {self.address} sent an invalid pose")
        return T

    def status(self) -> dict[str, Any]:
        return self.request("status")

    def events(self, since: int = 0) -> list[tuple[int, float, str]]:
        return [(int(s), float(t), str(x)) for s, t, x in self.request("events", since=since)["events"]]

    def script(self) -> str | None:
        return self.request("script")["script"]

    def inject(self, fault: str) -> None:
        """A fault now (``pstop``, ``drop``, ``program-stop``), any ``--fault`` text (``pstop@move=N``
        counts the emulator's moves since it started), or ``remote-on`` / ``slow=0`` / ``refuse=0``."""
        self.request("fault", fault=fault)


def probe(address: str, port: int = SIDE_PORT, timeout_s: float = 1.0) -> bool:
    """True when a brave6d UR emulator answers at ``address`` (a real controller has no such port)."""
    link = EmulatorLink(address, port, timeout_s)
    try:
        link.now()
        return True
    except EmulatorLinkError:
        return False
    finally:
        link.close()

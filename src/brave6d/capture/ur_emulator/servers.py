"""The emulator's network side, on one loopback address: RTDE (30004), dashboard (29999), the script
port (30003) and brave6d's own side channel (30099).

* **RTDE**: the handshake (protocol version 2, controller version, output and input recipes,
  start/pause) and data packages both ways; the controller's cycle runs at 500 Hz and each started
  connection gets its output recipe at the frequency it asked for. Input recipe ids are handed out
  1, 2, ... per connection, in the order they are set up (ur-rtde hard-codes them). A data package
  for an unknown recipe or of the wrong size, an output frequency out of range, a malformed name
  list or a message before its prerequisites is refused: the emulator logs it, sends an RTDE text
  message naming it, and closes that connection.
* **dashboard**: the text commands ur-rtde's DashboardClient sends (PolyscopeVersion, get serial
  number, is in remote control, stop, play, unlock protective stop, ...), one answer line each.
* **script port**: the text written there is a URScript program; a complete ``def ... end`` starts
  it (only ur-rtde's control script is executed; anything else is logged and ignored).
* **side channel** (not a UR port): JSON lines for what only an emulator can tell, the arm's true
  pose at a controller time (the simulated camera renders from it), the event log, the uploaded
  script, faults on request. Requests are bounded to 4 KiB a line.

Everything binds to a loopback address only (:func:`check_loopback`).
"""

from __future__ import annotations

import fcntl
import ipaddress
import json
import logging
import re
import socket
import struct
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from brave6d.core.errors import BraveError
from brave6d.capture.ur_emulator import rtde_protocol as rtde
from brave6d.capture.ur_emulator.controller import RUNTIME_NAMES, Controller

log = logging.getLogger(__name__)

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
#: brave6d's side channel: the emulator's truth and controls (no UR controller has this port)
SIDE_PORT = 30099
CYCLE_HZ = 500.0
#: A client that lets this much output pile up unread is disconnected (a controller drops slow clients).
MAX_PENDING = 1 << 20
#: Data packages are skipped while the kernel still holds this much unsent output for the client.
MAX_UNSENT = 8192
#: The kernel's send buffer of an RTDE connection (small: what waits there is stale state).
SEND_BUFFER = 32768
MAX_LINE = 4096
MAX_SCRIPT = 1 << 20
_SCRIPT_END = re.compile(r"^end[ \t]*\r?$", re.MULTILINE)


def _unsent(sock: socket.socket) -> int:
    """Bytes the kernel has not sent yet on ``sock`` (0 where the platform cannot tell)."""
    try:
        return struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0"))[0]
    except OSError:
        return 0


def check_loopback(address: str) -> str:
    """``address`` as an IP literal if it is a loopback address, else a one-line BraveError."""
    text = "127.0.0.1" if address == "localhost" else address
    try:
        ip = ipaddress.ip_address(text)
    except ValueError:
        raise BraveError(f"--address {address!r}: expected a loopback IP address such as 127.0.0.2") from None
    if not ip.is_loopback:
        raise BraveError(f"--address {address}: the UR emulator binds to loopback addresses only "
                         "(127.0.0.0/8 or ::1); it is a rehearsal tool, never a network service")
    return str(ip)


@dataclass
class _RtdeConnection:
    sock: socket.socket
    peer: str
    number: int
    lock: threading.Lock = field(default_factory=threading.Lock)
    pending: bytearray = field(default_factory=bytearray)
    output: rtde.Recipe | None = None
    every: int = 1
    inputs: dict[int, rtde.Recipe] = field(default_factory=dict)
    started: bool = False
    closed: bool = False
    protocol_ok: bool = False
    dropped: int = 0

    def send(self, data: bytes, *, droppable: bool = False) -> bool:
        """Queue and send without blocking; False (and the connection closed) if the client stopped reading.

        A ``droppable`` data package is skipped while older output still waits (in this queue or in the
        kernel's): each package is the whole state, so a slow client gets fresh data late rather than
        stale data in order (what fills TCP buffers otherwise is seconds of the past)."""
        with self.lock:
            if self.closed:
                return False
            if droppable and (self.pending or _unsent(self.sock) > MAX_UNSENT):
                self.dropped += 1
                return True
            self.pending += data
            if len(self.pending) > MAX_PENDING:
                self._close_locked()
                return False
            try:
                sent = self.sock.send(self.pending, socket.MSG_DONTWAIT)
                del self.pending[:sent]
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                self._close_locked()
                return False
            return True

    def close(self) -> None:
        with self.lock:
            self._close_locked()

    def _close_locked(self) -> None:
        if not self.closed:
            self.closed = True
            try:
                self.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self.sock.close()


class EmulatorServer:
    """All ports of one emulated controller on ``address``; :meth:`start` then :meth:`stop`."""

    def __init__(self, controller: Controller, address: str = "127.0.0.1", *, side_port: int = SIDE_PORT) -> None:
        self.controller = controller
        self.address = check_loopback(address)
        self.side_port = side_port
        self._listeners: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._rtde: list[_RtdeConnection] = []
        self._rtde_lock = threading.Lock()
        self._stop = threading.Event()
        self._connections = 0
        self._refuse_until = 0.0
        self.cycles = 0
        controller.hooks.drop_rtde = self.drop_rtde

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Bind every port (a clear error when one is taken) and start serving."""
        family = socket.AF_INET6 if ":" in self.address else socket.AF_INET
        for port, handler in ((DASHBOARD_PORT, self._dashboard), (SCRIPT_PORT, self._script),
                              (RTDE_PORT, self._rtde_client), (self.side_port, self._side)):
            try:
                listener = socket.create_server((self.address, port), family=family, reuse_port=False)
            except OSError as exc:
                self.stop()
                raise BraveError(f"cannot listen on {self.address}:{port} ({exc.strerror or exc}); is another "
                                 "emulator or controller using this address? Pick another, e.g. --address 127.0.0.3"
                                 ) from None
            self._listeners.append(listener)
            self._spawn(self._accept_loop, listener, handler, port)
        self._spawn(self._cycle_loop)

    def stop(self) -> None:
        self._stop.set()
        for listener in self._listeners:
            try:
                listener.close()
            except OSError:
                pass
        with self._rtde_lock:
            conns = list(self._rtde)
        for conn in conns:
            conn.close()

    def _spawn(self, target: Callable[..., None], *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True, name=f"ur-emulator-{target.__name__}")
        thread.start()
        self._threads.append(thread)

    def _accept_loop(self, listener: socket.socket, handler: Callable[[socket.socket, str], None], port: int) -> None:
        listener.settimeout(0.2)
        while not self._stop.is_set():
            try:
                sock, peer = listener.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._spawn(handler, sock, f"{peer[0]}:{peer[1]}")

    # ------------------------------------------------------------------ the controller's cycle
    def _cycle_loop(self) -> None:
        period = 1.0 / CYCLE_HZ
        next_at = time.perf_counter()
        while not self._stop.is_set():
            snapshot = self.controller.tick()
            self.cycles += 1
            with self._rtde_lock:
                conns = [c for c in self._rtde if c.started and not c.closed and c.output is not None]
            for conn in conns:
                if self.cycles % conn.every == 0:
                    recipe = conn.output
                    assert recipe is not None
                    payload = recipe.pack({n: Controller.value_for(snapshot, n) for n in recipe.names})
                    conn.send(rtde.frame(rtde.DATA_PACKAGE, payload), droppable=True)
            next_at += period
            delay = next_at - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            else:
                next_at = time.perf_counter()  # fell behind (a loaded machine): no catch-up burst

    def drop_rtde(self, outage_s: float = 0.0) -> int:
        """Close every RTDE connection and refuse new ones for ``outage_s`` wall-clock seconds (the
        'drop' fault): what a client sees when the network fails."""
        with self._rtde_lock:
            self._refuse_until = time.monotonic() + outage_s
            conns = [c for c in self._rtde if not c.closed]
        for conn in conns:
            conn.close()
        return len(conns)

    # ------------------------------------------------------------------ RTDE
    def _rtde_client(self, sock: socket.socket, peer: str) -> None:
        c = self.controller
        outage = time.monotonic() < self._refuse_until
        if outage or c.take_refusal():
            c.event(f"rtde: connection from {peer} refused " +
                    ("(network outage after a drop)" if outage else f"(refuse fault, {c.refuse_left} left)"))
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            sock.close()
            return
        self._connections += 1
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        conn = _RtdeConnection(sock, peer, self._connections)
        with self._rtde_lock:
            self._rtde.append(conn)
        c.event(f"rtde[{conn.number}]: connected from {peer}")
        try:
            self._serve_rtde(conn)
        except rtde.ProtocolError as exc:
            c.event(f"rtde[{conn.number}]: refused: {exc}")
            conn.send(rtde.text_message(f"refused: {exc}", level=1))
        except (ConnectionError, OSError, EOFError):
            pass
        finally:
            conn.close()
            with self._rtde_lock:
                if conn in self._rtde:
                    self._rtde.remove(conn)
            c.event(f"rtde[{conn.number}]: closed")

    def _read_exact(self, conn: _RtdeConnection, n: int) -> bytes:
        data = bytearray()
        while len(data) < n:
            if conn.closed or self._stop.is_set():
                raise EOFError
            try:
                chunk = conn.sock.recv(n - len(data))
            except socket.timeout:
                continue
            if not chunk:
                raise EOFError
            data += chunk
        return bytes(data)

    def _serve_rtde(self, conn: _RtdeConnection) -> None:
        conn.sock.settimeout(0.5)
        c = self.controller
        while True:
            size, msg_type = rtde.parse_header(self._read_exact(conn, rtde.HEADER.size))
            payload = self._read_exact(conn, size)
            if msg_type == rtde.REQUEST_PROTOCOL_VERSION:
                if len(payload) != 2:
                    raise rtde.ProtocolError(f"protocol version request of {len(payload)} bytes (2 expected)")
                (version,) = struct.unpack(">H", payload)
                conn.protocol_ok = version == rtde.PROTOCOL_VERSION
                c.event(f"rtde[{conn.number}]: protocol version {version} "
                        f"{'accepted' if conn.protocol_ok else 'refused (2 only)'}")
                conn.send(rtde.frame(msg_type, bytes([int(conn.protocol_ok)])))
            elif not conn.protocol_ok:
                raise rtde.ProtocolError(f"{rtde.MESSAGE_NAMES.get(msg_type, msg_type)} before protocol version 2 "
                                         "was agreed")
            elif msg_type == rtde.GET_URCONTROL_VERSION:
                conn.send(rtde.frame(msg_type, rtde.controller_version_payload(c.config.controller_version)))
            elif msg_type == rtde.SETUP_OUTPUTS:
                self._setup_outputs(conn, payload)
            elif msg_type == rtde.SETUP_INPUTS:
                self._setup_inputs(conn, payload)
            elif msg_type == rtde.START:
                ok = conn.output is not None or bool(conn.inputs)
                conn.started = ok
                c.event(f"rtde[{conn.number}]: start {'ok' if ok else 'refused (no recipe)'}")
                conn.send(rtde.frame(msg_type, bytes([int(ok)])))
            elif msg_type == rtde.PAUSE:
                conn.started = False
                c.event(f"rtde[{conn.number}]: pause")
                conn.send(rtde.frame(msg_type, b"\x01"))
            elif msg_type == rtde.DATA_PACKAGE:
                if not payload:
                    raise rtde.ProtocolError("empty data package")
                recipe = conn.inputs.get(payload[0])
                if recipe is None:
                    raise rtde.ProtocolError(f"data package for input recipe {payload[0]}, which was never set up "
                                             f"(this connection has {sorted(conn.inputs) or 'none'})")
                if not conn.started:
                    raise rtde.ProtocolError("data package before start")
                c.write_inputs(recipe.unpack(payload[1:]))
            elif msg_type == rtde.TEXT_MESSAGE:
                c.event(f"rtde[{conn.number}]: text message from the client ({len(payload)} bytes)")
            else:
                raise rtde.ProtocolError(f"unknown message type {msg_type}")

    def _setup_outputs(self, conn: _RtdeConnection, payload: bytes) -> None:
        if conn.started:
            raise rtde.ProtocolError("output setup while synchronisation runs (pause first)")
        frequency, names = rtde.output_setup_request(payload)
        types = rtde.resolve(names, rtde.OUTPUT_TYPES)
        ok = "NOT_FOUND" not in types
        recipe_id = 1 if ok else 0
        if ok:
            conn.output = rtde.Recipe(recipe_id, tuple(names), tuple(types))
            conn.every = max(1, round(CYCLE_HZ / frequency))
        missing = [n for n, t in zip(names, types) if t == "NOT_FOUND"]
        self.controller.event(f"rtde[{conn.number}]: output recipe of {len(names)} variables at {frequency:g} Hz"
                              + (f"; NOT_FOUND: {', '.join(missing[:5])}" if missing else ""))
        conn.send(rtde.frame(rtde.SETUP_OUTPUTS, bytes([recipe_id]) + ",".join(types).encode("ascii")))

    def _setup_inputs(self, conn: _RtdeConnection, payload: bytes) -> None:
        if conn.started:
            raise rtde.ProtocolError("input setup while synchronisation runs (pause first)")
        names = rtde.split_names(payload)
        if len(set(names)) != len(names):
            raise rtde.ProtocolError("input recipe names a variable twice")
        with self._rtde_lock:
            busy = {n for other in self._rtde if other is not conn and not other.closed
                    for r in other.inputs.values() for n in r.names}
        types = rtde.resolve(names, rtde.INPUT_TYPES, busy)
        ok = not any(t in ("NOT_FOUND", "IN_USE") for t in types)
        recipe_id = len(conn.inputs) + 1 if ok else 0
        if ok:
            if recipe_id > 255:
                raise rtde.ProtocolError("more than 255 input recipes")
            conn.inputs[recipe_id] = rtde.Recipe(recipe_id, tuple(names), tuple(types))
        bad = [f"{n}={t}" for n, t in zip(names, types) if t in ("NOT_FOUND", "IN_USE")]
        self.controller.event(f"rtde[{conn.number}]: input recipe {recipe_id} of {len(names)} variables"
                              + (f"; refused: {', '.join(bad[:5])}" if bad else ""))
        conn.send(rtde.frame(rtde.SETUP_INPUTS, bytes([recipe_id]) + ",".join(types).encode("ascii")))

    # ------------------------------------------------------------------ dashboard
    def _lines(self, sock: socket.socket) -> Any:
        """Yield the lines a client sends (bounded; ends when it closes or the server stops)."""
        sock.settimeout(0.5)
        buf = b""
        while not self._stop.is_set():
            try:
                chunk = sock.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                yield line.decode("utf-8", "replace").strip()
            if len(buf) > MAX_LINE:
                return

    def _dashboard(self, sock: socket.socket, peer: str) -> None:
        try:
            sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
            for line in self._lines(sock):
                reply = self._dashboard_reply(line)
                sock.sendall(reply.encode("utf-8") + b"\n")
                if line == "quit":
                    break
        except OSError:
            pass
        finally:
            sock.close()

    def _dashboard_reply(self, line: str) -> str:
        c = self.controller
        if line != "PolyscopeVersion" and line != "get serial number":
            c.event(f"dashboard: {line!r}")
        if line == "PolyscopeVersion":
            return f"URSoftware {c.config.polyscope_version} (emulated)"
        if line == "get serial number":
            return c.config.serial_number
        if line == "get robot model":
            return c.config.model.upper().rstrip("E")
        if line == "is in remote control":
            return "true" if c.remote_control else "false"
        if line == "stop":
            return "Stopped" if c.stop_program("stopped from the dashboard") else "Failed to execute: stop"
        if line == "play":
            return c.play()
        if line == "pause":
            return "Failed to execute: pause"
        if line == "unlock protective stop":
            return c.unlock_protective_stop()
        if line == "close safety popup":
            return "closing safety popup"
        if line == "close popup":
            return "closing popup"
        if line == "robotmode":
            return "Robotmode: RUNNING"
        if line == "safetymode":
            return f"Safetymode: {c.status()['safety_mode']}"
        if line == "safetystatus":
            return f"Safetystatus: {c.status()['safety_mode']}"
        if line == "programState":
            return f"{RUNTIME_NAMES.get(c.runtime_state, 'STOPPED')} <unnamed>"
        if line == "running":
            return f"Program running: {'true' if c.runtime_state == 2 else 'false'}"
        if line in ("power on", "power off", "brake release"):
            return {"power on": "Powering on", "power off": "Powering off", "brake release": "Brake releasing"}[line]
        if line == "quit":
            return "Disconnected"
        return f"could not understand: '{line[:200]}'"

    # ------------------------------------------------------------------ script port
    def _script(self, sock: socket.socket, peer: str) -> None:
        sock.settimeout(0.5)
        buf = ""
        try:
            while not self._stop.is_set():
                try:
                    chunk = sock.recv(65536)
                except socket.timeout:
                    continue
                if not chunk:
                    return
                buf += chunk.decode("utf-8", "replace")
                if len(buf) > MAX_SCRIPT:
                    self.controller.event(f"script port: more than {MAX_SCRIPT} bytes without a complete program; "
                                          "connection closed")
                    return
                match = _SCRIPT_END.search(buf)
                while match is not None:
                    program, buf = buf[:match.end()], buf[match.end():].lstrip("\r\n")
                    self.controller.start_program(program)
                    match = _SCRIPT_END.search(buf)
        except OSError:
            pass
        finally:
            sock.close()

    # ------------------------------------------------------------------ side channel
    def _side(self, sock: socket.socket, peer: str) -> None:
        try:
            for line in self._lines(sock):
                try:
                    request = json.loads(line)
                    if not isinstance(request, dict):
                        raise ValueError("not a JSON object")
                    reply = self._side_reply(request)
                except (ValueError, TypeError, KeyError) as exc:
                    reply = {"error": f"{type(exc).__name__}: {exc}"[:300]}
                sock.sendall(json.dumps(reply).encode("ascii") + b"\n")
        except OSError:
            pass
        finally:
            sock.close()

    def _side_reply(self, request: dict[str, Any]) -> dict[str, Any]:
        c = self.controller
        op = request.get("op")
        if op == "now":
            return {"t": c.now()}
        if op == "pose":
            t = request.get("t")
            t = c.now() if t is None else float(t)
            if not np.isfinite(t):
                raise ValueError("t must be finite")
            return {"t": t, "base_T_flange": c.true_base_T_flange(t).tolist()}
        if op == "status":
            return c.status()
        if op == "events":
            since = int(request.get("since", 0))
            return {"events": [[e.seq, e.t, e.text] for e in c.events_since(since)[:5000]]}
        if op == "script":
            return {"script": c.script}
        if op == "fault":
            text = request.get("fault")
            if not isinstance(text, str):
                raise ValueError("'fault' must be a --fault text, pstop, drop, program-stop or remote-on")
            c.inject(text)
            return {"ok": True}
        raise ValueError(f"unknown op {op!r}")

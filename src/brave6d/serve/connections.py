"""Per-connection limits of the HTTP server, so that slow clients cannot lock it out.

uvicorn closes a kept-alive connection that sends nothing for 5 s and answers 503 to requests
beyond its connection limit (:data:`brave6d.serve.limits.MAX_CONNECTIONS`), but a connection that sends
half a request line and stops (slowloris), or a body a byte at a time, is held for as long as
the client likes: 257 of them lock every other client out, before any token check. So the server
runs uvicorn's h11 protocol with these limits (:class:`brave6d.serve.limits.ServerLimits`):

* **header timeout**: the request line and headers must arrive within ``header_timeout_s`` of the
  connection opening, or of the previous response on a kept-alive connection; else the
  connection is closed (with ``408`` when part of a request had come);
* **body timeout**: a declared body must arrive within ``body_timeout_s`` of the headers; else
  ``408`` and the connection is closed. Once the request is complete the action's own
  ``request_timeout_s`` applies (an action is never cut by these);
* **per-client cap**: one client address (an IPv6 client: its /64) holds at most
  ``max_connections_per_client`` open connections, HTTP and WebSocket together; a connection
  beyond it gets ``429`` and is closed at once.

* **replies the client does not read**: a connection's next request (pipelined or not) is read
  only once the previous reply has left the server's buffer (down to the transport's low-water
  mark), so a connection holds at most one reply; a reply waiting to be sent must make way (some of
  it taken by the client) within ``write_timeout_s``, and one connection may have at most
  ``max_unsent_bytes`` of it buffered; else the connection is aborted and its buffer dropped at
  once (closing it would wait for the buffer to drain, which a client that does not read never
  lets happen). Large replies are streamed (``observation.npz``), so a stalled one holds a chunk.

A WebSocket (``/episodes/{id}/ws``) counts toward its client's cap from its first byte until it
closes; after the upgrade the HTTP timeouts no longer apply (websockets' pings keep it honest: a
client that does not read does not answer them and is closed after uvicorn's ping interval and timeout).
Error replies are the API's JSON error objects. :func:`guarded_protocols` makes the protocol
classes of one server; :func:`brave6d.serve.runner.uvicorn_config` gives them to uvicorn, for the CLI
server and :class:`brave6d.serve.runner.ServerThread` alike.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import ipaddress
import json
import logging
import socket
import struct
from collections import Counter
from dataclasses import dataclass
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from brave6d.serve.limits import ServerLimits

log = logging.getLogger(__name__)

#: Seconds a refused connection is given to read its 429 before it is closed.
REFUSED_GRACE_S = 1.0


#: Seconds after the last aborted connection before the freed memory is handed back to the system.
TRIM_DELAY_S = 1.0


def return_free_memory() -> None:
    """Hand the C heap's free pages back to the system (glibc's ``malloc_trim``; elsewhere nothing):
    the replies of aborted connections are freed in many threads' arenas, which glibc keeps."""
    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def client_key(host: str | None) -> str:
    """The address a connection is counted under: the peer's IPv4 address, the /64 of its IPv6
    address (one host usually owns a whole /64), ``local`` for a Unix socket."""
    if not host:
        return "local"
    try:
        ip = ipaddress.ip_address(host.split("%", 1)[0])
    except ValueError:
        return host
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)


def _peer(transport: asyncio.BaseTransport) -> str:
    peer = transport.get_extra_info("peername")
    return client_key(peer[0] if isinstance(peer, tuple) and peer else None)


class ClientConnections:
    """Open connections per client address, within a cap (used on the server's event loop only)."""

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self._open: Counter[str] = Counter()
        self._refusing: set[str] = set()  # clients refused since they last dropped below the cap

    def count(self, key: str) -> int:
        """Open connections of the client ``key`` (see :func:`client_key`)."""
        return self._open.get(key, 0)

    def admit(self, key: str) -> Seat | None:
        """A seat for a new connection of ``key``, or None when it holds ``cap`` already."""
        if self._open[key] >= self.cap:
            if key not in self._refusing:  # one warning per episode of refusals, not one per connection
                self._refusing.add(key)
                log.warning("refusing connections from %s: it holds %d already (the per-client cap)", key, self.cap)
            return None
        self._open[key] += 1
        return Seat(self, key)

    def _release(self, key: str) -> None:
        self._open[key] -= 1
        if self._open[key] <= 0:
            del self._open[key]
        if self._open[key] < self.cap:
            self._refusing.discard(key)


class Seat:
    """One admitted connection; :meth:`release` (idempotent) frees its place in the count."""

    def __init__(self, owner: ClientConnections, key: str) -> None:
        self.owner, self.key, self.released = owner, key, False

    def release(self) -> None:
        if not self.released:
            self.released = True
            self.owner._release(self.key)


def error_reply(status: int, message: str) -> bytes:
    """A complete HTTP/1.1 reply carrying the API's error object, closing the connection."""
    body = json.dumps({"error": message, "field": None, "status": status}).encode()
    reason = {408: "Request Timeout", 429: "Too Many Requests"}[status]
    head = (f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/json\r\ncontent-length: {len(body)}\r\n"
            "connection: close\r\n\r\n")
    return head.encode("ascii") + body


@dataclass(frozen=True)
class GuardedProtocols:
    """The protocol classes of one server and the connection count they share."""

    http: type[asyncio.Protocol]
    ws: type[asyncio.Protocol] | None
    clients: ClientConnections


def guarded_protocols(limits: ServerLimits) -> GuardedProtocols:
    """uvicorn protocol classes (h11 HTTP, and the WebSocket class uvicorn would pick) enforcing
    ``limits``' header and body timeouts and per-client cap (see the module docstring)."""
    from uvicorn.protocols.websockets.auto import AutoWebSocketsProtocol

    clients = ClientConnections(limits.max_connections_per_client)
    trim: list[asyncio.TimerHandle] = []  # the pending return_free_memory, once a connection was aborted
    ws_class: Any = None
    if AutoWebSocketsProtocol is not None:  # else uvicorn has no WebSocket library: no upgrades

        class GuardedWebSocket(AutoWebSocketsProtocol):  # type: ignore[misc, valid-type]
            """uvicorn's WebSocket protocol, releasing the seat of the HTTP connection it upgraded."""

            seat: Seat | None = None

            def connection_lost(self, exc: Exception | None) -> None:
                try:
                    super().connection_lost(exc)
                finally:
                    if self.seat is not None:
                        self.seat.release()

        ws_class = GuardedWebSocket

    class GuardedHttp(H11Protocol):
        """uvicorn's h11 protocol with the header and body timeouts and the per-client cap."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.seat: Seat | None = None
            self.refused = False
            self.timer: asyncio.TimerHandle | None = None
            self.waiting_for: str | None = None  # "headers", "body" or None (the app has the request)
            self.request_started = False  # bytes of the awaited request have come
            self.write_timer: asyncio.TimerHandle | None = None  # while a reply waits to be sent
            self.reply_pending = False  # a reply is complete but not yet sent: the next request waits

        # ---------------------------------------------------------------- connection
        def connection_made(self, transport: asyncio.BaseTransport) -> None:  # type: ignore[override]
            key = _peer(transport)
            self.seat = clients.admit(key)
            if self.seat is None:
                self.refused = True
                self._refuse(transport, key)
                return
            super().connection_made(transport)  # type: ignore[arg-type]
            self._await("headers")

        def _refuse(self, transport: asyncio.BaseTransport, key: str) -> None:
            assert isinstance(transport, asyncio.Transport)
            transport.write(error_reply(429, f"too many connections from {key}: at most {clients.cap} at once "
                                             "(close some and retry)"))
            if transport.can_write_eof():
                transport.write_eof()  # the client reads the reply, then end of file
            self.timer = self.loop.call_later(REFUSED_GRACE_S, transport.close)

        def data_received(self, data: bytes) -> None:
            if self.refused:
                return  # read and dropped, so that closing sends no reset before the 429 is read
            if data and self.waiting_for == "headers":
                self.request_started = True
            super().data_received(data)
            self._track()

        def eof_received(self) -> bool | None:
            if self.refused:
                return None  # close
            return super().eof_received()  # type: ignore[func-returns-value]

        def connection_lost(self, exc: Exception | None) -> None:
            self._stop_timer()
            if self.write_timer is not None:
                self.write_timer.cancel()
            if self.flow is not None and self.flow.write_paused:  # a reply was left unsent: return its memory
                if trim:
                    trim.pop().cancel()
                trim.append(self.loop.call_later(TRIM_DELAY_S, return_free_memory))
            if self.refused:
                return
            try:
                super().connection_lost(exc)
            finally:
                if self.seat is not None:
                    self.seat.release()

        def handle_websocket_upgrade(self, event: h11.Request) -> None:
            super().handle_websocket_upgrade(event)
            self._stop_timer()
            self.waiting_for = None
            ws = self.transport.get_protocol()
            if ws_class is not None and isinstance(ws, ws_class):
                ws.seat, self.seat = self.seat, None  # the WebSocket holds this connection's seat now

        def on_response_complete(self) -> None:
            if self.flow.write_paused and not self.transport.is_closing():
                self.reply_pending = True  # the next request is read once this reply has left (resume_writing)
                return
            super().on_response_complete()
            if not self.transport.is_closing() and self.transport.get_protocol() is self:
                self._await("headers")  # the next request on this kept-alive connection
                self._track()

        # ---------------------------------------------------------------- replies the client does not read
        def pause_writing(self) -> None:
            """The transport's buffer passed its high-water mark: the reply must now make way."""
            super().pause_writing()
            self._check_unsent()
            self._watch_writes(self.transport.get_write_buffer_size())

        def resume_writing(self) -> None:
            super().resume_writing()
            if self.write_timer is not None:
                self.write_timer.cancel()
                self.write_timer = None
            if self.reply_pending:
                self.reply_pending = False
                self.on_response_complete()

        def _watch_writes(self, unsent: int) -> None:
            self.write_timer = self.loop.call_later(limits.write_timeout_s, self._write_expired, unsent)

        def _write_expired(self, unsent_before: int) -> None:
            self.write_timer = None
            if self.transport.is_closing() or not self.flow.write_paused:
                return
            unsent = self.transport.get_write_buffer_size()
            if unsent >= unsent_before:
                self._abort(f"took none of its reply within {limits.write_timeout_s:g} s ({unsent} bytes unsent)")
            else:
                self._watch_writes(unsent)

        def _check_unsent(self) -> None:
            unsent = self.transport.get_write_buffer_size()
            if unsent > limits.max_unsent_bytes:
                self._abort(f"has {unsent} reply bytes unsent (at most {limits.max_unsent_bytes})")

        def _abort(self, why: str) -> None:
            log.info("closing a connection from %s: it %s", self.seat.key if self.seat else "?", why)
            sock = self.transport.get_extra_info("socket")
            if sock is not None:  # a reset: the kernel drops what it holds for the client too
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            self.loop.call_soon(self.transport.abort)  # drops the buffer; close() would wait for it to drain

        # ---------------------------------------------------------------- timeouts
        def _track(self) -> None:
            """Move the timer along with h11's view of the request being received."""
            if self.transport.is_closing() or self.transport.get_protocol() is not self:
                self._stop_timer()
                return
            state = self.conn.their_state
            if state is h11.SEND_BODY:
                if self.waiting_for == "headers":
                    self._await("body")
            elif state is not h11.IDLE and self.waiting_for is not None:
                self._stop_timer()  # the request is complete: the app has it
                self.waiting_for = None

        def _await(self, what: str) -> None:
            self._stop_timer()
            self.waiting_for = what
            self.request_started = what == "body"
            seconds = limits.header_timeout_s if what == "headers" else limits.body_timeout_s
            self.timer = self.loop.call_later(seconds, self._expired, what, seconds)

        def _stop_timer(self) -> None:
            if self.timer is not None:
                self.timer.cancel()
                self.timer = None

        def _expired(self, what: str, seconds: float) -> None:
            self.timer = None
            if self.transport.is_closing() or self.waiting_for != what:
                return
            answered = what == "body" and self.cycle is not None and self.cycle.response_started
            if self.request_started and not answered:  # (while awaiting headers, any cycle is the last one's)
                part = "request line and headers" if what == "headers" else "request body"
                self.transport.write(error_reply(408, f"the {part} did not arrive within {seconds:g} s"))
            self.transport.close()

    return GuardedProtocols(GuardedHttp, ws_class, clients)

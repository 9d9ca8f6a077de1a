"""Run the server with uvicorn: in the foreground (the CLI) or in a background thread (demo, tests,
benchmarks) on a loopback port chosen by the OS. Both run the same configuration
(:func:`uvicorn_config`): uvicorn's h11 protocol with the header and body timeouts and the
per-client connection cap of :mod:`brave6d.serve.connections`."""

from __future__ import annotations

import ipaddress
import logging
import socket
import threading
import time
from typing import Any, Self

from brave6d.serve.connections import ClientConnections
from brave6d.serve.limits import MAX_CONNECTIONS, ServerLimits

log = logging.getLogger(__name__)

#: uvicorn answers 503 beyond this many concurrent connections + tasks.
LIMIT_CONCURRENCY = MAX_CONNECTIONS


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


#: Connections the socket queues before they are accepted (uvicorn's own default backlog).
LISTEN_BACKLOG = 2048


def listening_socket(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port`` (port 0: any free port) and listening, for uvicorn to serve.

    Made with proto ``IPPROTO_TCP``, so that asyncio sets ``TCP_NODELAY`` on the connections it
    accepts (it checks the proto): with proto 0, every reply uvicorn writes in two parts (head,
    then body) waited for the client's delayed ACK, about 40 ms a request on loopback.
    """
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
        sock.listen(LISTEN_BACKLOG)  # listening before the address is announced: a client that connects
    except OSError:                  # while uvicorn still starts waits in the backlog instead of being refused
        sock.close()
        raise
    return sock


def uvicorn_config(app: Any, host: str = "127.0.0.1", port: int = 8765, log_level: str = "warning",
                   limits: ServerLimits | None = None) -> tuple[Any, ClientConnections]:
    """The uvicorn configuration serving ``app`` within ``limits`` (default: the app's own,
    ``app.state.limits``, else :class:`ServerLimits`' defaults), and the per-client connection
    count its protocols share. WebSocket messages are limited to ``max_body_bytes`` as bodies are."""
    import uvicorn

    from brave6d.serve.connections import guarded_protocols

    if limits is None:
        limits = getattr(getattr(app, "state", None), "limits", None) or ServerLimits()
    protocols = guarded_protocols(limits)
    config = uvicorn.Config(app, host=host, port=port, log_level=log_level, ws_max_size=limits.max_body_bytes,
                            http=protocols.http, ws=protocols.ws if protocols.ws is not None else "none",
                            timeout_keep_alive=5, limit_concurrency=LIMIT_CONCURRENCY, access_log=False,
                            lifespan="on", timeout_graceful_shutdown=SHUTDOWN_GRACE_S)
    return config, protocols.clients


#: Seconds uvicorn waits for requests still running at shutdown (they are withdrawn at once, see
#: :func:`draining_server`; one render in progress finishes) before it cancels them.
SHUTDOWN_GRACE_S = 30.0


def draining_server(config: Any) -> Any:
    """A ``uvicorn.Server`` for ``config`` that, when its shutdown starts (Ctrl-C, SIGTERM,
    ``should_exit``), first calls the app's ``state.drain`` (:meth:`brave6d.serve.inflight.InFlight.drain`):
    every action in flight is withdrawn and answers 503, so the shutdown waits for at most the render
    in progress instead of every queued one, and logs no traceback."""
    import uvicorn

    class DrainingServer(uvicorn.Server):
        async def shutdown(self, sockets: Any = None) -> None:
            drain = getattr(getattr(self.config.app, "state", None), "drain", None)
            if callable(drain):
                drain()
            await super().shutdown(sockets=sockets)

    return DrainingServer(config)


class ServerThread:
    """A uvicorn server on ``host`` (loopback by default) in a daemon thread.

    ``port=0`` lets the OS pick a free port (the socket is bound before the thread starts, so
    there is no race); ``url`` is the base URL; ``clients`` counts the open connections per client
    address. ``limits`` default to the app's (see :func:`uvicorn_config`). Use as a context manager.
    """

    def __init__(self, app: Any, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning",
                 limits: ServerLimits | None = None) -> None:
        self.sock = listening_socket(host, port)
        self.host, self.port = host, self.sock.getsockname()[1]
        config, self.clients = uvicorn_config(app, host, self.port, log_level, limits)
        self.server = draining_server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]},
                                       name="brave6d-uvicorn", daemon=True)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    def start(self, timeout: float = 60.0) -> ServerThread:
        self.thread.start()
        t0 = time.monotonic()
        while not self.server.started:
            if not self.thread.is_alive():
                raise RuntimeError("the server thread ended before it started (see the log)")
            if time.monotonic() - t0 > timeout:
                raise RuntimeError(f"the server did not start within {timeout:.0f} s")
            time.sleep(0.02)
        return self

    def stop(self, timeout: float = 10.0) -> None:
        self.server.should_exit = True
        self.thread.join(timeout)
        try:
            self.sock.close()
        except OSError:
            pass

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

"""Run the server with uvicorn: in the foreground (the CLI) or in a background thread (demo, tests,
benchmarks) on a loopback port chosen by the OS."""

from __future__ import annotations

import ipaddress
import logging
import socket
import threading
import time
from typing import Any, Self

log = logging.getLogger(__name__)

#: uvicorn answers 503 beyond this many concurrent connections + tasks.
LIMIT_CONCURRENCY = 256


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def uvicorn_config(app: Any, host: str = "127.0.0.1", port: int = 8765, log_level: str = "warning",
                   ws_max_size: int = 64 * 1024) -> Any:
    import uvicorn

    return uvicorn.Config(app, host=host, port=port, log_level=log_level, ws_max_size=ws_max_size,
                          timeout_keep_alive=5, limit_concurrency=LIMIT_CONCURRENCY, access_log=False,
                          lifespan="on")


class ServerThread:
    """A uvicorn server on ``host`` (loopback by default) in a daemon thread.

    ``port=0`` lets the OS pick a free port (the socket is bound before the thread starts, so
    there is no race); ``url`` is the base URL. Use as a context manager.
    """

    def __init__(self, app: Any, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning",
                 ws_max_size: int = 64 * 1024) -> None:
        import uvicorn

        self.sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((host, port))
        self.host, self.port = host, self.sock.getsockname()[1]
        self.server = uvicorn.Server(uvicorn_config(app, host, self.port, log_level, ws_max_size))
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

"""The server's actions in flight: each runs in the worker pool and is withdrawn, before it is
committed, when its client has gone, when it takes longer than the request timeout, or when the
server shuts down.

Why: renders are queued in the pool and drawn one at a time on the device. A client that sends a
maximum-size free view and drops the connection used to leave its render queued; 300 of them kept
every other client's renders waiting (504) for over a minute and a half, and Ctrl-C then waited for
them, logging a traceback for each. Here every action is a :class:`~brave6d.serve.episodes.Ticket`:

- the handler waits for the action, for its client to disconnect (the ASGI ``http.disconnect``
  message), for the server to drain, and for the request timeout, whichever comes first; on any but
  the first the ticket is cancelled (nothing is committed), a queued action is taken off the queue
  and the reply is 499 (client gone: nobody reads it), 503 (shutting down) or 504 (timeout);
- an action that was already running when it was withdrawn stops at its next render: the renderer
  asks :data:`brave6d.serve.renderer.STILL_WANTED` once it holds the device, and a withdrawn render
  is skipped (:class:`~brave6d.serve.renderer.RenderWithdrawn`) instead of drawn;
- :meth:`InFlight.drain` (called by :func:`brave6d.serve.runner.draining_server` when uvicorn starts
  its shutdown) withdraws everything in flight and refuses new actions with 503, so the shutdown
  waits for at most one render and logs nothing but its own lines.

A withdrawn action's late result or error is collected quietly (never "exception was never retrieved").
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Callable
from typing import Any

from brave6d.serve.episodes import Cancelled, EpisodeError, Ticket
from brave6d.serve.renderer import STILL_WANTED, RenderWithdrawn

#: What an ASGI ``receive`` callable is.
Receive = Callable[[], Any]


class ActionTimeout(EpisodeError):
    status = 504


class ClientGone(EpisodeError):
    """The client closed its connection while its action waited: nobody reads this reply."""

    status = 499


class ShuttingDown(EpisodeError):
    status = 503


def _collect(fut: asyncio.Future[Any]) -> None:
    """Retrieve a withdrawn action's late outcome, so that asyncio logs nothing about it."""
    if not fut.cancelled():
        fut.exception()


async def _disconnected(receive: Receive) -> None:
    """Return once the ASGI server says the client has gone (``http.disconnect``)."""
    while True:
        message = await receive()
        if message.get("type") == "http.disconnect":
            return


class InFlight:
    """The actions running or queued in ``executor`` for one app (see the module docstring)."""

    def __init__(self, executor: concurrent.futures.Executor, timeout_s: float) -> None:
        self.executor = executor
        self.timeout_s = timeout_s
        self.draining = False
        self._drains: set[asyncio.Future[None]] = set()  # one per action waiting: set when the server drains

    def running(self) -> int:
        """Actions not yet finished or withdrawn."""
        return len(self._drains)

    def drain(self) -> None:
        """Withdraw every action in flight (their requests answer 503) and refuse new ones (any thread)."""
        self.draining = True
        for waiter in list(self._drains):
            waiter.get_loop().call_soon_threadsafe(lambda w=waiter: w.done() or w.set_result(None))

    async def run(self, fn: Callable[..., Any], *args: Any, receive: Receive | None = None, **kwargs: Any) -> Any:
        """``fn(*args, ticket=..., **kwargs)`` in the pool, withdrawn as the module docstring says;
        ``receive``: the request's ASGI receive (None: no client to watch, a WebSocket message)."""
        if self.draining:
            raise ShuttingDown("the server is shutting down; retry on another server or later")
        ticket = Ticket()

        def job() -> Any:
            if ticket.cancelled:  # withdrawn while it was queued
                raise Cancelled()
            token = STILL_WANTED.set(lambda: not ticket.cancelled)
            try:
                return fn(*args, ticket=ticket, **kwargs)
            finally:
                STILL_WANTED.reset(token)

        work = self.executor.submit(job)
        fut = asyncio.wrap_future(work)
        drained: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        watchers: list[asyncio.Future[Any]] = [drained]
        if receive is not None:
            watchers.append(asyncio.ensure_future(_disconnected(receive)))
        self._drains.add(drained)
        try:
            done, _ = await asyncio.wait({fut, *watchers}, timeout=self.timeout_s,
                                         return_when=asyncio.FIRST_COMPLETED)
            if fut not in done and ticket.cancel():
                work.cancel()  # still queued: it never runs; running: its next render is skipped
                fut.add_done_callback(_collect)
                if watchers[0] in done:
                    raise ShuttingDown("the server is shutting down; the request was withdrawn (nothing changed)")
                if len(watchers) > 1 and watchers[1] in done:
                    raise ClientGone("the client closed the connection; the request was withdrawn (nothing changed)")
                raise ActionTimeout(f"the request took longer than {self.timeout_s:g} s and was withdrawn (nothing "
                                    "changed); the server is overloaded or the image is too large")
            try:
                return await fut
            except (Cancelled, RenderWithdrawn):  # pragma: no cover - only when a withdrawal won the race
                raise ActionTimeout(f"the request took longer than {self.timeout_s:g} s and was withdrawn") from None
        finally:
            self._drains.discard(drained)
            for w in watchers:
                w.cancel()

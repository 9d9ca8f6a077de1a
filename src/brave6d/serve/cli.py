"""``brave6d serve BUNDLE_OR_RELEASE``: serve a scene bundle, or every scene of a dataset release,
over HTTP + WebSocket (loopback by default).

A release's scenes are listed at ``GET /scenes`` and loaded when an episode first needs one
(``POST /episodes`` names the scene), within ``--max-loaded-scenes`` and ``--max-memory-mb``
(default: half the machine's memory); see :mod:`brave6d.serve.catalog`. Whether the path is a
bundle or a release, and the release's scene sources, are decided above the stages
(:mod:`brave6d.commands.serve` hands :func:`run` the function that does it), so that serve never
imports the dataset stage that owns the release format.

Security defaults: the server binds to 127.0.0.1; a non-loopback ``--host`` is refused unless
``--allow-remote`` is given, and then a token is required on every request (``--token``, or
``$BRAVE6D_TOKEN``, or a random one printed at start). Requests must name an allowed host in
their ``Host`` header (127.0.0.1, localhost, [::1], the bound address, ``--allow-host`` names):
a web page that rebinds its own DNS name to this machine gets 400. Slow clients cannot hold the
server's connections (:mod:`brave6d.serve.connections`): a request's headers must come within
``--header-timeout`` (10 s), its body within ``--body-timeout`` (30 s), and one client address
holds at most ``--max-client-connections`` (64) of the server's 256 connections; a client that does
not read its replies is cut after ``--write-timeout`` (20 s) or ``--max-unsent-bytes``. Every number is
bounded when the flags are parsed (:data:`brave6d.serve.limits.BOUNDS`): a value outside (NaN, inf,
negative, too large) ends the command with a line naming the flag, exit status 2.

Modes (:mod:`brave6d.serve.modes`): the server runs ``scored`` (no object pose, box, visible fraction
or placement reaches a client; the logs record the mode) unless ``--training`` asks for the paper's
interface with the ground truth. Every episode log is signed with the key in ``--log-key`` (default
``$BRAVE6D_LOG_KEY``, else ``~/.config/brave6d/episode-log.key``, made on first use), which
``brave6d evaluate`` checks (:mod:`brave6d.serve.log_digest`).
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import secrets
import signal
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from brave6d.core.errors import BraveError
from brave6d.core.runtime import quiet_openmp
from brave6d.serve.limits import MAX_CONNECTIONS, ServerLimits, limit_arg

if TYPE_CHECKING:
    from brave6d.serve.catalog import SourcesOf

log = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bundle", type=Path, metavar="BUNDLE_OR_RELEASE",
                        help="a bundle folder written by 'brave6d export', or a release (the folder 'brave6d release "
                             "build' wrote, or the unzipped dataset): every scene of it is served (checksums are "
                             "verified)")
    parser.add_argument("--cache-dir", type=Path, default=None,
                        help="where a release's bundle zips are unpacked on first use (default: $BRAVE6D_CACHE, "
                             "else ~/.cache/brave6d)")
    parser.add_argument("--max-loaded-scenes", type=limit_arg("max_loaded_scenes"), default=None,
                        help="scenes kept in memory at most (default: as many as --max-memory-mb allows)")
    parser.add_argument("--max-memory-mb", type=limit_arg("max_memory_mb"), default=None,
                        help="estimated memory the loaded scenes may take (default: half the machine's memory); "
                             "scenes no open episode uses are unloaded, least recently used first")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to bind (default 127.0.0.1: this machine only; any other address needs "
                             "--allow-remote)")
    parser.add_argument("--allow-remote", action="store_true",
                        help="allow a --host that is reachable from the network (a token is then required)")
    parser.add_argument("--token", default=None,
                        help="require this token on every request ('Authorization: Bearer TOKEN' or '?token=TOKEN'; "
                             "default: $BRAVE6D_TOKEN, which other users cannot see in the process list; with "
                             "--allow-remote and no token, a random one is made and printed)")
    parser.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                        help="also accept requests whose Host header names NAME (repeatable; any port; "
                             "'*.example.org': its subdomains; '*': any). Always accepted: 127.0.0.1, localhost, "
                             "[::1] and a specific --host")
    parser.add_argument("--port", type=limit_arg("port"), default=8765,
                        help="TCP port (default 8765; 0: any free port)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                        help="rasterizer device (auto: cuda when torch sees a GPU)")
    parser.add_argument("--log-dir", type=Path, default=None,
                        help="where episode logs (JSONL) go (default: 'episodes' beside the bundle)")
    add_mode_flags(parser)
    parser.add_argument("--visibility-stride", type=int, choices=range(1, 65), metavar="S", default=1,
                        help="visible fractions (training rewards, logs) from one pixel per SxS block (default 1: "
                             "every pixel, BOP's definition; the vector env's default is 4, give the same to "
                             "compare); submits record the exact fractions either way")
    d = ServerLimits()
    parser.add_argument("--max-episodes", type=limit_arg("max_episodes"), default=d.max_episodes,
                        help=f"open episodes at most (default {d.max_episodes})")
    parser.add_argument("--request-timeout", type=limit_arg("request_timeout_s"), default=d.request_timeout_s,
                        help=f"seconds one action may take before it is withdrawn with 504 (default "
                             f"{d.request_timeout_s:g})")
    parser.add_argument("--max-body-bytes", type=limit_arg("max_body_bytes"), default=d.max_body_bytes,
                        help=f"largest request body / WebSocket message (default {d.max_body_bytes})")
    parser.add_argument("--idle-timeout", type=limit_arg("idle_timeout_s"), default=d.idle_timeout_s,
                        help=f"close episodes idle for this many seconds (default {d.idle_timeout_s:g})")
    parser.add_argument("--header-timeout", type=limit_arg("header_timeout_s"), default=d.header_timeout_s,
                        help="seconds a client has to send a request's line and headers, from connecting or from "
                             f"the previous response; else 408 and the connection is closed (default "
                             f"{d.header_timeout_s:g})")
    parser.add_argument("--body-timeout", type=limit_arg("body_timeout_s"), default=d.body_timeout_s,
                        help="seconds a client has to send a request's body once its headers came; else 408 and "
                             f"the connection is closed (default {d.body_timeout_s:g})")
    parser.add_argument("--max-client-connections", type=limit_arg("max_connections_per_client"),
                        default=d.max_connections_per_client,
                        help="open connections (HTTP and WebSocket) one client address may hold; more get 429 "
                             f"(default {d.max_connections_per_client}, of {MAX_CONNECTIONS} in all)")
    parser.add_argument("--write-timeout", type=limit_arg("write_timeout_s"), default=d.write_timeout_s,
                        help="seconds a client that has a reply waiting may go without taking any of it; else the "
                             f"connection is closed (default {d.write_timeout_s:g})")
    parser.add_argument("--max-unsent-bytes", type=limit_arg("max_unsent_bytes"), default=d.max_unsent_bytes,
                        help="reply bytes one connection may have waiting in the server; more and it is closed "
                             f"(default {d.max_unsent_bytes}; a connection's next request is read once its "
                             "reply has gone)")


def add_mode_flags(parser: argparse.ArgumentParser) -> None:
    """``--training`` and ``--log-key``: the flags every serving command (HTTP, ROS 1, ROS 2) shares."""
    parser.add_argument("--training", action="store_true",
                        help="training mode: serve every object's ground truth (poses, boxes, visible fractions, "
                             "placements) as the paper's interface does; default: scored mode, where none of it "
                             "reaches an agent and the episodes can be ranked (docs/SECURITY.md)")
    parser.add_argument("--log-key", type=Path, default=None, metavar="FILE",
                        help="the secret key the episode logs are signed with (default: $BRAVE6D_LOG_KEY, else "
                             "~/.config/brave6d/episode-log.key, made on first use); 'brave6d evaluate' needs "
                             "the same key to rank scored episodes")


def mode_of(args: argparse.Namespace) -> str:
    """The mode the serving flags ask for."""
    from brave6d.serve.modes import SCORED, TRAINING

    return TRAINING if getattr(args, "training", False) else SCORED


@dataclass(frozen=True)
class Access:
    """Who may use the server: the ``Host`` names allowed besides loopback, and the token (None: none)."""

    allowed_hosts: tuple[str, ...]
    token: str | None
    token_generated: bool = False


def _host_name(host: str) -> str:
    """``host`` as it appears in a ``Host`` header (an IPv6 address in brackets)."""
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


def access_for(host: str, allow_remote: bool, token: str | None, allow_hosts: list[str],
               environ: dict[str, str] | None = None) -> Access:
    """The access settings of a server bound to ``host``; :class:`BraveError` (one line) when a
    non-loopback ``host`` lacks ``allow_remote``. The token comes from ``token``, else
    ``$BRAVE6D_TOKEN``, else (remote only) is made at random."""
    from brave6d.serve.app import check_token
    from brave6d.serve.client import TOKEN_ENV
    from brave6d.serve.runner import is_loopback

    remote = not is_loopback(host)
    if remote and not allow_remote:
        raise BraveError(f"--host {host} would expose the server to the network: add --allow-remote to do so "
                         "(a token is then required), or bind 127.0.0.1")
    env = os.environ if environ is None else environ
    token = token if token is not None else (env.get(TOKEN_ENV) or None)
    generated = token is None and remote
    if generated:
        token = secrets.token_urlsafe(24)
    hosts = list(allow_hosts)
    try:
        wildcard = ipaddress.ip_address(host).is_unspecified
    except ValueError:
        wildcard = False
    if remote and not wildcard:
        hosts.append(_host_name(host))
    return Access(tuple(hosts), check_token(token) if token is not None else None, generated)


def run(args: argparse.Namespace, sources_of: SourcesOf) -> int:
    """Serve the scenes ``sources_of(args.bundle, args.cache_dir)`` gives (see the module docstring)."""
    quiet_openmp()
    from brave6d.serve.app import LOOPBACK_HOSTS, create_app
    from brave6d.serve.catalog import SceneUnavailable, open_scenes
    from brave6d.serve.runner import draining_server, is_loopback, listening_socket, uvicorn_config

    # every number was bounded when the flags were parsed (limit_arg); ServerLimits checks again
    limits = ServerLimits(max_body_bytes=args.max_body_bytes, request_timeout_s=args.request_timeout,
                          max_episodes=args.max_episodes, idle_timeout_s=args.idle_timeout,
                          header_timeout_s=args.header_timeout, body_timeout_s=args.body_timeout,
                          max_connections_per_client=args.max_client_connections,
                          write_timeout_s=args.write_timeout, max_unsent_bytes=args.max_unsent_bytes)
    access = access_for(args.host, args.allow_remote, args.token, args.allow_host)
    if not is_loopback(args.host) and not args.allow_host:
        log.warning("binding to %s: only requests whose Host header names %s are accepted; add --allow-host NAME "
                    "for each name or address the clients use", args.host,
                    ", ".join([*LOOPBACK_HOSTS, *access.allowed_hosts]))
    budget = args.max_memory_mb if args.max_memory_mb is not None else default_memory_budget_mb()
    scenes = open_scenes(sources_of(args.bundle, args.cache_dir), device=args.device,
                         max_loaded=args.max_loaded_scenes, max_memory_mb=budget)
    if len(scenes.sources) == 1:  # one scene: load it now, so the first episode is as fast as the rest
        try:
            scenes.release(scenes.acquire(None))
        except SceneUnavailable as exc:  # at start, the bundle given is the user's: say what is wrong with it
            raise exc.cause if isinstance(exc.cause, BraveError) else exc from None
    log_dir = args.log_dir if args.log_dir is not None else Path(args.bundle).resolve().parent / "episodes"
    from brave6d.serve.log_digest import server_log_key

    mode = mode_of(args)
    key = server_log_key(args.log_key)
    app = create_app(scenes, device=args.device, log_dir=log_dir, limits=limits,
                     allowed_hosts=access.allowed_hosts, token=access.token, mode=mode, log_key=key,
                     visibility_stride=args.visibility_stride)
    try:
        sock = listening_socket(args.host, args.port)
    except OSError as exc:
        raise BraveError(f"cannot listen on {args.host}:{args.port}: {exc.strerror}") from None
    port = sock.getsockname()[1]
    host = _host_name(args.host)
    viewer = "/viewer/" + ("?token=<token>" if access.token is not None else "")
    loaded = scenes.loaded_scenes()
    what = (f"{loaded[0].bundle.name} ({loaded[0].renderer.num_gaussians} Gaussians, {loaded[0].device})" if loaded
            else f"{len(scenes.sources)} scenes ({', '.join(scenes.names())}; loaded on first use, at most "
                 f"{budget:.0f} MB{f' / {args.max_loaded_scenes} scenes' if args.max_loaded_scenes else ''}: "
                 f"GET /scenes)")
    print(f"brave6d serve: {what} on http://{host}:{port}  viewer: {viewer}  API: /docs  "
          f"episode logs: {log_dir}", flush=True)
    served = "every object's ground truth served: not ranked" if mode != "scored" else "no ground truth served"
    print(f"mode: {mode} ({served}); episode logs signed with key {key.key_id} ({key.source})", flush=True)
    if access.token_generated:
        print(f"token (send as 'Authorization: Bearer <token>' or '?token=<token>'): {access.token}", flush=True)
    level = "info" if getattr(args, "verbose", 0) else "warning"
    server = draining_server(uvicorn_config(app, args.host, port, level, limits)[0])  # Ctrl-C withdraws what runs
    # uvicorn shuts down gracefully on Ctrl-C, then raises the signal again with the handler it
    # found. With Python's default handler that goes through asyncio's Runner, which turns it into
    # a task cancellation and, once in a CI run, into a normal return (exit status 0); a handler
    # that raises KeyboardInterrupt itself makes the CLI's one-line "interrupted", status 130, certain.
    previous = signal.signal(signal.SIGINT, _raise_keyboard_interrupt)
    try:
        server.run(sockets=[sock])
    finally:
        signal.signal(signal.SIGINT, previous)
    return 0


def default_memory_budget_mb() -> float:
    """Half of this machine's physical memory, in MB (4096 where it cannot be read)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 / 2**20
    except (ValueError, OSError, AttributeError):
        return 4096.0


def _raise_keyboard_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt

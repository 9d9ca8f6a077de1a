"""``brave6d serve BUNDLE``: serve a scene bundle over HTTP + WebSocket (loopback by default)."""

from __future__ import annotations

import argparse
import logging
import socket
from pathlib import Path

from brave6d.errors import BraveError
from brave6d.runtime import quiet_openmp

log = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bundle", type=Path, help="bundle folder written by 'brave6d export' (checksums are verified)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to bind (default 127.0.0.1: this machine only; 0.0.0.0 exposes the "
                             "server to the network, which has no authentication)")
    parser.add_argument("--port", type=int, default=8765, help="TCP port (default 8765; 0: any free port)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                        help="rasterizer device (auto: cuda when torch sees a GPU)")
    parser.add_argument("--log-dir", type=Path, default=None,
                        help="where episode logs (JSONL) go (default: 'episodes' beside the bundle)")
    parser.add_argument("--max-episodes", type=int, default=32, help="open episodes at most (default 32)")
    parser.add_argument("--request-timeout", type=float, default=30.0,
                        help="seconds one action may take before it is withdrawn with 504 (default 30)")
    parser.add_argument("--max-body-bytes", type=int, default=64 * 1024,
                        help="largest request body / WebSocket message (default 65536)")
    parser.add_argument("--idle-timeout", type=float, default=900.0,
                        help="close episodes idle for this many seconds (default 900)")


def run(args: argparse.Namespace) -> int:
    quiet_openmp()
    import uvicorn

    from serve.app import ServerLimits, create_app
    from serve.bundle import load_bundle
    from serve.runner import is_loopback, uvicorn_config

    if not 0 <= args.port <= 65535:
        raise BraveError(f"--port must be in 0..65535, got {args.port}")
    if args.max_episodes < 1 or args.request_timeout <= 0 or args.max_body_bytes < 1024:
        raise BraveError("--max-episodes >= 1, --request-timeout > 0 and --max-body-bytes >= 1024 are required")
    if not is_loopback(args.host):
        log.warning("binding to %s: the server is reachable from the network and has no authentication",
                    args.host)
    bundle = load_bundle(args.bundle)
    log_dir = args.log_dir if args.log_dir is not None else Path(args.bundle).resolve().parent / "episodes"
    limits = ServerLimits(max_body_bytes=args.max_body_bytes, request_timeout_s=args.request_timeout,
                          max_episodes=args.max_episodes, idle_timeout_s=args.idle_timeout)
    app = create_app(bundle, device=args.device, log_dir=log_dir, limits=limits)
    sock = socket.socket(socket.AF_INET6 if ":" in args.host else socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.host, args.port))
    except OSError as exc:
        raise BraveError(f"cannot listen on {args.host}:{args.port}: {exc.strerror}") from None
    port = sock.getsockname()[1]
    host = f"[{args.host}]" if ":" in args.host else args.host
    print(f"brave6d serve: {bundle.name} ({app.state.scene.renderer.num_gaussians} Gaussians, "
          f"{app.state.scene.device}) on http://{host}:{port}  viewer: /viewer/  API: /docs  "
          f"episode logs: {log_dir}", flush=True)
    level = "info" if getattr(args, "verbose", 0) else "warning"
    server = uvicorn.Server(uvicorn_config(app, args.host, port, level, args.max_body_bytes))
    server.run(sockets=[sock])
    return 0

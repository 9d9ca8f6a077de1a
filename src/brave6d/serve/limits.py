"""The render server's value limits, owned here and nowhere else.

The image-size cap bounds the cost of one render and the size of one reply. It is applied by
the request models (:mod:`brave6d.serve.app`), by the bundle's render defaults when a bundle is
exported or loaded (:class:`brave6d.serve.bundle.RenderDefaults`, which fits larger defaults inside it)
and by :func:`brave6d.serve.bundle.export_bundle` (which refuses an explicit size beyond it), so that no
path renders or sends a larger image than an explicit request may ask for.

The physical bounds keep every pose and twist a client can send finite after any arithmetic the
server does with it (a ``look_at`` of eye 1e308 and target -1e308 overflows to inf; a twist of
1e308 rad/s to an infinite substep count).

The server's operational limits (:class:`ServerLimits`: body size, timeouts, episodes, the
per-connection limits of :mod:`brave6d.serve.connections`) and the range of every number the servers
take from their command lines (:data:`BOUNDS`) are here too, so that the API and the flags
refuse the same values (NaN, inf, negative, too large), naming the limit or the flag.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

from brave6d.core.cli_types import Bound
from brave6d.core.errors import BraveError

#: Smallest image side (pixels).
MIN_SIZE = 16
#: Largest image width (pixels).
MAX_WIDTH = 1280
#: Largest image height (pixels).
MAX_HEIGHT = 960

#: Largest duration of one ``move`` (seconds).
MAX_MOVE_DURATION_S = 10.0
#: Largest absolute value of a position coordinate or a matrix entry of a pose (metres): far
#: beyond any workspace, small enough that no product or difference of two overflows.
MAX_COORD_M = 1000.0
#: Largest absolute value of one component of a ``move``'s linear velocity (m/s).
MAX_LINEAR_SPEED_M_S = 10.0
#: Largest absolute value of one component of a ``move``'s angular velocity (rad/s; one turn per second).
MAX_ANGULAR_SPEED_RAD_S = 2.0 * math.pi


def image_size_error(width: int | None, height: int | None) -> str | None:
    """Why ``width`` x ``height`` (None: not given) is outside the cap, or None when it is inside."""
    for label, value, top in (("width", width, MAX_WIDTH), ("height", height, MAX_HEIGHT)):
        if value is not None and not MIN_SIZE <= value <= top:
            return f"{label} must be in {MIN_SIZE}..{top} pixels, got {value}"
    return None


def fit_image_size(width: int, height: int) -> tuple[int, int]:
    """``width`` x ``height`` scaled down (same aspect ratio) to fit the cap; unchanged when it fits.

    Raises ``ValueError`` when the size is below the minimum, or when the aspect ratio is so
    extreme that the fitted size would be.
    """
    if width < MIN_SIZE or height < MIN_SIZE:
        raise ValueError(f"image size {width}x{height} is below the minimum of {MIN_SIZE} pixels a side")
    scale = min(1.0, MAX_WIDTH / width, MAX_HEIGHT / height)
    if scale == 1.0:
        return width, height
    fitted = (min(MAX_WIDTH, round(width * scale)), min(MAX_HEIGHT, round(height * scale)))
    if min(fitted) < MIN_SIZE:
        raise ValueError(f"image size {width}x{height} cannot be fitted into {MAX_WIDTH}x{MAX_HEIGHT} "
                         f"keeping its aspect ratio and {MIN_SIZE} pixels a side")
    return fitted


# ----------------------------------------------------------------------------- server limits
class LimitError(BraveError, ValueError):
    """A server limit outside its bounds (NaN, infinite, negative, too large); names the limit."""


#: Connections the HTTP server holds at most (uvicorn answers 503 to requests beyond it).
MAX_CONNECTIONS = 256

#: The bounds of every server setting: the fields of :class:`ServerLimits` and the other numbers
#: the servers take from their command lines (ports, image sizes, scene counts, memory).
BOUNDS: dict[str, Bound] = {
    "max_body_bytes": Bound(1024, 16 * 2**20, integer=True),  # x MAX_CONNECTIONS: 4 GiB buffered at worst
    "request_timeout_s": Bound(0, 3600, low_open=True),
    "max_episodes": Bound(1, 10_000, integer=True),
    "idle_timeout_s": Bound(0, 7 * 86400, low_open=True),
    "workers": Bound(1, 256, integer=True),
    "header_timeout_s": Bound(0, 600, low_open=True),
    "body_timeout_s": Bound(0, 3600, low_open=True),
    "max_connections_per_client": Bound(1, MAX_CONNECTIONS, integer=True),
    "write_timeout_s": Bound(0, 3600, low_open=True),
    "max_unsent_bytes": Bound(64 * 1024, 2**30, integer=True),
    "port": Bound(0, 65535, integer=True),
    "max_loaded_scenes": Bound(1, 10_000, integer=True),
    "max_memory_mb": Bound(0, 2**24, low_open=True),  # 16 TiB
    "width": Bound(MIN_SIZE, MAX_WIDTH, integer=True),
    "height": Bound(MIN_SIZE, MAX_HEIGHT, integer=True),
    "move_duration_s": Bound(0, MAX_MOVE_DURATION_S, low_open=True),
}


def limit_arg(name: str) -> Callable[[str], Any]:
    """The argparse ``type=`` of the flag setting ``name`` (a key of :data:`BOUNDS`)."""
    return BOUNDS[name].arg_type()


@dataclass(frozen=True)
class ServerLimits:
    """Operational limits of one server, each checked against :data:`BOUNDS` when it is made
    (:class:`LimitError` naming the field: no server runs with a NaN timeout).

    ``header_timeout_s``: the request line and headers must arrive within it of the connection
    opening (or of the previous response on a kept-alive connection); ``body_timeout_s``: a
    declared body must arrive within it of the headers; ``max_connections_per_client``: open
    connections (HTTP and WebSocket) one client address may hold (an IPv6 client: its /64);
    ``write_timeout_s``: a connection with a reply waiting to be sent must take some of it within
    this time; ``max_unsent_bytes``: the reply bytes one HTTP connection may have waiting in the
    server. See :mod:`brave6d.serve.connections`.
    """

    max_body_bytes: int = 64 * 1024
    request_timeout_s: float = 30.0
    max_episodes: int = 32
    idle_timeout_s: float = 900.0
    workers: int = 16
    header_timeout_s: float = 10.0
    body_timeout_s: float = 30.0
    max_connections_per_client: int = 64
    write_timeout_s: float = 20.0
    max_unsent_bytes: int = 16 * 2**20

    def __post_init__(self) -> None:
        for f in fields(self):
            BOUNDS[f.name].check(getattr(self, f.name), f"ServerLimits.{f.name}", LimitError)

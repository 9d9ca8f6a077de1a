"""The render server's value limits, owned here and nowhere else.

The image-size cap bounds the cost of one render and the size of one reply. It is applied by
the request models (:mod:`serve.app`), by the bundle's render defaults when a bundle is
exported or loaded (:class:`serve.bundle.RenderDefaults`, which fits larger defaults inside it)
and by :func:`serve.bundle.export_bundle` (which refuses an explicit size beyond it), so that no
path renders or sends a larger image than an explicit request may ask for.

The physical bounds keep every pose and twist a client can send finite after any arithmetic the
server does with it (a ``look_at`` of eye 1e308 and target -1e308 overflows to inf; a twist of
1e308 rad/s to an infinite substep count).
"""

from __future__ import annotations

import math

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

"""Numerical conventions shared by every rasterizer backend.

The values follow gsplat 1.5.3 (``gsplat/cuda/include/Common.h`` and the
projection / rasterization kernels) so that the CPU kernel, the pure-torch
reference and the CUDA backend render the same image.
"""

from __future__ import annotations

TILE_SIZE = 16
"""Side of a square screen tile in pixels (gsplat's default ``tile_size``)."""

ALPHA_THRESHOLD = 1.0 / 255.0
"""A Gaussian whose alpha at a pixel is below this is skipped there."""

ALPHA_MAX = 0.999
"""Cap on a single Gaussian's alpha (gsplat; Inria uses 0.99)."""

T_MIN = 1e-4
"""A pixel stops compositing when its transmittance would drop to this or below."""

RADIUS_EXTEND = 3.33
"""Screen-space bounding box half-size in standard deviations (before the opacity-aware bound)."""

DEPTH_ALPHA_EPS = 1e-10
"""Expected depth is accumulated depth divided by ``max(alpha, DEPTH_ALPHA_EPS)``."""

QUAT_MIN_SQNORM = 1e-24
"""Quaternions with squared norm below this (zero, denormal) are treated as the identity
rotation and receive a zero gradient."""

SCALE_MIN = 1e-9
SCALE_MAX = 1e6
"""Activated scales are clamped to ``[SCALE_MIN, SCALE_MAX]`` (gradient zero outside)."""

RADIUS_MAX = 1 << 24
"""Screen radii are clamped to this many pixels so that they fit in int32."""

"""What several views of one object give that one view cannot: its position from the rays of the
views' estimates (parallax), for the RGB-only agent whose single-view distance is only as good as
the object's apparent size.

:func:`triangulate` is the least-squares point nearest to all rays; it answers None, never a
NaN, when the rays are too close to parallel to fix a depth (the camera moved along its line of
sight) or the point would lie behind a camera.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
#: Rays closer than this to parallel (largest angle between any two) fix no depth.
MIN_PARALLAX_DEG = 5.0


def triangulate(origins: Array, directions: Array, min_parallax_deg: float = MIN_PARALLAX_DEG) -> Array | None:
    """The point nearest (least squares) to the rays ``origins[i] + s * directions[i]`` (s > 0), or
    None with fewer than two finite rays, too little parallax, or the point behind a ray's origin."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    norms = np.linalg.norm(d, axis=1)
    keep = np.all(np.isfinite(o), axis=1) & np.all(np.isfinite(d), axis=1) & (norms > 1e-12)
    o, d = o[keep], d[keep] / norms[keep, None]
    if len(o) < 2:
        return None
    cos_min = float(np.clip((d @ d.T).min(), -1.0, 1.0))
    if math.degrees(math.acos(cos_min)) < min_parallax_deg:
        return None
    projectors = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # I - d d^T per ray
    A = projectors.sum(axis=0)
    b = np.einsum("nij,nj->i", projectors, o)
    eig = np.linalg.eigvalsh(A)
    if not eig[0] > 1e-9 * eig[-1]:
        return None
    point = np.linalg.solve(A, b)
    if not np.all(np.isfinite(point)) or np.any(((point - o) * d).sum(axis=1) <= 0):
        return None
    return point

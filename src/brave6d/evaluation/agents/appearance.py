"""Colour agreement of a pose: does the image show the model's colours where the pose puts them?

Depth alone cannot tell an object from its 180 degree flip when its shape is nearly symmetric (a
hex nut, a closed cup, a vial lying down): both explain the depth, and which one wins follows
sub-millimetre noise. The models' colours usually can. :func:`color_disagreement` projects the
model points that face the camera, keeps those the depth image confirms (the point is what the
pixel sees, not something in front of it), and correlates the model's colour with the image's
colour there, channel by channel. Pearson's correlation ignores brightness, gain and offset, so a
splat's colours and a sensor's count alike; it is minus the mean correlation (lower is better), and
0 where it cannot tell: a model without colours or of one colour, a flat image, too few points.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.evaluation.agents.perception import pixels_of

Array = NDArray[np.float64]
MIN_POINTS = 10  # fewer confirmed points than this: no verdict
MIN_MODEL_STD = 0.02  # a channel whose model colours vary less (0..1) carries no pattern
MIN_IMAGE_STD = 1e-3  # a channel of the image this flat (0..1) carries none either


def color_disagreement(colors: Array | None, points: Array, rgb: NDArray[Any], depth: NDArray[np.floating],
                       K: Array, tol: float) -> float:
    """Minus the mean Pearson correlation, over the channels in which the model's ``colors`` (N, 3)
    in [0, 1] vary, between them and the image's colours where their camera-frame ``points`` (N, 3;
    the model points facing the camera under the pose) project, counting only points whose depth the
    image confirms within ``tol`` (m). ``rgb``: (H, W, 3) integers over their full range, or floats in
    [0, 1]. In [-1, 1]; 0 when it cannot tell (see the module docstring)."""
    if colors is None or len(points) == 0:
        return 0.0
    u, v, inside = pixels_of(points, K, depth.shape)
    inside &= np.isfinite(points[:, 2]) & (points[:, 2] > 1e-3)
    u, v, z = u[inside], v[inside], points[inside, 2]
    observed = np.asarray(depth, dtype=np.float64)[v, u]
    confirmed = (observed > 0) & (np.abs(observed - z) < tol)
    if int(confirmed.sum()) < MIN_POINTS:
        return 0.0
    expected = np.asarray(colors)[inside][confirmed]
    image = np.asarray(rgb)
    full = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
    seen = image[v[confirmed], u[confirmed], :3].astype(np.float64) / full
    correlations = []
    for channel in range(3):
        a = expected[:, channel] - expected[:, channel].mean()
        b = seen[:, channel] - seen[:, channel].mean()
        sa, sb = float(np.sqrt(np.mean(a * a))), float(np.sqrt(np.mean(b * b)))
        if sa < MIN_MODEL_STD or sb < MIN_IMAGE_STD:
            continue
        correlations.append(float(np.mean(a * b)) / (sa * sb))
    if not correlations:
        return 0.0
    return -float(np.clip(np.mean(correlations), -1.0, 1.0))

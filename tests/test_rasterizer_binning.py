"""Tile binning of the CPU rasterizer (issue 5).

Binning keeps, for each (camera, Gaussian), only the tiles and rows that its
{alpha >= 1/255} footprint can reach.  That cut is only safe if it is conservative: these
tests render every pixel by brute force and check that no pixel a Gaussian reaches was
dropped, on random scenes with needle-thin, huge, off-screen and faint Gaussians
(hypothesis), and that the lists do not depend on the number of workers.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brave6d.training.rasterizer import kernels as K
from brave6d.training.rasterizer.constants import ALPHA_THRESHOLD, TILE_SIZE

@st.composite
def projected_scenes(draw):
    """Random 3D Gaussians projected by the kernel into 1-2 cameras of a small image."""
    n = draw(st.integers(1, 24))
    width = draw(st.integers(1, 70))
    height = draw(st.integers(1, 70))
    n_cam = draw(st.integers(1, 2))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    log_scale = draw(st.sampled_from([(-4.0, 0.0), (-6.0, 1.5), (-2.0, -1.0)]))
    means = np.stack([rng.uniform(-2.5, 2.5, n), rng.uniform(-2.5, 2.5, n),
                      rng.uniform(0.05, 6.0, n)], axis=-1).astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    scales = np.exp(rng.uniform(*log_scale, size=(n, 3))).astype(np.float32)
    opacities = rng.choice([0.004, 0.02, 0.5, 0.999], n).astype(np.float32)
    viewmats = np.repeat(np.eye(4, dtype=np.float32)[None], n_cam, axis=0)
    viewmats[:, :3, 3] = rng.uniform(-0.5, 0.5, (n_cam, 3))
    f = draw(st.sampled_from([0.3, 1.0, 4.0])) * max(width, height)
    Ks = np.repeat(np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]],
                            np.float32)[None], n_cam, axis=0)
    radii, means2d, depths, conics = K.project_fwd(
        means, quats, scales, opacities, True, viewmats, Ks, width, height, 0.3, 0.01, 1e10)
    rgb = rng.uniform(0.0, 1.0, (1, n, 3)).astype(np.float32)
    rec = K.prepare_splats(means2d, conics, rgb, depths, opacities)
    return rec, radii, depths, width, height


def _reached_pixels(rec, cg, width, height):
    """Pixels (y, x) where record cg's alpha reaches the threshold, by brute force in float64
    from the float32 pixel offsets, with a little slack so near-threshold pixels count too."""
    mx, my, ca, cb, cc, op = (float(v) for v in rec[cg, :6])
    ys, xs = np.mgrid[0:height, 0:width]
    dx = (np.float32(mx) - (xs.astype(np.float32) + np.float32(0.5))).astype(np.float64)
    dy = (np.float32(my) - (ys.astype(np.float32) + np.float32(0.5))).astype(np.float64)
    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    with np.errstate(over="ignore"):
        alpha = op * np.exp(-np.maximum(sigma, 0.0))
    return np.nonzero((sigma >= -1e-6) & (alpha >= ALPHA_THRESHOLD * (1.0 - 1e-4)))


HYPOTHESIS = settings(max_examples=60, deadline=None,
                      suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@HYPOTHESIS
@given(projected_scenes())
def test_binning_keeps_every_pixel_a_gaussian_reaches(scene):
    rec, radii, depths, width, height = scene
    n_cam, n = radii.shape[:2]
    tile_w, tile_h = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    offsets, flatten_ids, isect_rows, gauss_offsets, isect_of = K.bin_splats(
        rec, radii, depths, tile_w, tile_h, width, height, 2)
    kept = {}  # (tile, record) -> (first row, last row) relative to the tile
    for t in range(n_cam * tile_w * tile_h):
        for k in range(offsets[t], offsets[t + 1]):
            r = int(isect_rows[k])
            kept[t, int(flatten_ids[k])] = (r & 255, r >> 8)
    for cg in range(n_cam * n):
        c = cg // n
        if radii[c, cg % n, 0] <= 0 or radii[c, cg % n, 1] <= 0:
            assert gauss_offsets[cg + 1] == gauss_offsets[cg], "a culled Gaussian was binned"
            continue
        ys, xs = _reached_pixels(rec, cg, width, height)
        for y, x in zip(ys.tolist(), xs.tolist()):
            t = c * tile_w * tile_h + (y // TILE_SIZE) * tile_w + x // TILE_SIZE
            assert (t, cg) in kept, f"record {cg} reaches pixel ({x}, {y}) but tile {t} was dropped"
            lo, hi = kept[t, cg]
            assert lo <= y % TILE_SIZE <= hi, f"record {cg}: row {y} outside the kept rows {lo}-{hi}"
    # the Gaussian-major view lists the same intersections
    for cg in range(n_cam * n):
        for j in range(gauss_offsets[cg], gauss_offsets[cg + 1]):
            assert flatten_ids[isect_of[j]] == cg


@HYPOTHESIS
@given(projected_scenes())
def test_tile_lists_are_depth_sorted_and_independent_of_workers(scene):
    rec, radii, depths, width, height = scene
    tile_w, tile_h = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    runs = [K.bin_splats(rec, radii, depths, tile_w, tile_h, width, height, w) for w in (1, 2, 3, 7)]
    for other in runs[1:]:
        for a, b in zip(runs[0], other):
            np.testing.assert_array_equal(a, b)
    offsets, flatten_ids = runs[0][0], runs[0][1]
    n = radii.shape[1]
    for t in range(offsets.shape[0] - 1):
        ids = flatten_ids[offsets[t]:offsets[t + 1]].astype(np.int64)
        d = depths.reshape(-1)[ids]
        assert np.all(np.diff(d) >= 0), f"tile {t} is not sorted front to back"
        same = np.diff(d) == 0
        assert np.all(np.diff(ids)[same] > 0), f"tile {t}: equal depths lost index order"
        assert np.all(ids // n == t // (tile_w * tile_h)), "a tile lists another camera's Gaussian"

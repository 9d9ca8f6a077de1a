"""The RGB-only pose's distance from the visible mask's area.

PnP on a small object's predicted coordinates gets the rotation and the image position roughly
right but the distance only to about 4-7 % (a 30 px object: its scale rests on a pixel or two of
noisy coordinates). The coordinate net's mask measures the object's size in the crop more finely:
summed as probabilities it is a sub-cell area estimate. Under perspective the silhouette's area
falls as 1 / z^2, so the model's silhouette rendered at the PnP pose, against the mask's area, gives
the distance: ``z * sqrt(rendered / predicted)``, the translation scaled along its ray. Measured in
docs/BENCHMARKS.md (Learned baseline): AR given true boxes, RGB-only, 0.396 -> 0.466.

The mask is of the *visible* pixels: an occluded or cut-off object looks smaller and would be put
too far away. The crop's part outside the image is not counted on either side, and a scale that
moves z by more than :data:`MAX_AREA_Z_CHANGE` (an occlusion, not PnP's noise) keeps PnP's distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from brave6d.evaluation.learned.crops import crop_affine

Array = NDArray[np.float64]
#: Supersampled width at which a silhouette is rasterised (outline pixels count half: its area is
#: within 0.1 % of the exact one on the demo's objects).
RASTER_PX = 512
#: A mask-area distance more than this far (relative) from PnP's is not used (see the module docstring).
MAX_AREA_Z_CHANGE = 0.15
#: Fewer mask cells (summed probability) than this leave PnP's distance as it is.
MIN_MASK_AREA = 3.0


@dataclass(frozen=True)
class Silhouette:
    """A model's triangle mesh (metres, model frame) for rasterising its outline."""

    vertices_m: Array
    faces: NDArray[np.int64]

    def __post_init__(self) -> None:
        v, f = np.asarray(self.vertices_m), np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"silhouette: expected (N, 3) vertices and (F, 3) faces, got {v.shape} and {f.shape}")
        if not np.all(np.isfinite(v)) or f.min() < 0 or f.max() >= len(v):
            raise ValueError("silhouette: vertices must be finite and faces index them")


def silhouette_cells(mesh: Silhouette, R: Array, t_m: Array, K: Array, centre: tuple[float, float], side: float,
                     cells: int, image_size: tuple[int, int]) -> float:
    """Area, in cells of a ``cells`` x ``cells`` crop (``centre``, ``side``: image pixels), of the
    mesh's silhouette at ``(R, t_m)`` under ``K``, counting only what lies inside the image
    (``image_size``: width, height). 0 when any vertex is not in front of the camera."""
    import cv2

    cam = np.asarray(mesh.vertices_m) @ np.asarray(R).T + np.asarray(t_m).reshape(3)
    if not np.all(cam[:, 2] > 1e-6):
        return 0.0
    ss = max(1, RASTER_PX // cells)
    uv = cam[:, :2] / cam[:, 2:3] * (K[0, 0], K[1, 1]) + K[:2, 2]
    A = crop_affine(centre, side, cells * ss)
    xy = uv @ A[:, :2].T + A[:, 2]
    raster = np.zeros((cells * ss, cells * ss), np.uint8)
    for triangle in np.round(xy[np.asarray(mesh.faces)] * 16.0).astype(np.int64):
        if np.all(np.abs(triangle) < 2**26):  # far outside the crop: nothing to draw
            cv2.fillConvexPoly(raster, triangle.astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
    # filled polygons include the pixels their outline touches: 0.8 % too much area at 32x supersampling.
    # A pixel on the outline (one with a 4-neighbour outside) is half inside on average, so it counts
    # half (within 0.1 % of the exact area; beyond the crop's edge the silhouette goes on)
    outline = raster - cv2.erode(raster, cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3)),
                                 borderType=cv2.BORDER_REPLICATE)
    weight = raster.astype(np.float64) - 0.5 * outline
    # the raster's pixel centres in image pixels: only those inside the image count
    k = A[0, 0]
    axis = np.arange(cells * ss, dtype=np.float64)
    inside_x = np.abs((axis - A[0, 2]) / k + 0.5 - image_size[0] / 2.0) <= image_size[0] / 2.0
    inside_y = np.abs((axis - A[1, 2]) / k + 0.5 - image_size[1] / 2.0) <= image_size[1] / 2.0
    return float(weight[np.ix_(inside_y, inside_x)].sum()) / ss**2


def mask_area_scale(probability: Array, mesh: Silhouette, R: Array, t_m: Array, K: Array,
                    centre: tuple[float, float], side: float, image_size: tuple[int, int]) -> float | None:
    """The factor on ``t_m`` that makes the silhouette's area at the pose meet the mask's
    (``probability``: the mask's per-cell probabilities over the crop), or None where the mask is
    too small, the silhouette empty or the change beyond :data:`MAX_AREA_Z_CHANGE`."""
    predicted = float(np.sum(probability))
    cells = int(np.shape(probability)[-1])
    if not (math.isfinite(predicted) and predicted >= MIN_MASK_AREA):
        return None
    rendered = silhouette_cells(mesh, R, t_m, K, centre, side, cells, image_size)
    if not rendered > 0:
        return None
    scale = math.sqrt(rendered / predicted)
    if not (math.isfinite(scale) and abs(scale - 1.0) <= MAX_AREA_Z_CHANGE):
        return None
    return scale

"""The training frame: the scene's world moved and scaled once, so that training never sees its units.

A capture's world can be in any unit: the robot's metres, a COLMAP model's arbitrary units, an
``import --scale`` the user guessed. 3DGS has lengths in it (a near plane, the initial scales'
floor, the densification's size limits, the positions' learning rate and Adam's epsilon), and a
length fixed in the world's units makes what training learns depend on them. So :func:`brave6d.training.train`
converts the scene once, here, into the **training frame**: ``p_train = (p_world - centre) / unit``,
with ``centre`` the mean of the camera centres and ``unit`` Inria's scene radius (1.1 times the
largest distance of a camera centre from that mean, :func:`scene_radius`). In the training frame the
scene's extent is exactly 1 whatever the world's units, every length below is a number of extents,
and the trained Gaussians go back to the world once, at the end. The two conversions belong to what
they convert (:meth:`brave6d.training.views.TrainingData.in_frame`,
:meth:`brave6d.training.model.GaussianModel.in_world`); this module holds the frame and the lengths and
imports nothing else of training, so that both can use it.
The poses, the initial points and the depth targets are converted in float64 and then rounded to
float32, so two worlds that differ by a scale give the same float32 inputs (up to the rare number
whose float64 value lies on a float32 rounding boundary) and hence the same training, step for step.

Lengths in scene extents (the trainer, the holdout evaluation and the 3D filter read them from here
through :meth:`brave6d.training.views.TrainingData.scene_extent`, so that a caller training in world
units gets the same lengths relative to its scene):

* :data:`NEAR_PLANE`: Gaussians nearer a camera than 0.02 extents are culled (gsplat's 0.01 m on the
  demo's 0.47 m extent is 0.021);
* :data:`FAR_PLANE`: none in practice (gsplat's 1e10);
* :data:`MIN_INIT_DISTANCE`: the initial scale's floor (Inria's ``sqrt(1e-7)`` m on the demo's extent);
* the densification's ``grow_scale3d`` / ``prune_scale3d`` and the positions' learning rate were
  already in extents (Inria's), and Adam's epsilon for the positions is divided by the extent.

Everything else the trainer uses is in pixels (the densification's gradient threshold, the 2D
filter's 0.3 px, the tile size), in the image's colours, or dimensionless (quaternions, opacities,
the depth loss's relative error). The rasterizer's scale clamp (1e-9 to 1e6) and the 3D filter's
float range are float guards far outside any scene in the training frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import DataError

#: Inria's scene radius is this times the largest distance of a camera centre from their mean.
RADIUS_MARGIN = 1.1
#: The near plane, in scene extents: Gaussians nearer the camera are culled (training, holdout, 3D filter).
NEAR_PLANE = 0.02
#: The far plane, in scene extents (none in practice).
FAR_PLANE = 1e10
#: The far plane a bundle is served with, in scene extents (about gsplat's 100 m on the demo's 0.47 m extent).
SERVE_FAR_PLANE = 200.0
#: The floor of an initial Gaussian's scale (the RMS distance to its 3 nearest points), in scene extents:
#: Inria's ``sqrt(1e-7)`` m on the demo's extent.
MIN_INIT_DISTANCE = 6.7e-4


def scene_radius(centres: ArrayLike) -> float:
    """Inria's scene extent of cameras at ``centres`` [N, 3]: 1.1 x the largest distance from their mean.

    Cameras that all stand at one spot (or a single camera) have no extent: their world's unit,
    1.0, is taken (the only length such a capture has), so training stays finite.
    """
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    if len(c) == 0 or not np.isfinite(c).all():
        raise DataError("the scene's extent needs finite camera centres")
    radius = float(np.linalg.norm(c - c.mean(axis=0), axis=1).max())
    scale = float(np.abs(c).max())
    if not radius > 1e-12 * max(scale, 1e-300):
        return 1.0
    return RADIUS_MARGIN * radius


def near_far(extent: float) -> tuple[float, float]:
    """The rasterizer's ``(near_plane, far_plane)`` for a scene of ``extent`` (in its units)."""
    return NEAR_PLANE * extent, FAR_PLANE * extent


@dataclass(frozen=True)
class SceneFrame:
    """``p_train = (p_world - centre) / unit``: the training frame of a scene (module docstring)."""

    centre: tuple[float, float, float]
    unit: float  # world units per training unit: the scene's extent in the world

    @classmethod
    def of_cameras(cls, centres: ArrayLike) -> SceneFrame:
        """The frame of cameras at ``centres`` [N, 3] (world units)."""
        c = np.asarray(centres, np.float64).reshape(-1, 3)
        unit = scene_radius(c)
        mean = c.mean(axis=0)
        return cls((float(mean[0]), float(mean[1]), float(mean[2])), unit)

    @property
    def centre_array(self) -> NDArray[np.float64]:
        return np.asarray(self.centre, np.float64)

    # ------------------------------------------------------------------ world -> training frame
    def points(self, p_world: ArrayLike) -> NDArray[np.float64]:
        """World points [N, 3] in the training frame (float64)."""
        return (np.asarray(p_world, np.float64).reshape(-1, 3) - self.centre_array) / self.unit

    def pose(self, world_T_cam: ArrayLike) -> NDArray[np.float64]:
        """A camera pose (4x4, world) in the training frame: the same rotation, the centre moved and scaled."""
        out = np.array(world_T_cam, np.float64, copy=True).reshape(4, 4)
        out[:3, 3] = self.points(out[:3, 3])[0]
        return out

    # ------------------------------------------------------------------ training frame -> world
    def world_points(self, p_train: ArrayLike) -> NDArray[np.float64]:
        """Training-frame points [N, 3] in the world (float64)."""
        return np.asarray(p_train, np.float64).reshape(-1, 3) * self.unit + self.centre_array

    def to_json(self) -> dict[str, Any]:
        near, far = near_far(self.unit)
        return {"centre": list(self.centre), "unit": self.unit, "near_plane": near, "far_plane": far,
                "serve_far_plane": SERVE_FAR_PLANE * self.unit,
                "convention": "p_train = (p_world - centre) / unit; unit = the scene's extent (1.1 x the largest "
                              "camera distance from their mean) in world units"}

    @classmethod
    def from_json(cls, record: Any) -> SceneFrame:
        """The frame a :meth:`to_json` record holds; a malformed one raises :class:`DataError`."""
        try:
            centre = [float(v) for v in record["centre"]]
            unit = float(record["unit"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"a scene frame record needs 'centre' (3 numbers) and 'unit' ({exc})") from None
        if len(centre) != 3 or not all(math.isfinite(v) for v in centre) or not (math.isfinite(unit) and unit > 0):
            raise DataError(f"a scene frame record needs a finite centre and a positive unit, got {record!r}")
        return cls((centre[0], centre[1], centre[2]), unit)


def serve_planes(scene_dir: Any) -> tuple[float, float]:
    """The ``(near, far)`` planes (world units) a bundle of ``scene_dir`` is served with: the near plane
    its training used (``splat/metrics.json``'s ``scene_frame``) and :data:`SERVE_FAR_PLANE` extents, so
    that the server culls what training culled, whatever the scene's units. A scene trained before
    training frames, or whose record is unreadable, gets them from its capture's camera centres (else its
    spec's workspace)."""
    from brave6d.core.atomic import read_json
    from brave6d.core.calibration_io import camera_poses
    from brave6d.core.layout import SceneDir

    scene = SceneDir(scene_dir)
    unit = None
    if scene.metrics_path.is_file():
        try:
            record = read_json(scene.metrics_path).get("scene_frame")
            unit = SceneFrame.from_json(record).unit if record is not None else None
        except (DataError, AttributeError):
            unit = None
    if unit is None:
        try:
            unit = scene_radius([T[:3, 3] for _, T in camera_poses(scene)])
        except (DataError, OSError, ValueError):  # no capture: the spec's workspace, else the world's unit
            unit = _workspace_radius(scene)
    return NEAR_PLANE * unit, SERVE_FAR_PLANE * unit


def _workspace_radius(scene: Any) -> float:
    """Half the diagonal of the scene spec's workspace box (1.0 without a readable spec)."""
    try:
        ws = scene.load_spec().workspace
        half = 0.5 * float(np.linalg.norm(np.asarray(ws.max, np.float64) - np.asarray(ws.min, np.float64)))
    except Exception:  # noqa: BLE001 - any unreadable spec: the world's unit
        return 1.0
    return half if math.isfinite(half) and half > 0 else 1.0

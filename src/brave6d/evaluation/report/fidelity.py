"""Fidelity where agents look: the splat against the truth at the poses an agent goes to.

One comparison per view, the same for a simulated and a captured scene:

* **simulated** (the scene's ``scene.yaml`` has a ``simulation:`` part): seeded viewpoints per
  object at each distance (the distance section's :func:`viewpoint`, collision-checked, looking at
  the object's model centre), the splat rendered by the server (:class:`brave6d.serve.SceneServer`)
  and the simulator's truth (:class:`brave6d.capture.SimCamera` over the scene's meshes) at the SAME
  pose and bundle camera, with NO camera effect (no noise, blur, vignetting, lens distortion or depth
  noise; the capture's edge anti-aliasing kept): truth depth is the exact z-depth of the first hit
  (no sensor range), the target's pixels those of its id in the simulator's object-id buffer;
* **captured** (no ``simulation:``): the held-out frames of each capture ring (as the realism
  section picks them) from the annotation's BOP export (undistorted RGB, sensor depth with 0 = no
  data, ``mask_visib`` as the targets' pixels), the splat rendered at the frame's camera and pose.

Per view: PSNR/SSIM of the whole image (over the pixels the raw image covers) and of each target's
bounding box, the depth error on the target's pixels (:func:`depth_errors`), and the static
estimator (:mod:`brave6d.evaluation.report.single_view`) on the truth's depth and on the splat's, both
scored with BOP19 against the ground truth with the truth's depth as VSD's test depth, for targets at
least 10 % visible in the truth. Beside the box PSNR, its **sampling ceiling**
(:func:`sampling_ceiling`): the truth band-limited to what the training images could hold at that
view (:class:`TrainingSampling`, :func:`sampling_ratio`) against the full truth, the best box PSNR a
splat trained on those images can reach. :func:`fidelity_rows` pools the views per distance (medians; AR as the mean over targets,
BOP's pooling), :func:`fidelity_table` lays them out with metrics as rows and distances as columns.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brave6d.core.errors import DataError
from brave6d.evaluation.report.common import fmt, median, num, paired_standard_error

#: The agent's range: the capture's rings and closer than the nearest one (m).
DISTANCES_M = (0.10, 0.125, 0.15, 0.20, 0.30, 0.40, 0.50)
#: Depth tolerances (mm): 5 mm, and BOP VSD's delta (15 mm).
TOLERANCES_MM = (5.0, 15.0)
#: The capture's silhouette anti-aliasing of the simulated scene camera (rays per pixel side).
SIM_EDGE_SUPERSAMPLE = 3
#: Simulated truth depth has no sensor range: any hit counts (m).
SIM_DEPTH_RANGE = (0.0, 1000.0)


@dataclass(frozen=True)
class FidelitySweep:
    """Distances (m) and viewpoints per object and distance (simulated scenes), held-out and
    training views per capture ring (captured scenes), the image size as a fraction of the
    bundle's (simulated), the viewpoints' seed and the render device."""

    distances_m: tuple[float, ...] = DISTANCES_M
    views: int = 3  # per object and distance: 12 views per distance on the demo's 4 objects
    holdout_per_level: int = 3
    train_per_level: int = 0
    scale: float = 1.0
    seed: int = 0
    device: str = "auto"


# ----------------------------------------------------------------------------- metrics of one view
@dataclass(frozen=True)
class DepthErrors:
    """Depth error on a target's pixels that have truth depth (``pixels``): median |splat - truth|
    (mm, over the pixels where the splat has depth too), the shares of ``pixels`` within 5 and 15 mm
    (a pixel without splat depth is not within) and the share without splat depth. NaN without pixels."""

    pixels: int
    median_mm: float
    within_5mm: float
    within_15mm: float
    no_depth: float

    def to_json(self) -> dict[str, Any]:
        return {"depth_px": self.pixels, "depth_median_mm": self.median_mm, "within_5mm": self.within_5mm,
                "within_15mm": self.within_15mm, "no_depth": self.no_depth}


def has_depth(depth_m: NDArray[np.floating]) -> NDArray[np.bool_]:
    """Pixels with a depth value: finite and positive (0 = no data, as the sensor and the server write it)."""
    d = np.asarray(depth_m, dtype=np.float64)
    return np.isfinite(d) & (d > 0.0)


def depth_errors(splat_m: NDArray[np.floating], truth_m: NDArray[np.floating], mask: NDArray[np.bool_]
                 ) -> DepthErrors:
    """:class:`DepthErrors` of ``splat_m`` against ``truth_m`` (metres) on the pixels of ``mask``."""
    s, t = np.asarray(splat_m, dtype=np.float64), np.asarray(truth_m, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if not s.shape == t.shape == m.shape:
        raise DataError(f"depth errors: shapes differ: splat {s.shape}, truth {t.shape}, mask {m.shape}")
    ref = m & has_depth(t)
    n = int(ref.sum())
    if n == 0:
        return DepthErrors(0, math.nan, math.nan, math.nan, math.nan)
    both = ref & has_depth(s)
    err_mm = np.abs(s[both] - t[both]) * 1000.0
    within = [float(np.count_nonzero(err_mm <= tol)) / n for tol in TOLERANCES_MM]
    return DepthErrors(n, float(np.median(err_mm)) if err_mm.size else math.nan, within[0], within[1],
                       1.0 - float(both.sum()) / n)


def target_box(mask: NDArray[np.bool_]) -> tuple[slice, slice] | None:
    """Row and column slices of the bounding box of ``mask``'s pixels; None when it has none."""
    rows, cols = np.nonzero(np.asarray(mask, dtype=bool))
    if rows.size == 0:
        return None
    return slice(int(rows.min()), int(rows.max()) + 1), slice(int(cols.min()), int(cols.max()) + 1)


def image_scores(splat: NDArray[np.uint8], truth: NDArray[np.uint8], valid: NDArray[np.bool_] | None = None,
                 box: tuple[slice, slice] | None = None) -> tuple[float, float]:
    """PSNR (dB, 100 when identical) and SSIM of the splat's image against the truth's, over the whole
    image or within ``box``, on the ``valid`` pixels; NaN when no valid pixel is left."""
    from brave6d.evaluation.report.image_quality import psnr, ssim

    a, b = np.asarray(splat), np.asarray(truth)
    v = None if valid is None else np.asarray(valid, dtype=bool)
    if box is not None:
        a, b = a[box], b[box]
        v = None if v is None else v[box]
    if a.size == 0 or (v is not None and not v.any()):
        return math.nan, math.nan
    return psnr(a, b, v), ssim(a, b, v)


# ----------------------------------------------------------------------------- the training's sampling
@dataclass(frozen=True)
class TrainingSampling:
    """How finely the training images sampled the scene: the nearest capture ring (m) and the
    training images' focal length (px: the capture's over the preset's downscale). A training
    pixel covers ``nearest_m / focal_px`` metres on a target at the nearest ring, the finest it saw."""

    nearest_m: float
    focal_px: float

    @property
    def footprint_m(self) -> float:
        return self.nearest_m / self.focal_px


def recorded_downscale(metrics: dict[str, Any]) -> float:
    """The training images' downscale recorded in a training's ``metrics.json`` (its ``images``
    record, else its preset's); NaN when neither records one."""
    return num((metrics.get("images") or {}).get("downscale") or (metrics.get("preset_config") or {}).get("downscale"))


def training_sampling(scene: Any, focal_px: float, downscale: float | None = None) -> TrainingSampling | None:
    """The scene's :class:`TrainingSampling` for a capture camera of focal ``focal_px`` (the bundle's):
    ``downscale`` (None or NaN: the training's record, :func:`recorded_downscale` of ``splat/metrics.json``),
    the nearest ring from the capture's frames (``distance_m``; else ``scene.yaml``'s
    ``capture.distances_m``). None when the training or the rings are not recorded."""
    if downscale is None or math.isnan(downscale):
        if not scene.metrics_path.is_file():
            return None
        from brave6d.core.atomic import read_json

        downscale = recorded_downscale(read_json(scene.metrics_path))
        if not math.isfinite(downscale):
            return None
    if not (math.isfinite(downscale) and downscale > 0):
        raise DataError(f"{scene.root}: the training's image downscale must be positive, got {downscale}")
    if scene.frames_path.is_file():
        rings = [r.distance_m for r in scene.frames()]
    else:
        capture = getattr(scene.load_spec(), "capture", None)
        rings = list(capture.distances_m) if capture is not None else []
    if not rings:
        return None
    return TrainingSampling(float(min(rings)), float(focal_px) / float(downscale))


def sampling_ratio(view_distance_m: float, view_focal_px: float, sampling: TrainingSampling | None) -> float:
    """r = the training's pixel footprint on the target / the view's (``view_distance_m /
    view_focal_px``): above 1 the view resolves detail no training image held. NaN when unknown."""
    if sampling is None or not (view_distance_m > 0 and view_focal_px > 0):
        return math.nan
    return sampling.footprint_m / (float(view_distance_m) / float(view_focal_px))


def sampling_ceiling(truth: NDArray[np.uint8], ratio: float, box: tuple[slice, slice] | None = None,
                     valid: NDArray[np.bool_] | None = None) -> float:
    """PSNR (dB) in ``box`` of the truth band-limited to the training's sampling against the full
    truth: the truth area-averaged to 1/``ratio`` of its size and bilinearly back, i.e. the best a
    splat that only saw pixels ``ratio`` times coarser can match it (100 dB: no detail lost). NaN
    when ``ratio`` <= 1 or unknown (no ceiling: the training sampled at least as finely) or the box
    holds no valid pixel; never inf. An estimate, not a strict bound: bilinear is one reconstruction,
    and many training views at sub-pixel offsets can recover a little finer detail."""
    import cv2

    r = num(ratio)
    if not (math.isfinite(r) and r > 1.0):
        return math.nan
    t = np.ascontiguousarray(truth)
    h, w = t.shape[:2]
    small = cv2.resize(t, (max(1, round(w / r)), max(1, round(h / r))), interpolation=cv2.INTER_AREA)
    blurred = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR).reshape(t.shape)
    return image_scores(blurred, t, valid, box)[0]


def compare_target(rgb_splat: NDArray[np.uint8], rgb_truth: NDArray[np.uint8], depth_splat: NDArray[np.floating],
                   depth_truth: NDArray[np.floating], mask: NDArray[np.bool_],
                   valid: NDArray[np.bool_] | None = None, ratio: float = math.nan) -> dict[str, Any]:
    """One target's image and depth figures: its pixels, box PSNR/SSIM, the box's
    :func:`sampling_ceiling` at the sampling ratio ``ratio`` and :class:`DepthErrors`."""
    m = np.asarray(mask, dtype=bool) if valid is None else np.asarray(mask, dtype=bool) & np.asarray(valid, bool)
    box = target_box(m)
    box_psnr, box_ssim = image_scores(rgb_splat, rgb_truth, valid, box) if box is not None else (math.nan, math.nan)
    ceiling = sampling_ceiling(rgb_truth, ratio, box, valid) if box is not None else math.nan
    return {"px": int(m.sum()), "box_psnr": box_psnr, "box_ssim": box_ssim, "sampling_ratio": num(ratio),
            "box_psnr_ceiling": ceiling, **depth_errors(depth_splat, depth_truth, m).to_json()}


# ----------------------------------------------------------------------------- the views of a scene
class FidelityProbe:
    """The views of one scene and their comparison (see the module docstring).

    ``bundle`` gives the objects, their ground truth, the camera, the collision world and the
    render settings; ``renderer`` (a :class:`brave6d.serve.SplatRenderer`) the splat to measure
    (default: the bundle's). :meth:`items` lists ``(id, item)`` pairs, :meth:`measure` measures one.
    """

    def __init__(self, scene: Any, bundle: Any, sweep: FidelitySweep, renderer: Any = None,
                 downscale: float | None = None) -> None:
        if not bundle.objects:
            raise DataError(f"{bundle.root}: the bundle has no objects to look at")
        if sweep.views < 1 or not sweep.distances_m or any(not (d > 0 and math.isfinite(d)) for d in sweep.distances_m):
            raise DataError(f"fidelity: need views >= 1 and positive distances, got {sweep.views} and "
                            f"{list(sweep.distances_m)}")
        self.scene, self.bundle, self.sweep = scene, bundle, sweep
        self.spec = scene.load_spec()
        self.simulated = self.spec.simulation is not None
        self.mode = "simulated" if self.simulated else "captured"
        self._renderer = renderer
        self._state: dict[str, Any] = {}
        camera = bundle.camera
        if sweep.scale != 1.0:
            camera = camera.scaled(max(16, round(camera.width * sweep.scale)), max(16, round(camera.height * sweep.scale)))
        self.camera = camera
        #: the training images' sampling (``downscale``: the training's, default the scene's record)
        self.sampling = training_sampling(scene, bundle.camera.fx, downscale)
        self._items = self._sim_items() if self.simulated else self._captured_items()

    # ------------------------------------------------------------------ what is measured
    def items(self) -> list[tuple[str, Any]]:
        return list(self._items)

    def settings(self) -> dict[str, Any]:
        s = self.sweep
        out: dict[str, Any] = {"mode": self.mode, "device": s.device, "objects": len(self.bundle.objects),
                               "training_sampling": None if self.sampling is None else
                               {"nearest_ring_m": self.sampling.nearest_m, "focal_px": self.sampling.focal_px}}
        if self.simulated:
            out.update(distances_m=list(s.distances_m), views=s.views, seed=s.seed,
                       image=f"{self.camera.width}x{self.camera.height}")
        else:
            out.update(holdout_per_level=s.holdout_per_level, train_per_level=s.train_per_level, views=len(self._items))
        return out

    def _sim_items(self) -> list[tuple[str, Any]]:
        names = {o.name for o in self.spec.objects}
        missing = [o.name for o in self.bundle.objects if o.name not in names]
        if missing:
            raise DataError(f"{self.scene.spec_path}: no simulated object named {', '.join(missing)} "
                            f"(the bundle's objects; scene.yaml has {', '.join(sorted(names)) or 'none'})")
        return [(f"o{o.obj_id}-g{o.gt_id}-d{round(d * 1000)}-v{k}", (o.gt_id, float(d), k))
                for o in self.bundle.objects for d in self.sweep.distances_m for k in range(self.sweep.views)]

    def _captured_items(self) -> list[tuple[str, Any]]:
        from brave6d.annotation import BopLayout, read_scene_camera, read_scene_gt, read_scene_gt_info
        from brave6d.evaluation.report.real_vs_splat import choose_views

        layout = BopLayout.of_scene(self.scene)
        cams = read_scene_camera(layout.scene_camera_path)
        gts = read_scene_gt(layout.scene_gt_path)
        infos = read_scene_gt_info(layout.scene_gt_info_path)
        records = {r.index: r for r in self.scene.frames()}
        levels = {i: records[i].distance_level for i in gts if i in records}
        picked = choose_views(levels, {h.index for h in self.bundle.holdout}, set(cams) & set(infos),
                              self.sweep.holdout_per_level, self.sweep.train_per_level)
        self._state.update(layout=layout, cams=cams, gts=gts, infos=infos, records=records)
        return [(f"im{i}", (i, held)) for i, held in picked]

    # ------------------------------------------------------------------ lazily built tools
    def _prepared(self) -> dict[str, Any]:
        s = self._state
        if "scorer" in s:
            return s
        from brave6d.evaluation.metrics import models_from_bundle
        from brave6d.evaluation.report.single_view import StaticEstimator, ViewScorer
        from brave6d.serve import SceneServer

        b = self.bundle
        s["server"] = SceneServer(b, self.sweep.device, renderer=self._renderer)
        # compiles the kernels outside the first view's render time
        s["server"].renderer.warm_up(self.camera, b.holdout[0].world_T_cam if b.holdout else np.eye(4))
        s["scorer"] = ViewScorer(models_from_bundle(b))
        s["estimator"] = StaticEstimator({o.obj_id: (b.model_path(o), o.diameter_mm) for o in b.objects})
        if self.simulated:
            from brave6d.capture import SceneModel, SimCamera

            sim = self.spec.simulation
            s["truth"] = SimCamera(SceneModel.from_spec(self.spec), self.camera, None, lambda t: np.eye(4),
                                   lambda: 0.0, seed=sim.seed, light_direction=sim.light_direction,
                                   ambient=sim.ambient, background_rgb=sim.background_rgb,
                                   depth_range=SIM_DEPTH_RANGE, edge_supersample=SIM_EDGE_SUPERSAMPLE)
            s["sim_index"] = {o.name: k + 1 for k, o in enumerate(self.spec.objects)}
        else:
            from brave6d.evaluation.report.real_vs_splat import raw_data_pixels

            s["valid"] = raw_data_pixels(self.scene, (self.bundle.camera.width, self.bundle.camera.height))
        return s

    def _estimates(self, sides: dict[str, tuple[NDArray[np.floating], NDArray[np.uint8]]], K: NDArray[np.float64],
                   world_T_cam: NDArray[np.float64], obj_id: int, pixel: tuple[float, float],
                   cam_T_obj: NDArray[np.float64], visib: float) -> dict[str, Any]:
        """The static estimator on each side's depth and colour (``truth``, ``splat``), both scored
        with the truth's depth as VSD's test depth (as the realism section scores both on the
        captured depth)."""
        s = self._prepared()
        test_depth = sides["truth"][0]
        out: dict[str, Any] = {}
        for side, (depth_m, rgb) in sides.items():
            est = s["estimator"].estimate(depth_m, K, world_T_cam, obj_id, pixel, rgb)
            score = s["scorer"].score(est, obj_id, cam_T_obj, K, (depth_m.shape[1], depth_m.shape[0]), test_depth,
                                      visib)
            out.update({f"ar_{side}": score.ar, f"found_{side}": est.cam_T_obj is not None})
        return out

    def measure(self, item: Any) -> dict[str, Any]:
        """One view's point (see the module docstring)."""
        return self._measure_sim(item) if self.simulated else self._measure_captured(item)

    def _measure_sim(self, item: tuple[int, float, int]) -> dict[str, Any]:
        from brave6d.evaluation.report.sections.distance import viewpoint
        from brave6d.evaluation.report.single_view import MIN_VISIB_FRACT

        gt_id, distance, k = item
        s = self._prepared()
        obj = self.bundle.objects[gt_id]
        server = s["server"]
        rng = np.random.default_rng([self.sweep.seed, gt_id, round(distance * 1000), k])
        point: dict[str, Any] = {"obj_id": obj.obj_id, "object": obj.name, "distance_m": distance, "targets": []}
        found = viewpoint(server.centres_world[gt_id], distance, self.bundle.start, rng, self.bundle.world.check)
        if found is None:
            return {**point, "note": "every drawn viewpoint collides"}
        T, az, el = found
        cam = self.camera
        view = server.observe(T, cam, gt_id)
        t0 = time.perf_counter()
        truth = s["truth"].render(T)
        truth_s = time.perf_counter() - t0
        depth_truth = np.where(np.isfinite(truth.z_m), truth.z_m, 0.0).astype(np.float32)
        psnr_img, ssim_img = image_scores(view.rgb, truth.rgb)
        mask = truth.object_ids == s["sim_index"][obj.name]
        target = {"obj_id": obj.obj_id, "object": obj.name,
                  **compare_target(view.rgb, truth.rgb, view.depth, depth_truth, mask,
                                   ratio=sampling_ratio(distance, cam.fx, self.sampling))}
        state = view.target()
        visib = num(state.visib_fract) if state is not None else math.nan
        if server.visibility is not None:  # visible in the truth (the served fraction is the splat's)
            visib = num(server.visibility.compute(T, cam, depth_truth)[gt_id].visib_fract)
        target["visib_fract"] = visib
        if state is not None and visib >= MIN_VISIB_FRACT and target["px"] > 0:
            target.update(self._estimates({"truth": (depth_truth, truth.rgb), "splat": (view.depth, view.rgb)},
                                          cam.K, T, obj.obj_id,
                                          (cam.cx, cam.cy), state.cam_T_obj, visib))
        return {**point, "azimuth_deg": az, "elevation_deg": el, "psnr": psnr_img, "ssim": ssim_img,
                "render_s": view.timings_ms["render"] / 1000.0, "truth_s": truth_s, "targets": [target]}

    def _measure_captured(self, item: tuple[int, bool]) -> dict[str, Any]:
        from brave6d.core.atomic import read_png
        from brave6d.core.camera import PinholeCamera
        from brave6d.core.transforms import invert
        from brave6d.evaluation.report.real_vs_splat import depth_png_to_m
        from brave6d.evaluation.report.single_view import MIN_VISIB_FRACT, model_centre_m, project

        im_id, held_out = item
        s = self._prepared()
        layout, cam = s["layout"], s["cams"][im_id]
        rec = s["records"][im_id]
        point: dict[str, Any] = {"im_id": im_id, "holdout": held_out, "level": rec.distance_level,
                                 "distance_m": rec.distance_m, "targets": []}
        rgb_truth = read_png(layout.rgb_path(im_id), "rgb")
        if not layout.depth_path(im_id).is_file():
            raise DataError(f"{layout.depth_path(im_id)}: no depth image of captured frame {im_id}")
        depth_truth = depth_png_to_m(read_png(layout.depth_path(im_id), "depth"), cam.depth_scale)
        h, w = rgb_truth.shape[:2]
        K = cam.cam_K
        world_T_cam = invert(cam.cam_T_world())
        # the server's render (the bundle's render settings) at the frame's camera
        out = s["server"].observe(world_T_cam, PinholeCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2]), None)
        valid = s["valid"] if s["valid"] is not None and s["valid"].shape == (h, w) else None
        psnr_img, ssim_img = image_scores(out.rgb, rgb_truth, valid)
        names = {o.obj_id: o.name for o in self.bundle.objects}
        targets = []
        for gt_id, (g, gi) in enumerate(zip(s["gts"][im_id], s["infos"][im_id])):
            path = layout.mask_visib_path(im_id, gt_id)
            if not path.is_file():
                raise DataError(f"{path}: no visible mask of object {g.obj_id} in captured frame {im_id}")
            mask = np.asarray(read_png(path, "mask")) > 0
            if mask.ndim == 3:
                mask = mask.any(axis=2)
            target = {"obj_id": g.obj_id, "object": names.get(g.obj_id, str(g.obj_id)), "visib_fract": gi.visib_fract,
                      **compare_target(out.rgb, rgb_truth, out.depth, depth_truth, mask, valid,
                                       sampling_ratio(rec.distance_m, float(K[0, 0]), self.sampling))}
            if gi.visib_fract >= MIN_VISIB_FRACT and target["px"] > 0:
                cam_T_obj = g.cam_T_model()
                verts = s["scorer"].models[g.obj_id].points
                pixel = project(cam_T_obj[:3, :3] @ model_centre_m(verts) + cam_T_obj[:3, 3], K)
                target.update(self._estimates({"truth": (depth_truth, rgb_truth), "splat": (out.depth, out.rgb)}, K,
                                              world_T_cam, g.obj_id, pixel, cam_T_obj, gi.visib_fract))
            targets.append(target)
        return {**point, "psnr": psnr_img, "ssim": ssim_img, "render_s": out.timings_ms["render"] / 1000.0,
                "targets": targets}


# ----------------------------------------------------------------------------- pooling per distance
#: (key, label, digits) of the table's rows, in the issue's layout.
ROWS: tuple[tuple[str, str, int], ...] = (
    ("views", "views (targets scored)", 0),
    ("px", "target pixels", 0),
    ("psnr", "PSNR of the image (dB)", 1),
    ("ssim", "SSIM of the image", 3),
    ("box_psnr", "PSNR in the target's box (dB)", 1),
    ("box_psnr_ceiling", "box PSNR ceiling at the training's sampling (dB)", 1),
    ("sampling_ratio", "sampling ratio r (training pixel / view pixel on the target)", 2),
    ("box_ssim", "SSIM in the target's box", 3),
    ("depth_median_mm", "depth error on the target's pixels, median (mm)", 1),
    ("within_5mm", "share of target pixels within 5 mm", 2),
    ("within_15mm", "share within 15 mm (BOP VSD's delta)", 2),
    ("no_depth", "share of target pixels without splat depth", 2),
    ("ar_truth", "static estimator AR on the truth", 2),
    ("ar_splat", "static estimator AR on the splat", 2),
    ("ar_gap", "AR gap (truth - splat)", 2),
    ("ar_gap_se", "its standard error (per-target differences)", 2),
)


def _mean(values: Sequence[Any]) -> float:
    a = [num(v) for v in values]
    a = [v for v in a if math.isfinite(v)]
    return float(np.mean(a)) if a else math.nan


def fidelity_rows(points: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per distance (ascending): medians over the views (image) and targets (the rest; target
    pixels over every target, the others over targets with pixels), AR as the mean over scored targets."""
    groups: dict[float, list[dict[str, Any]]] = defaultdict(list)
    for p in points:
        groups[round(num(p.get("distance_m")), 4)].append(p)
    rows = []
    for d, pts in sorted(groups.items()):
        tg = [t for p in pts for t in p.get("targets", [])]
        seen = [t for t in tg if num(t.get("px")) > 0]
        scored = [t for t in tg if "ar_truth" in t and "ar_splat" in t]
        row: dict[str, Any] = {"distance_m": d, "views": len(pts), "targets": len(tg), "scored": len(scored),
                               "px": median([t.get("px") for t in tg]),
                               "psnr": median([p.get("psnr") for p in pts]), "ssim": median([p.get("ssim") for p in pts])}
        for k in ("box_psnr", "box_psnr_ceiling", "sampling_ratio", "box_ssim", "depth_median_mm", "within_5mm",
                  "within_15mm", "no_depth"):
            row[k] = median([t.get(k) for t in seen])
        row["ar_truth"], row["ar_splat"] = _mean([t["ar_truth"] for t in scored]), _mean([t["ar_splat"] for t in scored])
        row["ar_gap"] = row["ar_truth"] - row["ar_splat"] if scored else math.nan
        row["ar_gap_se"] = paired_standard_error([num(t["ar_truth"]) - num(t["ar_splat"]) for t in scored])
        row["render_s"] = median([p.get("render_s") for p in pts])
        rows.append(row)
    return rows


def fidelity_table(rows: Sequence[dict[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """Headers (``metric``, then the distances in cm) and one line per metric (the issue's layout);
    a value that cannot be measured (no target, no depth) reads ``n/a``, never NaN."""
    headers = ["metric", *(f"{fmt(r['distance_m'] * 100, 1).removesuffix('.0')} cm" for r in rows)]
    lines = []
    for key, label, digits in ROWS:
        if key == "views":
            lines.append([label, *(f"{r['views']} ({r['scored']})" for r in rows)])
        else:
            lines.append([label, *(fmt(r[key], digits) for r in rows)])
    return headers, lines


# ----------------------------------------------------------------------------- the figure
def plot_fidelity(path: Any, series: Sequence[tuple[str, Sequence[dict[str, Any]]]], title: str, machine: str,
                  settings: str) -> tuple[Any, int]:
    """One PNG: box PSNR, depth error, shares within 5/15 mm and AR (truth dashed, splat solid)
    against distance, one line per configuration (``(label, rows)``); returns the path and how
    many NaN points were left out."""
    from pathlib import Path

    from brave6d.evaluation.report.plots import legend, new_figure, plot_line, save_figure

    fig, (ax_psnr, ax_depth, ax_share, ax_ar) = new_figure(4, panel=(4.2, 3.4))
    dropped = 0
    for i, (label, rows) in enumerate(series):
        c = f"C{i}"
        cm = [r["distance_m"] * 100.0 for r in rows]
        dropped += plot_line(ax_psnr, cm, [r["box_psnr"] for r in rows], f"{label}: target's box", fmt="o-", color=c)
        dropped += plot_line(ax_psnr, cm, [r["psnr"] for r in rows], f"{label}: image", fmt="s:", color=c, alpha=0.7)
        dropped += plot_line(ax_depth, cm, [r["depth_median_mm"] for r in rows], label, fmt="o-", color=c)
        dropped += plot_line(ax_share, cm, [r["within_5mm"] for r in rows], f"{label}: 5 mm", fmt="o-", color=c)
        dropped += plot_line(ax_share, cm, [r["within_15mm"] for r in rows], f"{label}: 15 mm", fmt="^--", color=c)
        dropped += plot_line(ax_ar, cm, [r["ar_splat"] for r in rows], f"{label}: splat", fmt="o-", color=c)
        dropped += plot_line(ax_ar, cm, [r["ar_truth"] for r in rows], f"{label}: truth", fmt="x--", color=c, alpha=0.7)
    for ax, what in ((ax_psnr, "PSNR [dB] (median)"), (ax_depth, "depth error on target [mm] (median)"),
                     (ax_share, "share of target pixels within"), (ax_ar, "static estimator AR")):
        ax.set_xlabel("camera distance to the object's centre [cm]")
        ax.set_ylabel(what)
        legend(ax)
    ax_depth.set_ylim(bottom=0)
    ax_share.set_ylim(-0.02, 1.02)
    ax_ar.set_ylim(-0.03, 1.03)
    return save_figure(fig, Path(path), title, machine, settings), dropped

"""Multi-view fusion: one pose from the registrations of every view of an episode.

The submitted pose is expressed in the final view's camera frame (where VSD and MSPD are scored):
of that view's own registration and the other views' registrations that put the object at the same
place, the one that explains every view best (a nearer or side view may show how the object is
turned where the final view cannot), refined by point-to-plane ICP on the clusters of every view at
once (the views see more sides of the object than one) and kept when it explains the views at least
as well. Views are weighed by reliability: each by how well its own best registration explains it, so
a view no model pose explains (a splat artefact, a neighbour taken for the target) votes less.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from brave6d.core.transforms import invert
from brave6d.evaluation.agents.model import ModelCloud
from brave6d.evaluation.agents.perception import View
from brave6d.evaluation.agents.pointclouds import one_thread, point_cloud
from brave6d.evaluation.agents.registration import (
    Registration,
    RegistrationOptions,
    ViewScene,
    icp_rounds,
    register_scene,
    score_pose,
    view_scene,
    visible_points,
    voxel_size,
)

Array = NDArray[np.float64]
#: Another view's fit competes with the final view's own when the model's centroid lies within this
#: many model diameters under both (the same object, however each turned it).
SAME_PLACE_DIAMETERS = 0.5


def register_views(model: ModelCloud, views: Sequence[View], options: RegistrationOptions = RegistrationOptions(),
                   final: View | None = None) -> Registration | None:
    """The target's pose in the camera frame of ``final`` (default: the last of ``views``) from
    every view with a cluster, each candidate judged by its weighted mean score over all those
    views (:func:`view_weights`). With a cluster in the final view: its own registration (not
    redone when ``final`` is one of ``views``) or another view's that puts the model's centroid
    within ``SAME_PLACE_DIAMETERS`` of it, whichever has the best weighted mean (the own one on a
    tie), refined on all the views at once when that scores no worse. Without one: the views'
    registration with the best weighted mean. None when no view has a cluster."""
    found = [v for v in views if v.perception.cluster is not None]
    if not found:
        return None
    final_obs, final_seen = final if final is not None else views[-1]
    with one_thread():
        voxel = voxel_size(model, options)
        scenes = [view_scene(p.cluster, p.plane, p.min_height, o.depth, o.K, voxel, getattr(o, "rgb", None))
                  for o, p in found]
        cams_T_world = [invert(np.asarray(o.world_T_cam, dtype=np.float64)) for o, _ in found]
        regs = [register_scene(model, scene, options, voxel) for scene in scenes]
        weights = view_weights([r.score for r in regs])
        world_T_ref = np.asarray(final_obs.world_T_cam, dtype=np.float64)

        def mean_score(cam_T_obj: Array) -> float:  # a pose in the final view's frame
            world_T_obj = world_T_ref @ cam_T_obj
            return float(np.dot(weights, [score_pose(model, cam_T_world @ world_T_obj, scene, options.color_weight)[0]
                                          for scene, cam_T_world in zip(scenes, cams_T_world)]))

        refs_T_cam = [invert(world_T_ref) @ np.asarray(o.world_T_cam, dtype=np.float64) for o, _ in found]
        in_final = [ref_T_cam @ r.cam_T_obj for ref_T_cam, r in zip(refs_T_cam, regs)]
        # the final view is often one of the views (the agent went back to its start): reuse its work
        i_final = next((i for i, (_, p) in enumerate(found) if p is final_seen), None)
        if i_final is not None:
            own, cam_T_obj = regs[i_final], in_final[i_final]
        elif final_seen.cluster is not None:
            own = register_scene(model, view_scene(final_seen.cluster, final_seen.plane, final_seen.min_height,
                                                   final_obs.depth, final_obs.K, voxel, getattr(final_obs, "rgb", None)),
                                 options, voxel)
            cam_T_obj = own.cam_T_obj
        else:
            score, cam_T_obj, best = max(((mean_score(T), T, r) for T, r in zip(in_final, regs)), key=lambda c: c[0])
            return Registration(cam_T_obj, score, best.fitness, best.method, best.hypotheses)
        # The other views' fits that put the object where the final view sees it compete on how it
        # is turned: a nearer or side view may show what the final view cannot (a cup's handle a few
        # pixels wide); a fit elsewhere (a neighbour, an artefact) does not compete.
        near, centre = SAME_PLACE_DIAMETERS * model.diameter_m, model.points.mean(axis=0)
        rivals = [(T, r) for i, (T, r) in enumerate(zip(in_final, regs))
                  if i != i_final and _distance_of(centre, T, cam_T_obj) <= near]
        score, cam_T_obj, own = max([(mean_score(cam_T_obj), cam_T_obj, own)] +
                                    [(mean_score(T), T, r) for T, r in rivals], key=lambda c: c[0])
        if len(found) > 1:
            refined = multiview_icp(model, cam_T_obj, scenes, refs_T_cam, voxel)
            refined_score = mean_score(refined)
            if refined_score >= score:
                score, cam_T_obj = refined_score, refined
    return Registration(cam_T_obj, score, own.fitness, own.method, own.hypotheses)


def _distance_of(centre: Array, a_T_obj: Array, b_T_obj: Array) -> float:
    """Distance (m) between where two poses put the model-frame point ``centre``."""
    return float(np.linalg.norm((a_T_obj[:3, :3] - b_T_obj[:3, :3]) @ centre + a_T_obj[:3, 3] - b_T_obj[:3, 3]))


def view_weights(own_scores: Sequence[float]) -> Array:
    """Weights (summing to 1) of the views in :func:`register_views`'s mean score: each view by
    the score of its own best registration (clipped at 0, non-finite counts as 0); all alike if
    none is positive."""
    n = len(own_scores)
    w = np.clip(np.asarray(own_scores, dtype=np.float64), 0.0, None)
    w = np.where(np.isfinite(w), w, 0.0)
    top = float(w.max(initial=0.0))
    if not top > 0:
        return np.full(n, 1.0 / n)
    w = w / top  # first to at most 1: the sum of huge scores must not overflow
    return w / float(w.sum())


def multiview_icp(model: ModelCloud, ref_T_obj: Array, scenes: Sequence[ViewScene], refs_T_cam: Sequence[Array],
                  voxel: float) -> Array:
    """Point-to-plane ICP of every view's cluster at once, in the reference view's frame
    (``refs_T_cam``: each view's camera in that frame), onto the model points facing any of the
    views; the refined ``ref_T_obj``. Call it under :func:`one_thread` for reproducible sums."""
    pts = np.concatenate([sc.points @ T[:3, :3].T + T[:3, 3] for sc, T in zip(scenes, refs_T_cam)])
    source = point_cloud(pts).voxel_down_sample(0.5 * voxel)

    def facing_any(T: Array) -> NDArray[np.int64]:
        return np.unique(np.concatenate([visible_points(model, invert(ref_T_cam) @ T) for ref_T_cam in refs_T_cam]))

    return icp_rounds(model, ref_T_obj, source, facing_any, voxel)

"""training stage: 3DGS model, rasterizer backends, trainer, evaluation, PLY export.

Public API (imported lazily, so `import training` stays cheap: no torch / numba import).
Other stages (serve, evaluation) import only these names:

- training: ``train`` (in memory: loaded views + preset -> ``TrainedSplat``, with a ``HoldoutPoint`` per scoring), ``train_scene``
  (``brave6d train``: a scene directory -> ``splat/`` outputs, through ``train``), ``load_scene``
  (a scene's views, undistorted, with the holdout split), ``evaluate_holdout``;
- the holdout split (:mod:`brave6d.training.holdout`, no torch): ``read_holdout`` (the one reader of
  ``splat/holdout.json``, every stage's), ``write_holdout``, ``HoldoutSplit``, ``HeldOutView``,
  ``holdout_split`` (the rule);
- the training frame (:mod:`brave6d.training.scene_frame`): ``SceneFrame`` (the scene moved and scaled once so
  that training never sees its units) and ``serve_planes`` (the near/far planes a bundle of a scene is served
  with: its training's, in the scene's units);
- settings: ``Preset``, ``get_preset``, ``ANTIALIASING_MODES`` (``classic``, ``mip``), ``resolve_device`` (``auto``/``cpu``/``cuda`` -> torch device);
- training data in memory: ``TrainingData`` (a shared camera, train and holdout ``View`` lists) and ``View``
  (one frame: pose, image), what ``load_scene`` returns and ``train`` takes;
- captures made elsewhere (``brave6d import``): ``import_capture``, ``ImportOptions``, ``ImportResult``,
  ``read_source`` (a COLMAP model or a transforms.json as an ``ImportedCapture``), ``ScaleChoice``,
  ``UpChoice``; the pose sanity check run at import and at the start of training:
  ``check_camera_poses``, ``check_scene_poses``, ``PoseCheck``, ``PoseCheckError``;
- Gaussians: ``GaussianModel``, ``rasterize``, ``SplatData``, ``read_ply``, ``write_ply``, ``SH_C0``,
  ``sh_degree_for``, ``apply_filter_3d`` / ``compute_filter_3d`` (Mip-Splatting's 3D filter: what every
  renderer of a splat applies before ``rasterize``), ``write_viewer_ply`` / ``bake_filter_3d`` (the
  viewer PLY: that filter baked into scales and opacities, for viewers that ignore ``filter_3d``).

Repeatable: on the CPU, the same scene, preset and seed give a byte-identical ``point_cloud.ply``
(same Gaussians) on the same machine and install at the same thread count, COLMAP's initial points
included (seeded one-thread RANSAC, one-thread bundle adjustment), unless the time budget stops the
run; CUDA training is not (gsplat sums gradients with atomics). See docs/ARCHITECTURE.md section 5.
"""

from brave6d.core.lazy import lazy_exports

__all__ = ["ImportOptions", "ImportResult", "ImportedCapture", "PoseCheck", "PoseCheckError", "ScaleChoice",
           "TrainingData", "UpChoice", "View", "check_camera_poses", "check_scene_poses", "import_capture",
           "read_source",
           "ANTIALIASING_MODES", "SH_C0", "GaussianModel", "apply_filter_3d", "compute_filter_3d", "HeldOutView", "HoldoutPoint", "HoldoutSplit", "Preset", "SplatData", "TrainedSplat",
           "evaluate_holdout", "get_preset", "holdout_split", "load_scene", "rasterize", "read_holdout", "read_ply",
           "resolve_device", "sh_degree_for", "train", "train_scene", "write_holdout", "write_ply",
           "bake_filter_3d", "write_viewer_ply", "SceneFrame", "serve_planes"]

_LAZY = {
    "rasterize": ".rasterizer",
    "ANTIALIASING_MODES": ".presets",
    "apply_filter_3d": ".filter3d",
    "compute_filter_3d": ".filter3d",
    "train": ".training_run",
    "TrainedSplat": ".training_run",
    "HoldoutPoint": ".training_run",
    "train_scene": ".pipeline",
    "GaussianModel": ".model",
    "read_ply": ".ply",
    "write_ply": ".ply",
    "write_viewer_ply": ".ply",
    "bake_filter_3d": ".ply",
    "SplatData": ".ply",
    "SH_C0": ".ply",
    "sh_degree_for": ".ply",
    "holdout_split": ".holdout",
    "read_holdout": ".holdout",
    "write_holdout": ".holdout",
    "HoldoutSplit": ".holdout",
    "HeldOutView": ".holdout",
    "load_scene": ".views",
    "TrainingData": ".views",
    "View": ".views",
    "import_capture": ".importing.importer",
    "ImportOptions": ".importing.importer",
    "ImportResult": ".importing.importer",
    "read_source": ".importing.importer",
    "ImportedCapture": ".importing.source",
    "ScaleChoice": ".importing.world",
    "UpChoice": ".importing.world",
    "check_camera_poses": ".pose_check",
    "PoseCheck": ".pose_check",
    "PoseCheckError": ".pose_check",
    "check_scene_poses": ".scene_pose_check",
    "evaluate_holdout": ".holdout_eval",
    "Preset": ".presets",
    "get_preset": ".presets",
    "resolve_device": ".device",
    "SceneFrame": ".scene_frame",
    "serve_planes": ".scene_frame",
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

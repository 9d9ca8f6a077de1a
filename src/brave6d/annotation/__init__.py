"""Annotation stage: 3D-DAT import and BOP ground-truth export; the owner of the BOP dataset format.

Public API (imported lazily, so ``import annotation`` stays cheap: no Open3D or trimesh until a
name is used). Other stages import only these names:

- 3D-DAT import: ``import_threedat``, ``import_summary``, ``ImportResult``, ``read_threedat``,
  ``write_threedat_folder``, ``ThreeDatError``, ``AlignmentOptions``, ``AlignmentError``;
- the scene's annotation (``objects.json``, one reader and one writer for every stage):
  ``load_annotation``, ``write_annotation``, ``Annotation``, ``AnnotatedObject``, ``AnnotatedInstance``,
  ``ContinuousSymmetry``;
- BOP export: ``export_bop``, ``export_summary``, ``BopExportOptions``, ``BopExportResult``;
- the BOP dataset format (:mod:`brave6d.annotation.bop_format`, the one reader of BOP files in the
  project): ``BopLayout``, ``read_scene_camera``, ``read_scene_gt``, ``read_scene_gt_info``,
  ``read_models_info``, ``model_file``, ``dataset_image_size``, ``bop_cam_K``, ``dump_bop_json``,
  ``SceneCamera``, ``GtPose``, ``GtInfo``; a split's images for training and estimation
  (:mod:`brave6d.annotation.bop_split`: JPEG or PNG ``rgb/``, depth in mm by each image's ``depth_scale``):
  ``read_bop_split``, ``read_split_scene``, ``SplitImage``, ``read_split_rgb``, ``read_depth_mm``, ``find_rgb_file``, ``split_scene_folders``,
  ``RGB_SUFFIXES`` (the colour image suffixes ``rgb/`` may hold); a test split without ground truth through its
  targets file: ``read_test_targets`` (``test_targets_bop19.json``), ``read_split_targets``; a scene's masks as
  COCO annotations (``scene_gt_coco.json``, :mod:`brave6d.annotation.bop_coco`): ``scene_gt_coco``,
  ``read_scene_gt_coco``, ``mask_to_rle``, ``rle_to_mask``, ``COCO_FILE``;
- meshes: ``read_ply_mesh``, ``write_ply_mesh``, ``MeshData`` (:mod:`brave6d.annotation.ply_mesh`, the one
  reader and writer of mesh PLY files), ``load_mesh`` (any mesh format, PLY through that reader),
  ``model_diameter`` (largest point distance, the BOP ``diameter``), ``write_bop_models`` (a BOP models
  folder of an object library: PLY in mm and ``models_info.json``);
- silhouettes by ray casting (BOP masks and the server's visible fractions): ``SilhouetteCaster``,
  ``Silhouette``, ``bbox_xywh``;
- checks and test scenes: ``mask_iou_against_sim_truth``, ``make_synthetic_scene``.

The modules behind them, one job each: ``threedat`` (read a 3D-DAT folder), ``threedat_writer``
(write one: the demo's "human annotator"), ``alignment`` (rigid alignment of camera poses),
``pairing`` (3D-DAT camera lines <-> captured views), ``importer``, ``store`` (``objects.json``),
``ply_mesh`` (mesh PLY files), ``models`` (meshes, BOP PLY models in mm, ``models_info``
entries), ``visibility`` (masks by ray casting), ``bop`` (the export), ``bop_format``, ``staging``
(hard links), ``validation`` (mask IoU against the simulator), ``cli`` (``brave6d annotate``),
``demo``, ``synthetic``.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "import_threedat": ".importer", "import_summary": ".importer", "ImportResult": ".importer",
    "read_threedat": ".threedat", "ThreeDatError": ".threedat", "write_threedat_folder": ".threedat_writer",
    "AlignmentOptions": ".alignment", "AlignmentError": ".alignment",
    "load_annotation": ".store", "write_annotation": ".store", "Annotation": ".store",
    "AnnotatedObject": ".store", "AnnotatedInstance": ".store", "ContinuousSymmetry": ".threedat",
    "export_bop": ".bop", "export_summary": ".bop", "BopExportOptions": ".bop", "BopExportResult": ".bop",
    "BopLayout": ".bop_format", "read_scene_camera": ".bop_format", "read_scene_gt": ".bop_format",
    "read_scene_gt_info": ".bop_format", "read_models_info": ".bop_format", "model_file": ".bop_format",
    "dataset_image_size": ".bop_format", "bop_cam_K": ".bop_format", "dump_bop_json": ".bop_format",
    "SceneCamera": ".bop_format", "BOP19_MIN_VISIB_FRACT": ".bop_format", "GtPose": ".bop_format", "GtInfo": ".bop_format",
    "read_bop_split": ".bop_split", "read_split_scene": ".bop_split", "SplitImage": ".bop_split",
    "read_split_rgb": ".bop_split", "read_depth_mm": ".bop_split", "find_rgb_file": ".bop_split",
    "split_scene_folders": ".bop_split", "RGB_SUFFIXES": ".bop_split", "read_split_targets": ".bop_split",
    "read_test_targets": ".bop_format",
    "scene_gt_coco": ".bop_coco", "read_scene_gt_coco": ".bop_coco", "mask_to_rle": ".bop_coco",
    "rle_to_mask": ".bop_coco", "COCO_FILE": ".bop_coco",
    "read_ply_mesh": ".ply_mesh", "write_ply_mesh": ".ply_mesh", "MeshData": ".ply_mesh", "load_mesh": ".models",
    "SilhouetteCaster": ".visibility", "Silhouette": ".visibility", "bbox_xywh": ".visibility",
    "model_diameter": ".models", "write_bop_models": ".models", "mask_iou_against_sim_truth": ".validation", "make_synthetic_scene": ".toy_scene",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

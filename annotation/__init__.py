"""Annotation stage: 3D-DAT import and BOP ground-truth export.

Modules (each with one job; import them directly, this package imports nothing heavy):

- :mod:`annotation.threedat`: read a 3D-DAT folder into typed objects (errors name file + entry).
- :mod:`annotation.threedat_writer`: write a 3D-DAT folder (the demo's "human annotator").
- :mod:`annotation.alignment`: rigid alignment of two sets of camera poses, residuals, refusal.
- :mod:`annotation.pairing`: 3D-DAT camera-pose lines <-> captured views (3D-DAT's image order).
- :mod:`annotation.importer`: ``import_threedat(dat_dir, scene_dir)`` -> ``<scene>/annotation/``.
- :mod:`annotation.store`: ``objects.json`` (obj_id map, world poses, meshes) read/write.
- :mod:`annotation.models`: meshes, BOP PLY models in mm, ``models_info`` entries.
- :mod:`annotation.visibility`: object masks by ray casting (Open3D).
- :mod:`annotation.bop`: ``export_bop(scene_dir)`` -> ``<scene>/annotation/bop/``.
- :mod:`annotation.bop_format`: BOP layout and typed readers (for evaluation).
- :mod:`annotation.validation`: mask IoU against the simulator's object-id buffers (tests).
- :mod:`annotation.cli`: ``brave6d annotate import-3ddat | export-bop``.
- :mod:`annotation.demo`: the demo's 3D-DAT writer and pipeline stage.
"""

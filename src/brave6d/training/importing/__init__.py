"""Importing a capture made elsewhere (``brave6d import``): a COLMAP model or a nerfstudio /
instant-ngp ``transforms.json`` with its images -> a scene directory that ``train``, ``export`` and
``serve`` use as if the project had captured it.

One job per module: :mod:`.source` (the in-memory capture and the camera conventions),
:mod:`.colmap_source` and :mod:`.transforms_source` (the two readers), :mod:`.image_io` (decoding,
EXIF orientation, resampling), :mod:`.world` (metric scale, up, centre), :mod:`.scene_files`
(``capture/import.json``, ``capture/imported_points.ply``), :mod:`.importer` (the whole import).
The public names are ``brave6d.training``'s (``import_capture``, ``ImportOptions``, ...).
"""

"""The demo's annotation stage: play the human annotator, then import and export like a lab would.

:func:`write_demo_threedat` is the ONLY place where the simulator's true object poses (the
spec's ``objects``) are read: it writes them as a 3D-DAT folder, exactly the files a lab gets
from the tool, with the CAPTURED camera poses (robot-reported, calibrated hand-eye) and the
undistorted images. Everything downstream reads that folder through the importer.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from brave6d.annotation.threedat import ContinuousSymmetry, LibraryEntry
from brave6d.annotation.threedat_writer import write_threedat_folder
from brave6d.core.calibration_io import camera_poses
from brave6d.core.layout import SceneDir
from brave6d.core.undistort import ensure_undistorted

if TYPE_CHECKING:
    from brave6d.core.run_context import RunContext
    from brave6d.core.progress import StageResult


def write_demo_threedat(scene_dir: Path | str, out_dir: Path | str, with_images: bool = True) -> Path:
    """Write the demo's truth as a 3D-DAT folder; returns its ``dataset.yaml``.

    Library ids are the spec object names; object poses are the spec poses (world = robot base);
    camera poses are ``camera_poses(scene)`` keyed by frame index; ``camera.yaml`` is the
    undistorted calibrated camera; ``with_images`` hard-links the undistorted frames.
    """
    scene = SceneDir(scene_dir)
    spec = scene.load_spec()
    frames = ensure_undistorted(scene)
    instances = []
    for obj in spec.objects:
        sym = obj.symmetry
        entry = LibraryEntry(
            id=obj.name, mesh=spec.resolve(obj.mesh).resolve(), scale=obj.scale, name=obj.name,
            class_name=obj.category.value, description=obj.description or None,
            symmetries_discrete=tuple(np.reshape(m, (4, 4)) for m in sym.discrete) if sym else (),
            symmetries_continuous=tuple(ContinuousSymmetry(tuple(a)) for a in sym.continuous_axes) if sym else (),
        )
        instances.append((entry, obj.pose.matrix()))
    poses = {record.index: world_T_cam for record, world_T_cam in camera_poses(scene)}
    images = None
    if with_images:
        images = {r.index: (frames.rgb_path(r), frames.depth_path(r)) for r in frames.records}
    return write_threedat_folder(out_dir, spec.name, instances, frames.camera, poses, images=images,
                                 camera_name=spec.camera.model)


def stage_annotation(ctx: RunContext) -> StageResult:
    """Pipeline stage on the simulated rig: write the 3D-DAT folder, import it, export BOP; figures
    for the summary table. A real capture has no true poses to write: a person annotates it in
    3D-DAT and imports it (``brave6d annotate import-3ddat``), so a real rig is refused."""
    from brave6d.annotation.bop import export_bop
    from brave6d.annotation.importer import import_threedat
    from brave6d.annotation.validation import mask_iou_against_sim_truth
    from brave6d.core.errors import BraveError
    from brave6d.core.progress import StageResult

    if not ctx.rig.simulated:
        raise BraveError(f"{ctx.scene.root}: the annotate stage writes the simulator's true poses, and a capture "
                         f"with {ctx.rig} has none; annotate it in 3D-DAT and import it with "
                         f"'brave6d annotate import-3ddat DAT_DIR {ctx.scene.root}'")

    dat_dir = ctx.workdir / "threedat"
    write_demo_threedat(ctx.scene.root, dat_dir)
    imported = import_threedat(dat_dir, ctx.scene.root, obj_ids=ctx.obj_ids)  # None: the scene's own ids
    exported = export_bop(ctx.scene.root)
    figures = {
        "objects": imported.n_objects,
        "instances": imported.n_instances,
        "views": exported.images,
        "align rms mm": imported.alignment.rms_mm,
        "targets": exported.targets,
        "mean visib": exported.mean_visib_fract,
    }
    if ctx.scene.capture.sim_object_ids_dir.is_dir():
        # a check of the export against the simulator's id buffers; nothing downstream reads them
        check = mask_iou_against_sim_truth(ctx.scene.root)
        figures["mask IoU vs sim (mean/min)"] = f"{check['mean_iou']:.3f}/{check['min_iou']:.3f}"
    return StageResult("annotation", figures=figures)

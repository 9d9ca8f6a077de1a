"""``brave6d annotate``: ``import-3ddat DAT_DIR SCENE_DIR`` and ``export-bop SCENE_DIR``."""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.annotation.alignment import AlignmentOptions


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    imp = sub.add_parser("import-3ddat", help="import 3D-DAT object poses into SCENE_DIR/annotation/",
                         description="Read a 3D-DAT folder (dataset config, object library, poses.yaml, camera.yaml, "
                         "groundtruth_handeye.txt), align its world frame to the robot base frame using the matching "
                         "camera poses, and write SCENE_DIR/annotation/objects.json with stable BOP obj_ids.")
    imp.add_argument("dat_dir", type=Path, help="3D-DAT folder (or its dataset config file)")
    imp.add_argument("scene_dir", type=Path, help="captured and calibrated scene directory")
    imp.add_argument("--scene", default=None, help="3D-DAT scene id (needed when the folder holds several)")
    imp.add_argument("--dataset", type=Path, default=None, metavar="DATASET.yaml",
                     help="take the obj_ids from this dataset's object library (3D-DAT object ids = library names), "
                          "so that an object keeps one obj_id in every scene of the dataset")
    defaults = AlignmentOptions()
    imp.add_argument("--max-rms-mm", type=float, default=defaults.max_rms_mm,
                     help="refuse when the camera-pose alignment residual RMS exceeds this "
                     f"(default {defaults.max_rms_mm})")
    imp.add_argument("--max-rms-deg", type=float, default=defaults.max_rms_deg,
                     help=f"same for the rotation residual in degrees (default {defaults.max_rms_deg})")
    exp = sub.add_parser("export-bop", help="write SCENE_DIR/annotation/bop/ (BOP ground truth for every view)",
                         description="Per captured view: scene_camera.json, scene_gt.json, scene_gt_info.json, "
                         "mask/, mask_visib/, undistorted rgb/ and depth/, plus models/ in mm with models_info.json.")
    exp.add_argument("scene_dir", type=Path, help="scene directory with an imported annotation")
    exp.add_argument("--split", default="test", help="BOP split folder name (default: test)")
    exp.add_argument("--scene-id", type=int, default=1, help="BOP scene id (default: 1)")
    exp.add_argument("--copy-images", action="store_true", help="copy rgb/depth instead of hard-linking them")
    exp.add_argument("--no-static", action="store_true",
                     help="ignore the spec's static meshes as occluders (objects still occlude each other)")


def run(args: argparse.Namespace) -> int:
    if args.action == "import-3ddat":
        from brave6d.annotation.importer import import_threedat, import_summary

        options = AlignmentOptions(max_rms_mm=args.max_rms_mm, max_rms_deg=args.max_rms_deg)
        obj_ids = None
        if args.dataset is not None:
            from brave6d.core.dataset_spec import parse_dataset_spec
            from brave6d.core.errors import SpecError
            from brave6d.core.yaml_io import read_yaml

            # only the library's order is needed: its names are checked, its meshes are not read
            obj_ids = parse_dataset_spec(read_yaml(args.dataset, error=SpecError), args.dataset).obj_ids()
        result = import_threedat(args.dat_dir, args.scene_dir, args.scene, options, obj_ids=obj_ids)
        print(result.alignment.summary())
        for warning in result.warnings:
            print(f"warning: {warning}")
        figures = ", ".join(f"{k}={v}" for k, v in import_summary(result).items())
        print(f"imported {result.n_instances} instances of {result.n_objects} objects into "
              f"{Path(args.scene_dir) / 'annotation'} ({figures})")
        return 0
    if args.action == "export-bop":
        from brave6d.annotation.bop import BopExportOptions, export_bop, export_summary

        result = export_bop(args.scene_dir, BopExportOptions(split=args.split, scene_id=args.scene_id,
                                                             copy_images=args.copy_images,
                                                             include_static=not args.no_static))
        figures = ", ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}"
                            for k, v in export_summary(result).items())
        print(f"wrote {result.layout.root} ({figures})")
        return 0
    raise AssertionError(f"unknown action {args.action!r}")

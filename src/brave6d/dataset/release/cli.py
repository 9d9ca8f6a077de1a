"""``brave6d release``: ``build WORKDIR OUT [--force]`` and ``verify OUT``."""

from __future__ import annotations

import argparse
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    build = sub.add_parser("build", help="package a dataset work directory as a BOP-style release",
                           description="Write OUT: <name>_base.zip (dataset_info.json, camera.json, BOP19 targets), "
                           "<name>_models.zip (models in mm, models_info.json), <name>_test_all.zip (every scene's "
                           "BOP ground truth and images; holdout views in test/XXXXXX/holdout.json), one "
                           "render-server bundle zip per scene, manifest.json, a dataset card README.md and "
                           "SHA256SUMS; <name>_train_pbr.zip when WORKDIR/synth/train_pbr exists and "
                           "<name>_learned.zip (learned/model.pt and its card) when WORKDIR/learned/model does, and the ROS 2 "
                           "interfaces wheel for agents (brave6d_ros2_interfaces-*.whl) when $BRAVE6D_ROS2_PYTHON (or "
                           "this Python) has the ROS 2 wheels. Files are streamed into the zips; OUT appears only when complete.")
    build.add_argument("workdir", type=Path, help="dataset work directory (dataset.yaml, scenes/)")
    build.add_argument("out", type=Path, help="release folder to write (absent or empty)")
    build.add_argument("--force", action="store_true",
                       help="move a non-empty OUT aside (to OUT.old-<time>; nothing is deleted)")
    verify = sub.add_parser("verify", help="check a release folder: checksums, zips, JSON, views, ids, bundles",
                            description="Recompute every checksum in SHA256SUMS, test every zip's CRCs, validate "
                            "every JSON file, check that every referenced view exists, that object ids agree across "
                            "scenes, models and the library, and that each bundle loads. Exit status 2 names the "
                            "first problem.")
    verify.add_argument("out", type=Path, help="release folder (as written by 'brave6d release build')")


def run(args: argparse.Namespace) -> int:
    if args.action == "build":
        from brave6d.dataset.release.build import build_release

        result = build_release(args.workdir, args.out, force=args.force)
        if result.moved_aside is not None:
            print(f"moved the previous {args.out} aside to {result.moved_aside}")
        print(f"wrote {result.root}: {result.scenes} scenes, {result.images} images, {len(result.sizes)} files, "
              f"{result.total_bytes / 1e6:.1f} MB")
        for wheel in sorted(n for n in result.sizes if n.endswith(".whl")):
            print(f"agents: pip install {result.root / wheel} (ROS 2 interfaces, docs/ROS.md)")
        return 0
    if args.action == "verify":
        from brave6d.dataset.release.verify import verify_release

        report = verify_release(args.out)
        print(f"{report.root}: OK ({report.files} files, {report.bytes / 1e6:.1f} MB, {report.scenes} scenes, "
              f"{report.images} images, {report.bundles} bundles"
              + (f", {report.train_pbr_images} synthetic training images" if report.train_pbr_images else "")
              + (f", learned model ({report.learned_model})" if report.learned_model else "")
              + (f", ROS 2 interfaces wheel {report.ros2_interfaces}" if report.ros2_interfaces else "") + ")")
        return 0
    raise AssertionError(f"unknown action {args.action!r}")

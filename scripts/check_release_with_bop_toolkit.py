"""Read a BRAVE-6D release with bop_toolkit's own readers (``bop_toolkit_lib.inout``).

bop_toolkit is not on PyPI and pins numpy<2, so it cannot be a dependency of this project: this
script unzips the release's BOP zips into a temporary folder with the project's safe unpacker
(``brave6d.dataset.release.zips``: a release is untrusted, so member names and sizes are checked before
anything is written), makes (once) a separate virtualenv with bop_toolkit's reader dependencies,
re-runs itself there on the unzipped folder and reads every file with bop_toolkit's functions,
checking what BOP's conventions promise (paths from its dataset_params templates, image sizes,
ids, masks). The part that runs in that virtualenv imports nothing from brave6d.

    python scripts/check_release_with_bop_toolkit.py RELEASE_DIR --bop-toolkit PATH/TO/bop_toolkit
        [--venv .venv-bop-toolkit]

Exit status 0 when every file reads and every check holds; otherwise 1 and the first problem.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

READER_DEPS = ["numpy<2", "scipy", "imageio", "pypng", "pillow"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("release", type=Path, help="a folder written by 'brave6d release build'")
    parser.add_argument("--bop-toolkit", type=Path, required=True, help="a checkout of github.com/thodan/bop_toolkit")
    parser.add_argument("--venv", type=Path, default=Path(".venv-bop-toolkit"), help="where the virtualenv goes")
    args = parser.parse_args()
    if os.environ.get("BRAVE6D_BOP_CHECK_INSIDE") == "1":
        sys.path.insert(0, str(args.bop_toolkit.resolve()))
        try:
            return check(Path(os.environ["BRAVE6D_BOP_DATASET"]))
        except (OSError, KeyError, ValueError) as exc:  # a file bop_toolkit cannot read
            return _fail(f"{type(exc).__name__}: {exc}")
    with tempfile.TemporaryDirectory() as tmp:
        try:
            base = unpack_release(args.release, Path(tmp))
        except ValueError as exc:  # the project's DataError (a ValueError): a zip refused, naming the member
            return _fail(str(exc))
        return _rerun_in_venv(args, base)


def unpack_release(release: Path, dest: Path) -> Path:
    """BOP's own instructions, with the project's safe unpacker: unzip ``<name>_base.zip`` into
    ``dest``, then the models and test zips into the ``<name>/`` folder it made; returns that folder."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from brave6d.dataset.release.zips import open_zip

    bases = sorted(release.glob("*_base.zip"))
    if len(bases) != 1:
        raise ValueError(f"{release}: expected one *_base.zip, found {len(bases)}")
    dest.mkdir(parents=True, exist_ok=True)
    with open_zip(bases[0]) as zf:
        zf.extract(dest)
    cameras = sorted(dest.rglob("camera.json"))
    if not cameras:
        raise ValueError(f"{bases[0].name}: no camera.json")
    base = cameras[0].parent
    for archive in [*sorted(release.glob("*_models.zip")), *sorted(release.glob("*_test_*.zip"))]:
        with open_zip(archive) as zf:
            zf.extract(base)
    return base


def _rerun_in_venv(args: argparse.Namespace, base: Path) -> int:
    python = args.venv / "bin" / "python"
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(args.venv)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "-q", *READER_DEPS], check=True)
    env = {**os.environ, "BRAVE6D_BOP_CHECK_INSIDE": "1", "BRAVE6D_BOP_DATASET": str(base)}
    return subprocess.run([str(python), *sys.argv], env=env).returncode


def check(base: Path) -> int:
    """Read everything under the dataset folder ``base`` with bop_toolkit_lib.inout."""
    import numpy as np
    from bop_toolkit_lib import inout

    cam = inout.load_cam_params(base / "camera.json")
    width, height = cam["im_size"]
    models_info = inout.load_json(base / "models" / "models_info.json", keys_to_int=True)
    for obj_id, info in models_info.items():
        model = inout.load_ply(base / "models" / f"obj_{obj_id:06d}.ply")
        extent = model["pts"].max(axis=0) - model["pts"].min(axis=0)
        if len(model["pts"]) == 0 or not 0 < info["diameter"] < 10 * float(np.linalg.norm(extent)) + 1e-9:
            return _fail(f"model {obj_id}: {len(model['pts'])} points, diameter {info['diameter']} vs extent {extent}")
    targets = inout.load_json(base / "test_targets_bop19.json")
    split = base / "test"
    scene_dirs = sorted(p for p in split.iterdir() if p.is_dir())
    counts = {"scenes": 0, "images": 0, "images without depth": 0, "instances": 0, "targets": len(targets)}
    gt_objects: dict[tuple[int, int], list[int]] = {}
    for scene_dir in scene_dirs:
        scene_id = int(scene_dir.name)
        # bop_toolkit's dataset_params path templates for the classic BOP layout
        tpath = {k: str(split / "{scene_id:06d}" / v) for k, v in {
            "rgb": "rgb/{im_id:06d}.png", "depth": "depth/{im_id:06d}.png",
            "mask": "mask/{im_id:06d}_{gt_id:06d}.png", "mask_visib": "mask_visib/{im_id:06d}_{gt_id:06d}.png"}.items()}
        scene_camera = inout.load_scene_camera(scene_dir / "scene_camera.json")
        scene_gt = inout.load_scene_gt(scene_dir / "scene_gt.json")
        scene_gt_info = inout.load_json(scene_dir / "scene_gt_info.json", keys_to_int=True)
        if set(scene_gt) != set(scene_camera) or set(scene_gt) != set(scene_gt_info):
            return _fail(f"scene {scene_id}: scene_gt, scene_camera and scene_gt_info list different images")
        for im_id, gts in scene_gt.items():
            K = scene_camera[im_id]["cam_K"]
            if K.shape != (3, 3) or not np.all(np.isfinite(K)):
                return _fail(f"scene {scene_id} image {im_id}: cam_K {K}")
            rgb = inout.load_im(tpath["rgb"].format(scene_id=scene_id, im_id=im_id))
            depth_path = Path(tpath["depth"].format(scene_id=scene_id, im_id=im_id))
            depth = inout.load_depth(depth_path) if (scene_dir / "depth").is_dir() else np.zeros((height, width))
            counts["images without depth"] += not (scene_dir / "depth").is_dir()
            if rgb.shape[:2] != (height, width) or depth.shape != (height, width):
                return _fail(f"scene {scene_id} image {im_id}: rgb {rgb.shape}, depth {depth.shape}, camera {width}x{height}")
            if len(scene_gt_info[im_id]) != len(gts):
                return _fail(f"scene {scene_id} image {im_id}: {len(gts)} GT poses, {len(scene_gt_info[im_id])} GT infos")
            for gt_id, (gt, info) in enumerate(zip(gts, scene_gt_info[im_id])):
                if gt["obj_id"] not in models_info:
                    return _fail(f"scene {scene_id} image {im_id} instance {gt_id}: obj_id {gt['obj_id']} has no model")
                if gt["cam_R_m2c"].shape != (3, 3) or gt["cam_t_m2c"].shape != (3, 1):
                    return _fail(f"scene {scene_id} image {im_id} instance {gt_id}: pose shapes")
                for kind in ("mask", "mask_visib"):
                    mask = inout.load_im(tpath[kind].format(scene_id=scene_id, im_id=im_id, gt_id=gt_id))
                    if mask.shape != (height, width):
                        return _fail(f"scene {scene_id} image {im_id} instance {gt_id}: {kind} {mask.shape}")
                if not 0.0 <= info["visib_fract"] <= 1.0:
                    return _fail(f"scene {scene_id} image {im_id} instance {gt_id}: visib_fract {info['visib_fract']}")
                counts["instances"] += 1
            gt_objects[(scene_id, im_id)] = [g["obj_id"] for g in gts]
            counts["images"] += 1
        counts["scenes"] += 1
    for t in targets:
        objs = gt_objects.get((t["scene_id"], t["im_id"]))
        if objs is None or objs.count(t["obj_id"]) < t["inst_count"]:
            return _fail(f"test target {t} does not match scene_gt")
    print("bop_toolkit read the release: " + ", ".join(f"{v} {k}" for k, v in counts.items())
          + f", {len(models_info)} models, camera {width}x{height}")
    return 0


def _fail(message: str) -> int:
    print(f"bop_toolkit check failed: {message}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())

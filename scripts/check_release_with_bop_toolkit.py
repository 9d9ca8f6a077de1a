"""Read a BRAVE-6D release with bop_toolkit's own readers (``bop_toolkit_lib.inout``), or
evaluate a BOP results CSV with bop_toolkit's own evaluation scripts and check it equals brave6d's.

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

    python scripts/check_release_with_bop_toolkit.py --results RESULTS.csv --split SPLIT_DIR
        --models MODELS_DIR --bop-toolkit PATH/TO/bop_toolkit [--venv .venv-bop-toolkit]

evaluates RESULTS.csv (``brave6d learn bop-results``, ``brave6d estimate bop``) on a BOP split
(its scene folders, ground truth and depth) with bop_toolkit's ``scripts/eval_calc_errors.py`` and
``scripts/eval_calc_scores.py``, run with exactly the settings its ``eval_bop19_pose.py`` passes
them (VSD delta 15 mm, taus and thresholds 0.05..0.5, MSSD 0.05..0.5 x diameter, MSPD 5..50 px
x 640 / width, ``n_top`` -1, ``max_sym_disc_step`` 0.01, ``visib_gt_min`` -1, the vispy renderer on
EGL: Mesa's software renderer without a display, ``EGL_PLATFORM=surfaceless``), the targets
BOP19's (instances at least 10 % visible, as its ``enumerate_test_targets.py``). eval_bop19_pose.py
itself is not run because it knows VSD's delta only for BOP's own dataset names; its loop over the
two scripts is repeated here. bop_toolkit's ``dataset_params`` also knows only its own datasets,
so the split is laid out as a dataset named ``brave6d`` (``test/`` linking to the split,
``models_eval/`` to the models) and ``dataset_params`` is told its objects, scenes and image size
before each script runs. Prints bop_toolkit's AR, AR_VSD, AR_MSSD, AR_MSPD beside brave6d's own
scoring of the same CSV (``brave6d.evaluation.metrics.evaluate_bop19``); exit status 0 when every
figure agrees to ``--tolerance`` (1e-6). MSSD and MSPD need no rendering and agree exactly; VSD
compares renders, which agree as well: brave6d's VSD renderer follows the OpenGL rules
bop_toolkit's vispy renderer meets on Mesa's llvmpipe (``brave6d.evaluation.metrics.gl_raster``:
the same pixels and depths; docs/BENCHMARKS.md gives the measurement).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

READER_DEPS = ["numpy<2", "scipy", "imageio", "pypng", "pillow"]
#: What the evaluation scripts need besides (the vispy renderer, through PyOpenGL on EGL).
EVAL_DEPS = ["vispy", "PyOpenGL"]
DATASET = "brave6d"
AGREEMENT = 1e-6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("release", type=Path, nargs="?", help="a folder written by 'brave6d release build'")
    parser.add_argument("--results", type=Path, help="a BOP results CSV to evaluate (instead of a release)")
    parser.add_argument("--split", type=Path, help="with --results: the BOP split folder it was estimated on")
    parser.add_argument("--models", type=Path, help="with --results: the BOP models folder (mm)")
    parser.add_argument("--tolerance", type=float, default=AGREEMENT,
                        help="with --results: the largest difference of an AR accepted (default %(default)g)")
    parser.add_argument("--bop-toolkit", type=Path, required=True, help="a checkout of github.com/thodan/bop_toolkit")
    parser.add_argument("--venv", type=Path, default=Path(".venv-bop-toolkit"), help="where the virtualenv goes")
    args = parser.parse_args()
    if (args.release is None) == (args.results is None) or (args.results is not None and not (args.split and args.models)):
        parser.error("give RELEASE, or --results with --split and --models")
    if os.environ.get("BRAVE6D_BOP_CHECK_INSIDE") == "1":
        sys.path.insert(0, str(args.bop_toolkit.resolve()))
        try:
            if args.results is not None:
                return evaluate_inside(Path(os.environ["BRAVE6D_BOP_DATASET"]), args.bop_toolkit.resolve(),
                                       json.loads(os.environ["BRAVE6D_BOP_OURS"]), args.tolerance)
            return check(Path(os.environ["BRAVE6D_BOP_DATASET"]))
        except (OSError, KeyError, ValueError) as exc:  # a file bop_toolkit cannot read
            return _fail(f"{type(exc).__name__}: {exc}")
    if args.results is not None:
        with tempfile.TemporaryDirectory() as tmp:
            try:
                ours = brave6d_scores(args.results, args.split, args.models)
                datasets = lay_out_dataset(args.results, args.split, args.models, Path(tmp))
            except ValueError as exc:  # the project's DataError: a CSV or split it refuses
                return _fail(str(exc))
            return _rerun_in_venv(args, datasets, {"BRAVE6D_BOP_OURS": json.dumps(ours)}, EVAL_DEPS)
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


def _rerun_in_venv(args: argparse.Namespace, base: Path, env_extra: dict[str, str] | None = None,
                   extra_deps: list[str] | None = None) -> int:
    python = args.venv / "bin" / "python"
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(args.venv)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "-q", *READER_DEPS], check=True)
    if extra_deps and subprocess.run([str(python), "-c", "import vispy, OpenGL"], capture_output=True).returncode:
        subprocess.run([str(python), "-m", "pip", "install", "-q", *extra_deps], check=True)
    env = {**os.environ, "BRAVE6D_BOP_CHECK_INSIDE": "1", "BRAVE6D_BOP_DATASET": str(base), **(env_extra or {})}
    return subprocess.run([str(python), *sys.argv], env=env).returncode


# ----------------------------------------------------------------------------- results: outside the venv
def brave6d_scores(results: Path, split: Path, models: Path) -> dict[str, float]:
    """brave6d's BOP19 figures of ``results`` on ``split`` (every GT instance of every scene folder)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "src"))
    from brave6d.evaluation.estimate_bop import scene_folders
    from brave6d.evaluation.metrics import evaluate_bop19, load_models, load_scene_gt_instances, read_bop_results

    gts = [g for s in scene_folders(split) for g in load_scene_gt_instances(s)]
    scores = evaluate_bop19(gts, read_bop_results(results), load_models(models, sorted({g.obj_id for g in gts})))
    return {"ar": float(scores.ar), "vsd": float(scores.ar_vsd), "mssd": float(scores.ar_mssd),
            "mspd": float(scores.ar_mspd), "targets": int(scores.n_targets)}


def lay_out_dataset(results: Path, split: Path, models: Path, dest: Path) -> Path:
    """``dest/datasets/brave6d/{test -> split, models_eval -> models}`` and the CSV under
    ``dest/results`` with the name bop_toolkit parses (method, dataset, split); returns ``dest``."""
    root = dest / "datasets" / DATASET
    root.mkdir(parents=True)
    (root / "test").symlink_to(split.resolve(), target_is_directory=True)
    (root / "models_eval").symlink_to(models.resolve(), target_is_directory=True)
    (dest / "results").mkdir()
    (dest / "results" / f"brave6d_{DATASET}-test.csv").write_bytes(results.read_bytes())
    return dest


# ----------------------------------------------------------------------------- results: inside the venv
#: eval_bop19_pose.py's settings (BOP19: 6D localisation, n_top -1), its taus and thresholds made
#: as it makes them (np.arange: the same floats, the same text on the scripts' command lines).
VSD_DELTA = 15


def _bop19_thresholds() -> tuple[list[float], dict[str, list[float]]]:
    import numpy as np

    taus = list(np.arange(0.05, 0.51, 0.05))
    return taus, {"vsd": taus, "mssd": list(np.arange(0.05, 0.51, 0.05)), "mspd": list(np.arange(5, 51, 5))}


def register_dataset(base: Path) -> None:
    """Tell bop_toolkit's dataset_params the dataset at ``base/datasets/brave6d`` (it knows only BOP's
    own): its parameters are those of a classic BOP dataset (LM's branch) with this one's objects,
    scenes, image size and paths."""
    import glob

    from bop_toolkit_lib import dataset_params, inout

    root = str(base / "datasets" / DATASET)
    split_orig, model_orig = dataset_params.get_split_params, dataset_params.get_model_params

    def swap(value: object, datasets_path: str) -> object:
        lm = os.path.join(datasets_path, "lm")
        return root + value[len(lm):] if isinstance(value, str) and value.startswith(lm) else value

    def get_split_params(datasets_path, dataset_name, split, split_type=None):  # type: ignore[no-untyped-def]
        if dataset_name != DATASET:
            return split_orig(datasets_path, dataset_name, split, split_type)
        p = {k: swap(v, datasets_path) for k, v in split_orig(datasets_path, "lm", split, split_type).items()}
        scenes = sorted(int(os.path.basename(d)) for d in glob.glob(os.path.join(root, split, "[0-9]" * 6)))
        first = sorted(glob.glob(os.path.join(root, split, f"{scenes[0]:06d}", "depth", "*.png")))[0]
        height, width = inout.load_depth(first).shape
        p.update(name=DATASET, scene_ids=scenes, im_size=(width, height), depth_range=None, azimuth_range=None,
                 elev_range=None)
        return p

    def get_model_params(datasets_path, dataset_name, model_type=None):  # type: ignore[no-untyped-def]
        if dataset_name != DATASET:
            return model_orig(datasets_path, dataset_name, model_type)
        p = {k: swap(v, datasets_path) for k, v in model_orig(datasets_path, "lm", model_type).items()}
        info = inout.load_json(p["models_info_path"], keys_to_int=True)
        p.update(obj_ids=sorted(info), symmetric_obj_ids=sorted(
            o for o, i in info.items() if i.get("symmetries_discrete") or i.get("symmetries_continuous")))
        return p

    dataset_params.get_split_params, dataset_params.get_model_params = get_split_params, get_model_params


def write_targets(base: Path) -> int:
    """``test_targets_bop19.json``: per image and object, the instances at least 10 % visible
    (bop_toolkit's enumerate_test_targets.py with min_visib_fract 0.1); returns their number."""
    from bop_toolkit_lib import inout

    root = base / "datasets" / DATASET
    targets = []
    for scene in sorted(p for p in (root / "test").iterdir() if p.is_dir()):
        scene_gt = inout.load_scene_gt(str(scene / "scene_gt.json"))
        scene_gt_info = inout.load_scene_gt(str(scene / "scene_gt_info.json"))
        for im_id in sorted(scene_gt):
            counts: dict[int, int] = {}
            for gt, info in zip(scene_gt[im_id], scene_gt_info[im_id]):
                if info["visib_fract"] >= 0.1:
                    counts[gt["obj_id"]] = counts.get(gt["obj_id"], 0) + 1
            targets += [{"im_id": im_id, "inst_count": n, "obj_id": o, "scene_id": int(scene.name)}
                        for o, n in sorted(counts.items())]
    inout.save_json(str(root / "test_targets_bop19.json"), targets)
    return sum(t["inst_count"] for t in targets)


def _run_script(toolkit: Path, base: Path, script: str, arguments: list[str]) -> None:
    """bop_toolkit's ``scripts/<script>`` in a fresh interpreter, after :func:`register_dataset`."""
    code = ("import runpy, sys; sys.path.insert(0, sys.argv[1]); sys.path.insert(0, sys.argv[2]); "
            "import check_release_with_bop_toolkit as c; from pathlib import Path; "
            "c.register_dataset(Path(sys.argv[3])); script = sys.argv[4]; sys.argv = [script, *sys.argv[5:]]; "
            "runpy.run_path(script, run_name='__main__')")
    command = [sys.executable, "-c", code, str(toolkit), str(Path(__file__).resolve().parent), str(base),
               str(toolkit / "scripts" / script), *arguments]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise ValueError(f"bop_toolkit's {script} failed: {done.stderr.strip().splitlines()[-1:]}")


def evaluate_inside(base: Path, toolkit: Path, ours: dict[str, float], tolerance: float = AGREEMENT) -> int:
    """eval_bop19_pose.py's loop over eval_calc_errors.py and eval_calc_scores.py; bop_toolkit's
    figures against ``ours`` (see the module docstring)."""
    import numpy as np
    from bop_toolkit_lib import inout, misc

    os.environ.setdefault("EGL_PLATFORM", "surfaceless")  # EGL without a display (Mesa)
    VSD_TAUS, CORRECT_TH = _bop19_thresholds()
    n_targets = write_targets(base)
    result = f"brave6d_{DATASET}-test.csv"
    ests = inout.load_bop_results(str(base / "results" / result), version="bop19")
    passed, message, times, _ = inout.check_consistent_timings(ests, "im_id")
    if not passed:
        return _fail(f"bop_toolkit: {message}")
    common = [f"--results_path={base / 'results'}", f"--eval_path={base / 'eval'}",
              f"--datasets_path={base / 'datasets'}", "--targets_filename=test_targets_bop19.json"]
    theirs: dict[str, float] = {}
    for error in ("vsd", "mssd", "mspd"):
        arguments = ["--n_top=-1", f"--error_type={error}", f"--result_filenames={result}", "--renderer_type=vispy",
                     "--max_sym_disc_step=0.01", "--skip_missing=1", "--num_workers=1", *common]
        if error == "vsd":
            arguments += [f"--vsd_deltas={DATASET}:{VSD_DELTA}", f"--vsd_taus={','.join(map(str, VSD_TAUS))}",
                          "--vsd_normalized_by_diameter=True"]
        _run_script(toolkit, base, "eval_calc_errors.py", arguments)
        signs = ([misc.get_error_signature(error, -1, vsd_delta=VSD_DELTA, vsd_tau=tau) for tau in VSD_TAUS]
                 if error == "vsd" else [misc.get_error_signature(error, -1)])
        recalls = []
        for sign in signs:
            for th in CORRECT_TH[error]:
                _run_script(toolkit, base, "eval_calc_scores.py", [
                    f"--error_dir_paths={os.path.join('brave6d_' + DATASET + '-test', sign)}",
                    f"--eval_path={base / 'eval'}", f"--datasets_path={base / 'datasets'}",
                    "--targets_filename=test_targets_bop19.json", "--visib_gt_min=-1", f"--correct_th_{error}={th}"])
                scores = inout.load_json(str(base / "eval" / f"brave6d_{DATASET}-test" / sign /
                                             f"scores_{misc.get_score_signature([th], -1)}.json"))
                recalls.append(scores["recall"])
        theirs[error] = float(np.mean(recalls))
    theirs["ar"] = float(np.mean([theirs[e] for e in ("vsd", "mssd", "mspd")]))
    width = max(len(k) for k in theirs)
    worst = max(abs(theirs[k] - ours[k]) for k in theirs)
    print(f"bop_toolkit's evaluation of {len(ests)} estimates, {n_targets} targets, "
          f"{np.mean(list(times.values())) * 1000:.1f} ms per image as the CSV says:")
    for k in ("ar", "vsd", "mssd", "mspd"):
        print(f"  AR{'' if k == 'ar' else '_' + k.upper():<{width + 1}} bop_toolkit {theirs[k]:.9f}  brave6d {ours[k]:.9f}"
              f"  difference {theirs[k] - ours[k]:+.2e}")
    if n_targets != ours["targets"]:
        return _fail(f"bop_toolkit counts {n_targets} targets, brave6d {ours['targets']}")
    if worst > tolerance:
        return _fail(f"the figures differ by up to {worst:.2e} (more than {tolerance:g})")
    print(f"bop_toolkit and brave6d agree to {tolerance:g} (largest difference {worst:.1e})")
    return 0


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

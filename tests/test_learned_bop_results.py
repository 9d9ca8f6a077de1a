"""``brave6d learn bop-results`` (issue 66, item 2): a trained model over a BOP split as bop_toolkit's
results CSV: BOP's columns, R row-major, t in mm, one time per image; brave6d's scoring of the CSV
gives the held-out scoring's AR of the detected boxes on the same images."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from brave6d.evaluation.learned import LearnedEstimator, get_learn_preset, score_heldout, train_learned
from brave6d.evaluation.learned.data import load_training_data

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "data" / "samples" / "blenderproc_train_pbr"
SPLIT, MODELS = SAMPLE / "train_pbr", SAMPLE / "models"
PRESET = get_learn_preset("tiny").with_overrides(detector_steps=80, pose_steps=60, checkpoint_every=80)
IMAGES = 8


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bop_results") / "model"
    train_learned(SPLIT, MODELS, out, PRESET, "cpu", show_progress=False)
    return out


@pytest.fixture(scope="module")
def csv(model: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("csv") / "brave6d_demo-test.csv"
    proc = subprocess.run([str(Path(sys.executable).with_name("brave6d")), "learn", "bop-results", str(model),
                           str(SPLIT), "--models", str(MODELS), "--out", str(out), "--max-images", str(IMAGES),
                           "--score"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return out, proc.stdout


def test_the_csv_has_bops_columns_rotations_mm_and_one_time_per_image(csv: tuple[Path, str]) -> None:
    path, stdout = csv
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert len(lines) > 3, stdout  # the model finds something in 8 images
    times: dict[tuple[int, int], set[float]] = {}
    depths: list[float] = []
    for line in lines[1:]:
        scene_id, im_id, obj_id, score, R, t, seconds = line.split(",")
        R9 = np.array(R.split(), dtype=float).reshape(3, 3)  # row-major, space-separated
        t3 = np.array(t.split(), dtype=float)
        np.testing.assert_allclose(R9 @ R9.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(R9) > 0
        assert t3.shape == (3,) and t3[2] > 0
        depths.append(t3[2])
        assert 0 <= float(score) <= 1 and int(obj_id) in (1, 2, 3, 4) and int(im_id) < IMAGES
        times.setdefault((int(scene_id), int(im_id)), set()).add(float(seconds))
    assert all(len(v) == 1 and next(iter(v)) > 0 for v in times.values())  # BOP: one time per image
    assert np.median(depths) > 10  # mm (the camera is 15-60 cm away: metres would be below 1)
    assert "estimates of" in stdout and "ms per image" in stdout and stdout.splitlines()[-1].startswith("AR ")


def test_scoring_the_csv_gives_the_heldout_scoring_of_the_detected_boxes(model: Path, csv: tuple[Path, str]) -> None:
    """The same images through ``score_heldout``'s detected-box variant (the agents' way) and through
    the CSV: the same BOP19 AR (one instance per object per image in this split)."""
    path, stdout = csv
    estimator = LearnedEstimator.load(model, models_dir=MODELS)
    data = load_training_data(SPLIT, MODELS, PRESET.work_width, PRESET.heldout_every, show_progress=False,
                              crop_width=estimator.crop_source_width)
    held = score_heldout(estimator, data, MODELS, show_progress=False, images=list(range(IMAGES)))
    from brave6d.evaluation.metrics import evaluate_bop19, load_models, load_scene_gt_instances, read_bop_results

    gts = [g for g in load_scene_gt_instances(SPLIT / "000000") if g.im_id < IMAGES]
    scored = evaluate_bop19(gts, read_bop_results(path), load_models(MODELS, [1, 2, 3, 4]))
    assert held.pose_ar["detected_rgb"] > 0.01, held.pose_ar  # something to compare
    assert scored.ar == pytest.approx(held.pose_ar["detected_rgb"], abs=1e-9), (stdout, held.pose_ar)
    assert stdout.splitlines()[-1].startswith(f"AR {scored.ar:.3f} ")  # what --score printed


@pytest.mark.skipif(not os.environ.get("BOP_TOOLKIT"), reason="set BOP_TOOLKIT to a checkout of thodan/bop_toolkit "
                    "(not on PyPI; BOP_TOOLKIT_VENV: where its virtualenv goes) and install libegl-mesa0")
def test_bop_toolkit_evaluates_the_weight_free_csv_as_brave6d_does(tmp_path: Path) -> None:
    """bop_toolkit's own eval_calc_errors.py / eval_calc_scores.py on the weight-free estimator's CSV
    of the BlenderProc sample's first 2 images (JPEG, depth_scale 0.1): AR, AR_VSD, AR_MSSD, AR_MSPD
    equal to brave6d's scoring to 1e-6 (a minute or two: 120 runs of its scoring script)."""
    from brave6d.evaluation.estimate_bop import estimate_bop_split
    from brave6d.evaluation.metrics import write_bop_results

    csv_path = write_bop_results(tmp_path / "wf.csv", estimate_bop_split(SPLIT, MODELS, im_ids=range(2)).estimates)
    venv = os.environ.get("BOP_TOOLKIT_VENV", str(tmp_path / "venv"))
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "check_release_with_bop_toolkit.py"), "--results",
                           str(csv_path), "--split", str(SPLIT), "--models", str(MODELS), "--bop-toolkit",
                           os.environ["BOP_TOOLKIT"], "--venv", venv], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "agree to 1e-06" in proc.stdout


def _without_ground_truth(tmp_path: Path) -> tuple[Path, Path]:
    """The sample's split as a BOP test split whose ground truth is withheld (no scene_gt*.json, no
    masks), and the targets file bop_toolkit's enumerate_test_targets.py would write for the first
    IMAGES images (objects with instances >= 10 % visible, and their counts)."""
    import json
    import shutil

    from brave6d.annotation import read_bop_split
    from brave6d.evaluation.learned.split_results import bop19_targets

    split = Path(shutil.copytree(SPLIT, tmp_path / "test"))
    targets = []
    for image in read_bop_split(SPLIT)[:IMAGES]:
        targets += [{"im_id": image.im_id, "inst_count": n, "obj_id": o, "scene_id": image.scene_id}
                    for o, n in sorted(bop19_targets(image.infos, image.gts).items())]
    for scene in split.iterdir():
        for name in ("scene_gt.json", "scene_gt_info.json"):
            (scene / name).unlink()
        for folder in ("mask", "mask_visib"):
            shutil.rmtree(scene / folder, ignore_errors=True)
    targets_file = tmp_path / "test_targets_bop19.json"
    targets_file.write_text(json.dumps(targets))
    return split, targets_file


def test_a_test_split_without_ground_truth_is_estimated_from_its_targets_file(
        model: Path, csv: tuple[Path, str], tmp_path: Path) -> None:
    """The same images, targets from test_targets_bop19.json instead of scene_gt*.json: the same
    estimates, line for line but the time; without the targets file, one line naming scene_gt.json;
    --score where no ground truth is, one line."""
    split, targets_file = _without_ground_truth(tmp_path)
    brave6d = str(Path(sys.executable).with_name("brave6d"))
    out = tmp_path / "test.csv"
    proc = subprocess.run([brave6d, "learn", "bop-results", str(model), str(split), "--models", str(MODELS),
                           "--out", str(out), "--targets", str(targets_file)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr

    def without_time(p: Path) -> list[str]:
        return [line.rsplit(",", 1)[0] for line in p.read_text().splitlines()]

    assert len(without_time(out)) > 3 and without_time(out) == without_time(csv[0])
    for extra, expect in (([], f"{split / '000000' / 'scene_gt.json'}: not found: a test split without ground "
                                "truth is estimated from its targets file (--targets test_targets_bop19.json)"),
                          (["--targets", str(targets_file), "--score"], f"{split}: --score needs the split's "
                                                                        "ground truth (scene_gt.json)")):
        bad = subprocess.run([brave6d, "learn", "bop-results", str(model), str(split), "--models", str(MODELS),
                              "--out", str(tmp_path / "bad.csv"), *extra], capture_output=True, text=True,
                             timeout=300)
        assert bad.returncode != 0 and expect in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
        assert not (tmp_path / "bad.csv").exists()


@pytest.mark.parametrize("entries, expect", [
    ({"scene_id": 0}, "expected a JSON list of targets"),
    ([{"scene_id": 0, "im_id": 1, "obj_id": 2}], "entry 0: 'inst_count' must be a positive integer, got None"),
    ([{"scene_id": 0, "im_id": 1, "obj_id": 2, "inst_count": 0}], "entry 0: 'inst_count' must be a positive"),
    ([{"scene_id": 0, "im_id": -1, "obj_id": 2, "inst_count": 1}], "entry 0: 'im_id' must be a non-negative"),
    ([{"scene_id": 0, "im_id": 1, "obj_id": True, "inst_count": 1}], "entry 0: 'obj_id' must be a non-negative"),
    ([{"scene_id": 0, "im_id": 1, "obj_id": 2.0, "inst_count": 1}], "entry 0: 'obj_id' must be a non-negative"),
    ([{"scene_id": 0, "im_id": 1, "obj_id": 2, "inst_count": 1}] * 2, "entry 1: scene 0 image 1 object 2 is listed twice"),
    (["x"], "entry 0: expected an object"),
])
def test_a_malformed_targets_file_is_refused_naming_the_entry_and_field(tmp_path: Path, entries: object,
                                                                          expect: str) -> None:
    import json

    from brave6d.annotation import read_test_targets
    from brave6d.core.errors import DataError

    path = tmp_path / "test_targets_bop19.json"
    path.write_text(json.dumps(entries))
    with pytest.raises(DataError) as err:
        read_test_targets(path)
    assert str(err.value).startswith(f"{path}: ") and expect in str(err.value) and "\n" not in str(err.value)


def test_a_target_whose_image_is_missing_is_refused_naming_it(tmp_path: Path) -> None:
    import json

    from brave6d.annotation import read_split_targets
    from brave6d.core.errors import DataError

    split, targets_file = _without_ground_truth(tmp_path)
    assert [(i.scene_id, i.im_id) for i in read_split_targets(split, targets_file)[0]] == [(0, i) for i in range(IMAGES)]
    for entry, expect in (({"scene_id": 3}, f"scene 3 has no folder {split / '000003'}"),
                          ({"im_id": 999}, f"{split / '000000' / 'scene_camera.json'}: no entry for image 999")):
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps([{"scene_id": 0, "im_id": 0, "obj_id": 1, "inst_count": 1, **entry}]))
        with pytest.raises(DataError, match=expect):
            read_split_targets(split, bad)

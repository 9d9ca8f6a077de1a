"""BOP splits as BlenderProc and the BOP toolkit write them (issue 66, item 1): the shipped sample
(``data/samples/blenderproc_train_pbr``: JPEG ``rgb/``, depth PNGs in 0.1 mm, ``depth_scale`` 0.1)
reads and scores as the same images written as PNG + mm; ``gray/`` and a missing ``depth_scale`` are
refused in one line naming the file and field."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from brave6d.annotation import read_bop_split, read_split_scene
from brave6d.core.atomic import read_png, write_png
from brave6d.core.errors import DataError

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "data" / "samples" / "blenderproc_train_pbr"
SPLIT = SAMPLE / "train_pbr"
MODELS = SAMPLE / "models"


def as_png_and_mm(src: Path, dest: Path) -> Path:
    """The sample's images written the brave6d way: the decoded JPEG as PNG (the same pixels), the
    depth rounded to mm as PNG with depth_scale 1."""
    shutil.copytree(src, dest)
    for scene in sorted(p for p in dest.iterdir() if p.is_dir()):
        cams = json.loads((scene / "scene_camera.json").read_text())
        for key, cam in cams.items():
            im_id = int(key)
            jpg = scene / "rgb" / f"{im_id:06d}.jpg"
            write_png(jpg.with_suffix(".png"), read_png(jpg, "rgb"))
            jpg.unlink()
            depth = scene / "depth" / f"{im_id:06d}.png"
            mm = read_png(depth, "depth").astype(np.float64) * float(cam["depth_scale"])
            write_png(depth, np.clip(np.rint(mm), 0, 65535).astype(np.uint16))
            cam["depth_scale"] = 1.0
        (scene / "scene_camera.json").write_text(json.dumps(cams))
    return dest


@pytest.fixture(scope="module")
def png_mm(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return as_png_and_mm(SPLIT, tmp_path_factory.mktemp("png_mm") / "train_pbr")


def test_the_sample_is_written_as_blenderproc_writes_it() -> None:
    """JPEG colour, depth_scale 0.1 on every image, depth in tenths of a mm (a table ~25 cm away
    reads ~2500 units), masks as PNG; small enough to ship (< 2.5 MB with its models)."""
    images = read_bop_split(SPLIT)
    assert len(images) >= 12
    assert {im.rgb_path.suffix for im in images} == {".jpg"}
    assert {im.camera.depth_scale for im in images} == {0.1}
    raw = read_png(images[0].depth_path, "depth")
    assert 1500 < np.median(raw[raw > 0]) < 6000  # 15-60 cm in 0.1 mm units
    assert images[0].read_rgb().shape == (200, 320, 3)
    size = sum(p.stat().st_size for p in SAMPLE.rglob("*") if p.is_file())
    assert size < 2.5e6, size
    assert (SAMPLE / "README.md").is_file()


def test_jpeg_and_tenths_of_mm_read_as_the_same_training_data_as_png_and_mm(png_mm: Path) -> None:
    """The learned estimator's reader: the same images, cameras, instances and target coordinates;
    depth in mm within the rounding to whole mm (the old reader refused the JPEG split, and read
    0.1 mm depth as mm: ten times too far)."""
    from brave6d.evaluation.learned.data import load_training_data

    jpeg = load_training_data(SPLIT, MODELS, 160, 5, show_progress=False)
    png = load_training_data(png_mm, MODELS, 160, 5, show_progress=False)
    assert len(jpeg.images) == len(png.images) and len(jpeg.instances) == len(png.instances) > 10
    for a, b in zip(jpeg.images, png.images):
        assert (a.scene_id, a.im_id, a.heldout, a.instances) == (b.scene_id, b.im_id, b.heldout, b.instances)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_allclose(a.K, b.K)
        da, db = a.read_depth_mm(), b.read_depth_mm()
        assert np.array_equal(da > 0, db > 0)
        assert np.abs(da - db).max() <= 0.5 + 1e-9
        assert 150 < np.median(da[da > 0]) < 600  # mm, not tenths
    for a, b in zip(jpeg.instances, png.instances):
        assert (a.obj_id, a.box, a.region) == (b.obj_id, b.box, b.region)
        np.testing.assert_array_equal(a.coords, b.coords)


def test_the_weight_free_estimator_scores_both_the_same_within_noise(png_mm: Path, tmp_path: Path) -> None:
    """The weight-free estimator (depth + true boxes) over the first 2 images of both splits: BOP19
    AR equal within 0.03 (depth rounded to 1 mm vs 0.1 mm, JPEG vs its decoded PNG)."""
    from brave6d.evaluation.estimate_bop import estimate_bop_split, score_results_csv
    from brave6d.evaluation.metrics import write_bop_results

    ars = []
    for split in (SPLIT, png_mm):
        run = estimate_bop_split(split, MODELS, im_ids=range(2))
        csv = write_bop_results(tmp_path / f"{len(ars)}.csv", run.estimates)
        line = score_results_csv(csv, split, MODELS, images=range(2))
        ars.append(float(line.split()[1]))
    assert ars[0] > 0.3, ars
    assert abs(ars[0] - ars[1]) <= 0.03, ars


def test_a_grey_split_is_refused_naming_gray(tmp_path: Path) -> None:
    scene = tmp_path / "train_pbr" / "000000"
    shutil.copytree(SPLIT / "000000", scene)
    (scene / "rgb").rename(scene / "gray")
    with pytest.raises(DataError) as info:
        read_bop_split(tmp_path / "train_pbr")
    message = str(info.value)
    assert "\n" not in message and str(scene / "gray") in message and "colour" in message


def without_depth_scale(tmp_path: Path, im_id: int) -> Path:
    """A copy of the sample's scene folder whose image ``im_id`` lacks ``depth_scale``."""
    scene = tmp_path / "train_pbr" / "000000"
    shutil.copytree(SPLIT / "000000", scene)
    cams = json.loads((scene / "scene_camera.json").read_text())
    del cams[str(im_id)]["depth_scale"]
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    return scene


def test_a_missing_depth_scale_is_refused_naming_file_and_field(tmp_path: Path) -> None:
    scene = without_depth_scale(tmp_path, 3)
    for read in (lambda: read_split_scene(scene),
                 lambda: __import__("brave6d.evaluation.learned.data", fromlist=["x"]).load_training_data(
                     tmp_path / "train_pbr", MODELS, 160, 5, show_progress=False)):
        with pytest.raises(DataError) as info:
            read()
        message = str(info.value)
        assert "\n" not in message
        assert str(scene / "scene_camera.json") in message and "image 3" in message and "'depth_scale'" in message


def test_learn_train_refuses_a_missing_depth_scale_in_one_line(tmp_path: Path) -> None:
    """The command line: one line on stderr, exit status 2, no traceback, no model written."""
    without_depth_scale(tmp_path, 0)
    brave6d = Path(sys.executable).with_name("brave6d")
    proc = subprocess.run([str(brave6d), "learn", "train", str(tmp_path / "train_pbr"),
                           "--models", str(MODELS), "--out", str(tmp_path / "model"), "--preset", "tiny"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "depth_scale" in lines[0] and "scene_camera.json" in lines[0], proc.stderr
    assert not (tmp_path / "model" / "model.pt").exists()


def test_synth_writes_the_blenderproc_convention(tmp_path: Path) -> None:
    """``brave6d synth --convention blenderproc``: JPEG colour (quality 95), depth in 0.1 mm with
    depth_scale 0.1, the same ground truth and pixels (within JPEG's loss) as the brave6d convention."""
    from brave6d.synth import SynthOptions, synthesize

    spec = ROOT / "data" / "demo" / "scene.yaml"
    for convention in ("brave6d", "blenderproc"):
        synthesize(spec, tmp_path / convention, SynthOptions(images=1, width=160, height=100, convention=convention))
    a = read_bop_split(tmp_path / "brave6d" / "train_pbr")[0]
    b = read_bop_split(tmp_path / "blenderproc" / "train_pbr")[0]
    assert (a.rgb_path.suffix, b.rgb_path.suffix) == (".png", ".jpg")
    assert (a.camera.depth_scale, b.camera.depth_scale) == (1.0, 0.1)
    assert [g.obj_id for g in a.gts] == [g.obj_id for g in b.gts]
    import cv2

    ok, jpeg = cv2.imencode(".jpg", a.read_rgb()[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    np.testing.assert_array_equal(b.read_rgb(), cv2.imdecode(jpeg, cv2.IMREAD_COLOR)[:, :, ::-1])  # the same pixels, JPEG'd
    da, db = a.read_depth_mm(), b.read_depth_mm()
    assert np.array_equal(da > 0, db > 0) and np.abs(da - db).max() <= 0.5 + 1e-6
    assert not np.array_equal(db, np.rint(db))  # finer than mm
    # BlenderProc's scene_gt_coco.json beside them (the brave6d convention writes none)
    from brave6d.annotation import read_scene_gt_coco, rle_to_mask

    assert not (a.scene_dir / "scene_gt_coco.json").exists()
    coco_file = b.scene_dir / "scene_gt_coco.json"
    coco = read_scene_gt_coco(coco_file)
    kept = [gt_id for gt_id in range(len(b.gts)) if (read_png(b.mask_visib_path(gt_id)) > 0).any()]
    assert [ann["category_id"] for ann in coco[0]] == [b.gts[i].obj_id for i in kept] and kept
    for ann, gt_id in zip(coco[0], kept):
        np.testing.assert_array_equal(rle_to_mask(ann["segmentation"]), read_png(b.mask_visib_path(gt_id)) > 0)
    before = coco_file.read_bytes()
    # resumable like the default: a second run finds the image complete, and gathers the same files
    result = synthesize(spec, tmp_path / "blenderproc", SynthOptions(images=1, width=160, height=100,
                                                                    convention="blenderproc"))
    assert (result.rendered, result.skipped) == (0, 1) and coco_file.read_bytes() == before


def test_the_samples_coco_file_is_its_masks_as_bop_toolkit_writes_them() -> None:
    """The shipped scene_gt_coco.json is what annotation's writer makes from the sample's masks
    (checked once against bop_toolkit's own pycoco_utils on these 47 instances: every field equal);
    each RLE decodes to its visible mask, each box is the full mask's, ``ignore`` below 10 % visible."""
    from brave6d.annotation import read_scene_gt_coco, read_scene_gt, read_scene_gt_info, rle_to_mask, scene_gt_coco

    d = SAMPLE / "train_pbr" / "000000"
    gts, infos = read_scene_gt(d / "scene_gt.json"), read_scene_gt_info(d / "scene_gt_info.json")
    made = scene_gt_coco(d, {i: [g.obj_id for g in v] for i, v in gts.items()},
                         {i: [g.visib_fract for g in v] for i, v in infos.items()}, ".jpg", "blenderproc_train_pbr",
                         [g.obj_id for v in gts.values() for g in v])
    assert json.loads((d / "scene_gt_coco.json").read_text()) == made
    by_image = read_scene_gt_coco(d / "scene_gt_coco.json")
    assert sorted(by_image) == sorted(gts) and sum(map(len, by_image.values())) == 47
    for im_id, anns in by_image.items():
        for gt_id, ann in enumerate(anns):  # every instance of this sample is visible
            visib = read_png(d / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png") > 0
            full = read_png(d / "mask" / f"{im_id:06d}_{gt_id:06d}.png") > 0
            np.testing.assert_array_equal(rle_to_mask(ann["segmentation"]), visib)
            ys, xs = np.nonzero(full)
            assert ann["bbox"] == [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
            assert ann["area"] == visib.sum() and ann["ignore"] == (infos[im_id][gt_id].visib_fract < 0.1)


@settings(max_examples=150, deadline=None)
@given(hnp.arrays(np.bool_, hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=12)))
def test_any_mask_survives_coco_rle(mask: np.ndarray) -> None:
    """Column-major runs that start with zeros and cover every pixel; decoding gives the mask back."""
    from brave6d.annotation import mask_to_rle, rle_to_mask

    rle = mask_to_rle(mask)
    assert rle["size"] == list(mask.shape) and sum(rle["counts"]) == mask.size
    assert all(c > 0 for c in rle["counts"][1:])
    if mask.size:
        assert (rle["counts"][0] == 0) == bool(mask.ravel(order="F")[0])
    np.testing.assert_array_equal(rle_to_mask(rle), mask)


@pytest.mark.parametrize("rle, expect", [
    ({"size": [2, 2], "counts": [1, 2]}, "the runs cover 3 pixels, the mask has 2 x 2 = 4"),
    ({"size": [2, 2], "counts": [5, -1]}, "'counts' must be a list of non-negative integers"),
    ({"size": [2, 2], "counts": "PQ0"}, "'counts' must be a list of non-negative integers (uncompressed RLE)"),
    ({"size": [2], "counts": [4]}, "'size' must be [height, width]"),
    ({"size": [2, True], "counts": [2]}, "'size' must be [height, width]"),
    ({"size": [100_000, 100_000], "counts": [10**10]}, "a 100000 x 100000 mask is over the pixel limit"),
])
def test_a_bad_rle_is_refused_in_one_line(rle: dict, expect: str) -> None:
    from brave6d.annotation import rle_to_mask
    from brave6d.core.errors import DataError

    with pytest.raises(DataError) as err:
        rle_to_mask(rle, "x.json: annotations[3] segmentation")
    assert str(err.value) == f"x.json: annotations[3] segmentation: {expect}" or expect in str(err.value)
    assert str(err.value).startswith("x.json: annotations[3] segmentation: ")


@settings(max_examples=60, deadline=None)
@given(scale=st.one_of(st.floats(allow_nan=False, allow_infinity=False), st.integers(-10**6, 10**6),
                       st.text(max_size=5), st.none(), st.booleans(), st.lists(st.floats(-1, 1), max_size=2)))
def test_any_depth_scale_is_a_positive_finite_number_or_refused_naming_it(tmp_path_factory: pytest.TempPathFactory,
                                                                          scale: object) -> None:
    """Whatever a scene_camera.json gives as depth_scale: a positive finite number read as given, or
    one line naming the file, the image and the field; never a zero, negative or non-finite scale."""
    from brave6d.annotation import read_scene_camera

    path = tmp_path_factory.mktemp("cam") / "scene_camera.json"
    path.write_text(json.dumps({"0": {"cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1], "depth_scale": scale}}))
    try:
        cam = read_scene_camera(path, require_depth_scale=True)[0]
    except DataError as exc:
        message = str(exc)
        assert "\n" not in message and str(path) in message and "image 0" in message and "depth_scale" in message
        return
    assert np.isfinite(cam.depth_scale) and cam.depth_scale > 0
    assert isinstance(scale, (int, float)) and not isinstance(scale, bool) and cam.depth_scale == float(scale)

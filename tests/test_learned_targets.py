"""The learned estimator's training targets against what they must encode: detector patches (zoomed,
mirrored) whose centre cells, offsets and sizes decode back to the instances' boxes, and coordinate
crops whose targets sit where the crop map puts them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.evaluation.learned.crops import crop_affine, crop_to_image
from brave6d.evaluation.learned.data import ImageRecord, Instance, ObjectInfo, TrainingData
from brave6d.evaluation.learned.networks import DETECTOR_STRIDE
from brave6d.evaluation.learned.targets import ZOOM_RANGE, detector_batch, pose_batch


def _data(box: tuple[float, float, float, float], size: tuple[int, int] = (320, 200)) -> TrainingData:
    """One image with one object whose box is ``box`` (pixel edges), coordinates everywhere in its region."""
    w, h = size
    rgb = np.zeros((h, w, 3), np.uint8)
    obj = ObjectInfo(1, 0, np.zeros(3), 10.0, 20.0, np.eye(3)[None], np.zeros((1, 3)), np.zeros((3, 3)),
                     np.zeros((1, 3), np.int64))
    x0, y0 = int(box[0]), int(box[1])
    rw, rh = int(math.ceil(box[2])) - x0, int(math.ceil(box[3])) - y0
    inst = Instance(0, 1, 0, np.eye(3), np.array([0.0, 0.0, 300.0]), 1.0, box, (x0, y0),
                    np.full((rh, rw, 3), 0.5, np.float16), np.ones((rh, rw), bool), box)
    record = ImageRecord(1, 0, rgb, np.eye(3), np.eye(3), size, False, Path("none"), rgb, np.eye(3), [0])
    return TrainingData(Path("none"), [record], [inst], {1: obj}, "digest")


@settings(max_examples=40, deadline=None)
@given(x=st.floats(20, 250), y=st.floats(20, 150), w=st.floats(4, 50), h=st.floats(4, 40), seed=st.integers(0, 10**6))
def test_detector_targets_decode_back_to_the_box(x: float, y: float, w: float, h: float, seed: int) -> None:
    data = _data((x, y, x + w, y + h))
    batch = detector_batch(data, [0], np.random.default_rng(seed), 4, 128)
    for b in range(4):
        cells = np.argwhere(batch["weight"][b, 0] > 0)
        assert len(cells) <= 1
        if not len(cells):
            continue
        gy, gx = cells[0]
        assert batch["heat"][b, 0, gy, gx] == 1.0 and batch["heat"][b, 0].max() == 1.0
        bw, bh = np.exp(batch["size"][b, :, gy, gx])
        zoom = bw / w
        assert ZOOM_RANGE[0] - 1e-6 <= zoom <= ZOOM_RANGE[1] + 1e-6 and math.isclose(bh / h, zoom, rel_tol=1e-4)
        cx = (gx + batch["offset"][b, 0, gy, gx]) * DETECTOR_STRIDE
        cy = (gy + batch["offset"][b, 1, gy, gx]) * DETECTOR_STRIDE
        assert 0.0 <= batch["offset"][b, :, gy, gx].min() and batch["offset"][b, :, gy, gx].max() < 1.0
        assert 0.0 <= cx < 128 and 0.0 <= cy < 128
    assert np.all(np.isfinite(batch["images"]))


def test_a_bright_object_lands_under_its_box_after_zoom_and_mirror() -> None:
    data = _data((100.0, 60.0, 130.0, 90.0))
    data.images[0].rgb[60:90, 100:130] = 255  # the object: a white square exactly under its box
    hits = 0
    for seed in range(20):
        batch = detector_batch(data, [0], np.random.default_rng(seed), 2, 128)
        for b in range(2):
            cells = np.argwhere(batch["weight"][b, 0] > 0)
            if not len(cells):
                continue
            gy, gx = cells[0]
            cx = int((gx + batch["offset"][b, 0, gy, gx]) * DETECTOR_STRIDE)
            cy = int((gy + batch["offset"][b, 1, gy, gx]) * DETECTOR_STRIDE)
            assert batch["images"][b, :, cy, cx].mean() > 1.0, seed  # bright (normalised) at the box centre
            hits += 1
    assert hits >= 10


def test_the_crop_map_and_its_inverse_agree() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        centre, side, size = tuple(rng.uniform(0, 300, 2)), float(rng.uniform(5, 200)), int(rng.choice([16, 32, 64]))
        A = crop_affine(centre, side, size)
        xy = rng.uniform(-50, 350, size=(10, 2))
        back = crop_to_image(xy @ A[:, :2].T + A[:, 2], centre, side, size)
        np.testing.assert_allclose(back, xy, atol=1e-9)


def test_coordinate_crops_carry_the_coordinates_inside_the_box() -> None:
    data = _data((100.0, 60.0, 140.0, 100.0))
    batch = pose_batch(data, [0], np.random.default_rng(0), 8, 64)
    assert batch["crops"].shape == (8, 3, 64, 64) and batch["coords"].shape == (8, 3, 16, 16)
    assert np.all(batch["classes"] == 0)
    for b in range(8):
        mask = batch["masks"][b, 0] > 0
        assert 20 <= mask.sum() <= 256  # the box fills about 1/1.5 of the crop's side, jittered
        np.testing.assert_allclose(batch["coords"][b][:, mask], 0.5, atol=1e-3)
        assert np.all(batch["coords"][b][:, ~mask] == 0.0)


@given(side=st.one_of(st.floats(-1e9, 1e9), st.just(math.nan), st.just(math.inf)), smallest=st.sampled_from([32, 48, 64]),
       extra=st.sampled_from([0, 16, 64]))
def test_a_crop_follows_its_box_in_steps_of_16_within_its_sizes(side: float, smallest: int, extra: int) -> None:
    from brave6d.evaluation.learned.crops import crop_size

    largest = smallest + extra
    px = crop_size(side, smallest, largest)
    assert px % 16 == 0 and smallest <= px <= largest
    if math.isfinite(side) and smallest <= side <= largest:
        assert side <= px < side + 16  # the box's own pixels, rounded up to the net's grain
    assert crop_size(side + 17, smallest, largest) >= px if math.isfinite(side) and abs(side) < 1e8 else True


def test_box_following_crops_batch_one_size_with_as_many_pixels_and_every_instance_alike() -> None:
    # three objects, near (a 100 px box), middling (50) and far (20): crops of 128 / 80 / 48 px at
    # crop_px_min 48 .. crop_px 128; each batch one size, holding about the pixels of 8 crops of 48 px
    near = _data((10.0, 10.0, 90.0, 110.0), size=(320, 240))
    middle, far = _data((150.0, 20.0, 200.0, 60.0)), _data((250.0, 150.0, 270.0, 170.0))
    data = TrainingData(Path("none"), near.images + [middle.images[0], far.images[0]],
                        near.instances + [replace_image(middle.instances[0], 1), replace_image(far.instances[0], 2)],
                        near.objects, "digest")
    from brave6d.evaluation.learned.targets import pose_sizes

    assert {s: k for s, k in pose_sizes(data, [0, 1, 2], 48, 128).items()} == {48: [2], 80: [1], 128: [0]}
    rng = np.random.default_rng(0)
    seen = {0: 0, 1: 0, 2: 0}
    for _ in range(300):
        batch = pose_batch(data, [0, 1, 2], rng, 8, 128, 48)
        n, _, size, _ = batch["crops"].shape
        assert size in (48, 80, 128) and batch["coords"].shape[-1] == size // 4
        assert abs(n * size * size - 8 * 48 * 48) <= 0.25 * 8 * 48 * 48  # the pixels of a batch of 8 small crops
        seen[{48: 2, 80: 1, 128: 0}[size]] += n
    assert max(seen.values()) < 1.3 * min(seen.values())  # each instance about as often as the others
    fixed = pose_batch(data, [0, 1, 2], np.random.default_rng(0), 8, 64)  # crop_px_min None: one size, as before
    assert fixed["crops"].shape == (8, 3, 64, 64)


def replace_image(inst: Instance, image: int) -> Instance:
    from dataclasses import replace

    return replace(inst, image=image)

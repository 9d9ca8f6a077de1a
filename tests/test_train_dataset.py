"""Training data: holdout split, calibrated poses, undistortion, bad frames."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.layout import FrameRecord
from brave6d.training.views import holdout_split, load_scene
from brave6d.training.toy_scenes import plane_views, write_scene


def rec(index: int, level: int) -> FrameRecord:
    return FrameRecord(index=index, view_id=f"v{index}", distance_level=level, distance_m=0.2 + 0.1 * level,
                       rgb=f"rgb/{index:06d}.png", base_T_tcp=np.eye(4).tolist(), joints=[0.0] * 6, timestamp=0.0)


@settings(max_examples=60, deadline=None)
@given(levels=st.lists(st.integers(0, 3), min_size=1, max_size=200), seed=st.integers(0, 1000))
def test_holdout_is_deterministic_stratified_and_about_ten_percent(levels: list[int], seed: int) -> None:
    records = [rec(i, lv) for i, lv in enumerate(levels)]
    train, test = holdout_split(records)
    shuffled = list(records)
    np.random.default_rng(seed).shuffle(shuffled)
    assert holdout_split(shuffled) == (train, test)  # independent of record order
    assert sorted(train + test) == list(range(len(levels)))
    assert not set(train) & set(test)
    for level in set(levels):
        n = levels.count(level)
        n_test = sum(1 for i in test if levels[i] == level)
        if n == 1:
            assert n_test == 0
        else:
            assert 1 <= n_test <= n - 1
            assert n_test == min(max(math.floor(0.1 * n + 0.5), 1), n - 1)


def test_holdout_views_are_spread_over_the_level() -> None:
    records = [rec(i, 0) for i in range(90)] + [rec(90 + i, 1) for i in range(80)]
    _, test = holdout_split(records)
    level0 = [i for i in test if i < 90]
    assert level0 == [5, 15, 25, 35, 45, 55, 65, 75, 85]  # 9 of 90, evenly spaced
    assert len([i for i in test if i >= 90]) == 8
    assert np.diff(level0).min() == 10


CAM = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)


def small_scene(tmp_path: Path, **kw) -> tuple:
    views = plane_views(CAM, [0.4, 0.5], 6)
    tcp_T_cam = np.eye(4)
    tcp_T_cam[:3, 3] = [0.01, -0.06, 0.03]
    return write_scene(tmp_path / "scene", CAM, views, tcp_T_cam=tcp_T_cam, **kw), views, tcp_T_cam


def test_load_scene_uses_calibrated_poses_and_undistorted_images(tmp_path: Path) -> None:
    scene, _, _ = small_scene(tmp_path)
    # a different "calibrated" hand-eye must change the poses: training reads calibration/handeye.json
    other = np.eye(4)
    other[:3, 3] = [0.0, 0.0, 0.1]
    data_json = json.loads(scene.handeye_path.read_text())
    data_json["tcp_T_cam"] = other.tolist()
    scene.handeye_path.write_text(json.dumps(data_json))
    data = load_scene(scene, downscale=2)
    assert len(data.train) + len(data.test) == 12
    assert {v.distance_level for v in data.test} == {0, 1}
    assert data.camera.width == 32 and data.camera.height == 24
    assert data.camera.fx == pytest.approx(25.0)
    assert data.undistorted_root == scene.root / "undistorted"
    assert "undistorted once" in data.undistortion
    records = {r.index: r for r in scene.frames()}
    for v in data.views:
        want = np.asarray(records[v.index].base_T_tcp) @ other
        np.testing.assert_allclose(v.base_T_cam, want, atol=1e-12)
        assert v.image.shape == (24, 32, 3) and v.image.dtype == np.uint8


def test_missing_frame_names_it_or_is_skipped(tmp_path: Path) -> None:
    scene, _, _ = small_scene(tmp_path)
    load_scene(scene)  # undistorted copy exists now
    (scene.root / "undistorted" / "rgb" / "000003.png").unlink()
    load_scene(scene)  # a lost undistorted file is simply made again
    (scene.capture_dir / "rgb" / "000003.png").unlink()
    with pytest.raises(DataError, match=r"frame 3 \(v0003\).*000003.png.*--skip-bad-frames"):
        load_scene(scene)
    data = load_scene(scene, skip_bad_frames=True)
    assert [s.view_id for s in data.skipped] == ["v0003"]
    assert 3 not in {v.index for v in data.views}


def test_corrupt_capture_frame_names_it_or_is_skipped(tmp_path: Path) -> None:
    scene, _, _ = small_scene(tmp_path)
    (scene.capture_dir / "rgb" / "000005.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(DataError, match="000005.png"):
        load_scene(scene)
    data = load_scene(scene, skip_bad_frames=True)
    assert [s.index for s in data.skipped] == [5]
    assert len(data.views) == 11
    assert "in memory" in data.undistortion


def test_skipping_keeps_the_split_of_other_frames(tmp_path: Path) -> None:
    scene, _, _ = small_scene(tmp_path)
    full = load_scene(scene)
    victim = full.train[0].index
    (scene.root / "undistorted" / "rgb" / f"{victim:06d}.png").write_bytes(b"junk")
    part = load_scene(scene, skip_bad_frames=True)
    assert [v.index for v in part.test] == [v.index for v in full.test]
    assert [v.index for v in part.train] == [v.index for v in full.train if v.index != victim]

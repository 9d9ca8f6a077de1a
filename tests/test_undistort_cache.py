"""The undistortion cache is keyed on content: a recapture redoes exactly the frames that changed."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from brave6d.core.atomic import depth_m_to_mm_u16, move_aside, read_png, write_png
from brave6d.core.calibration_io import write_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir
from brave6d.core.transforms import look_at
from brave6d.core.undistort import ensure_undistorted

CAM = PinholeCamera(64, 40, 50.0, 50.0, 31.5, 19.5, (0.1, -0.05, 0.0, 0.0, 0.0))


def capture(scene: SceneDir, images: list[np.ndarray], shift: float = 0.0) -> None:
    """Write a capture of ``images`` (same file names every time, as ``capture run`` does)."""
    log = FrameLog(scene.frames_path)
    for i, rgb in enumerate(images):
        name = f"{i:06d}.png"
        write_png(scene.rgb_dir / name, rgb)
        write_png(scene.depth_dir / name, depth_m_to_mm_u16(np.full((40, 64), 0.3 + 0.01 * i)))
        T = look_at([0.2 + 0.05 * i + shift, 0.0, 0.4], [0.45, 0.0, 0.0])
        log.append(FrameRecord(index=i, view_id=f"v{i}", distance_level=0, distance_m=0.3, rgb=f"rgb/{name}",
                               depth=f"depth/{name}", base_T_tcp=T.tolist(), joints=[0.0] * 6, timestamp=float(i)))


def random_images(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 255, (40, 64, 3), dtype=np.uint8) for _ in range(n)]


def stats(paths: list[Path]) -> list[tuple[int, int]]:
    return [(p.stat().st_ino, p.stat().st_mtime_ns) for p in paths]


@pytest.fixture
def scene(tmp_path: Path) -> SceneDir:
    scene = SceneDir(tmp_path / "scene")
    write_intrinsics(scene, CAM)
    return scene


def test_recapture_redoes_exactly_the_changed_frame(scene: SceneDir) -> None:
    images = random_images(3, seed=0)
    capture(scene, images)
    first = ensure_undistorted(scene)
    rgb = [first.rgb_path(r) for r in first.records]
    depth = [first.depth_path(r) for r in first.records]
    before_rgb, before_depth = stats(rgb), stats(depth)  # type: ignore[arg-type]
    old_frame1 = read_png(rgb[1], "rgb")

    # capture run --force: the old capture is moved aside, a new one written under the same names;
    # frame 1 looks different now, the others are byte-identical, every pose moved
    move_aside(scene.capture_dir)
    changed = list(images)
    changed[1] = 255 - images[1]
    capture(scene, changed, shift=0.01)
    second = ensure_undistorted(scene)

    new_frame1 = read_png(second.rgb_path(second.records[1]), "rgb")
    assert not np.array_equal(new_frame1, old_frame1)
    np.testing.assert_array_equal(new_frame1, CAM.undistort_image(changed[1], cv2.INTER_LINEAR))
    after_rgb = stats(rgb)
    assert after_rgb[0] == before_rgb[0] and after_rgb[2] == before_rgb[2]  # unchanged frames not rewritten
    assert after_rgb[1] != before_rgb[1]
    assert stats(depth) == before_depth  # the depth files did not change either
    assert stats(rgb) == stats([second.rgb_path(r) for r in second.records])
    ensure_undistorted(scene)
    assert stats(rgb) == after_rgb  # nothing to redo


def test_missing_output_is_redone_and_strays_removed(scene: SceneDir) -> None:
    capture(scene, random_images(3, seed=1))
    frames = ensure_undistorted(scene)
    lost = frames.rgb_path(frames.records[2])
    kept = stats([frames.rgb_path(frames.records[0])])
    lost.unlink()
    stray = frames.root / "rgb" / "000099.png"
    shutil.copy(frames.rgb_path(frames.records[0]), stray)
    ensure_undistorted(scene)
    assert lost.is_file()
    assert not stray.exists()
    assert stats([frames.rgb_path(frames.records[0])]) == kept


def test_a_corrupt_raw_frame_is_named_and_the_others_are_kept(scene: SceneDir) -> None:
    capture(scene, random_images(3, seed=2))
    (scene.rgb_dir / "000001.png").write_bytes(b"not a png")
    with pytest.raises(DataError, match=r"frame 1 \(v1\): .*000001\.png: not an image this program reads"):
        ensure_undistorted(scene)
    frames_dir = scene.root / "undistorted" / "rgb"
    assert not (frames_dir / "000001.png").exists()
    done = stats([frames_dir / "000000.png"])
    write_png(scene.rgb_dir / "000001.png", random_images(1, seed=3)[0])
    ensure_undistorted(scene)
    assert (frames_dir / "000001.png").is_file() and (frames_dir / "000002.png").is_file()
    assert stats([frames_dir / "000000.png"]) == done  # undistorted before the error: not redone

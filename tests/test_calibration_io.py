"""Kernel access to calibration results: schema round trip, clear errors, undistortion cache."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from brave6d.core.atomic import read_png, write_png, depth_m_to_mm_u16
from brave6d.core.calibration_io import camera_poses, read_handeye, read_intrinsics, write_handeye, write_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError, NonRigidTransformError
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir
from brave6d.core.transforms import look_at, make_transform, rpy_deg_to_matrix
from brave6d.core.undistort import ensure_undistorted

CAM = PinholeCamera(64, 40, 50.0, 50.0, 31.5, 19.5, (0.1, -0.05, 0.0, 0.0, 0.0))


def _scene_with_frames(root: Path, n: int = 3) -> SceneDir:
    scene = SceneDir(root)
    log = FrameLog(scene.frames_path)
    rng = np.random.default_rng(0)
    for i in range(n):
        name = f"{i:06d}.png"
        write_png(scene.rgb_dir / name, rng.integers(0, 255, (40, 64, 3), dtype=np.uint8))
        write_png(scene.depth_dir / name, depth_m_to_mm_u16(np.full((40, 64), 0.3 + 0.01 * i)))
        T = look_at([0.2 + 0.05 * i, 0.0, 0.4], [0.45, 0.0, 0.0])
        log.append(FrameRecord(index=i, view_id=f"v{i}", distance_level=0, distance_m=0.3, rgb=f"rgb/{name}",
                               depth=f"depth/{name}", base_T_tcp=T.tolist(), joints=[0.0] * 6, timestamp=float(i)))
    return scene


def test_round_trip_and_camera_poses(tmp_path: Path) -> None:
    scene = _scene_with_frames(tmp_path)
    tcp_T_cam = make_transform(rpy_deg_to_matrix((0.5, -1.0, 2.0)), [0.01, -0.06, 0.03])
    write_intrinsics(scene, CAM, rms_px=0.12)
    write_handeye(scene, tcp_T_cam, method="refined")
    assert read_intrinsics(scene) == CAM
    np.testing.assert_array_equal(read_handeye(scene), tcp_T_cam)
    poses = camera_poses(scene)
    assert len(poses) == 3
    for record, base_T_cam in poses:
        np.testing.assert_allclose(base_T_cam, record.base_T_tcp_matrix @ tcp_T_cam, atol=1e-15)


def test_errors_name_the_file(tmp_path: Path) -> None:
    scene = SceneDir(tmp_path)
    with pytest.raises(DataError, match="handeye.json: file not found"):
        read_handeye(scene)
    scene.calibration_dir.mkdir(parents=True)
    scene.handeye_path.write_text(json.dumps({"tcp_T_cam": np.diag([1.0, 2.0, 1.0, 1.0]).tolist()}))
    with pytest.raises(DataError, match="handeye.json: tcp_T_cam: rotation block is not orthonormal"):
        read_handeye(scene)
    scene.intrinsics_path.write_text(json.dumps({"K": 1}))
    with pytest.raises(DataError, match="intrinsics.json: field 'camera'"):
        read_intrinsics(scene)
    with pytest.raises(NonRigidTransformError):
        write_handeye(scene, np.eye(3))


def test_undistorted_frames_written_once_and_redone_on_change(tmp_path: Path) -> None:
    scene = _scene_with_frames(tmp_path)
    write_intrinsics(scene, CAM)
    und = ensure_undistorted(scene)
    assert und.camera == CAM.without_distortion()
    first = und.rgb_path(und.records[0])
    mtime = first.stat().st_mtime_ns
    raw = read_png(scene.rgb_dir / "000000.png", "rgb")
    assert not np.array_equal(read_png(first, "rgb"), raw)  # distortion removed
    depth = read_png(und.depth_path(und.records[1]), "depth")
    assert set(np.unique(depth)) <= {0, 310}  # nearest: depth values are never blended
    assert ensure_undistorted(scene).rgb_path(und.records[0]).stat().st_mtime_ns == mtime  # reused
    write_intrinsics(scene, PinholeCamera(64, 40, 50.0, 50.0, 31.5, 19.5, (0.2, 0.0, 0.0, 0.0, 0.0)))
    ensure_undistorted(scene)
    assert first.stat().st_mtime_ns != mtime  # intrinsics changed: redone

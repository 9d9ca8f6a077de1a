"""Scene-directory layout: atomic writes survive a killed writer, frames.jsonl recovers from an
interrupted append, images round-trip."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from brave6d.core.atomic import (
    atomic_write_json,
    atomic_write_text,
    depth_m_to_mm_u16,
    depth_mm_u16_to_m,
    read_json,
    read_png,
    write_png,
)
from brave6d.core.errors import DataError
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir, init_scene_dir
from brave6d.core.spec import load_scene_spec
from brave6d.core.transforms import look_at


def _record(i: int) -> FrameRecord:
    T = look_at([0.3 + 0.01 * i, 0.0, 0.4], [0.45, 0.0, 0.0])
    return FrameRecord(index=i, view_id=f"d0_v{i:03d}", distance_level=0, distance_m=0.2,
                       rgb=f"rgb/{i:06d}.png", depth=f"depth/{i:06d}.png", base_T_tcp=T.tolist(),
                       joints=[0.1 * i, -1.5, 1.5, -1.5, -1.5, 0.0], timestamp=1.5 * i)


def test_atomic_write_survives_killed_writer(tmp_path: Path) -> None:
    """A writer killed mid-write leaves the old file intact and complete."""
    target = tmp_path / "metrics.json"
    atomic_write_json(target, {"version": "old", "values": list(range(10))})
    script = textwrap.dedent(f"""
        import time
        from brave6d.core.atomic import atomic_write
        def slow(handle):
            handle.write(b'{{"version": "new", "values": [')
            handle.flush()
            print("started", flush=True)
            time.sleep(30)
            handle.write(b']}}')
        atomic_write({str(target)!r}, slow)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "started"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    assert read_json(target) == {"version": "old", "values": list(range(10))}


def test_atomic_write_exception_keeps_old_file_and_no_temp(tmp_path: Path) -> None:
    from brave6d.core.atomic import atomic_write

    target = tmp_path / "a.txt"
    atomic_write_text(target, "old")

    def failing(handle):  # noqa: ANN001
        handle.write(b"partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, failing)
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_json_refuses_nan(tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        atomic_write_json(tmp_path / "x.json", {"psnr": float("nan")})
    assert not (tmp_path / "x.json").exists()


def test_read_json_errors_name_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "handeye.json"
    bad.write_text("{not json")
    with pytest.raises(DataError, match="handeye.json: not valid JSON"):
        read_json(bad)
    with pytest.raises(DataError, match="missing.json: file not found"):
        read_json(tmp_path / "missing.json")


def test_frame_log_round_trip_and_partial_tail(tmp_path: Path) -> None:
    log = FrameLog(tmp_path / "frames.jsonl")
    for i in range(3):
        log.append(_record(i))
    with open(log.path, "ab") as handle:  # a process killed mid-append
        handle.write(b'{"index": 3, "view_id": "d0_v0')
    records = log.read()
    assert [r.index for r in records] == [0, 1, 2]
    np.testing.assert_allclose(records[1].base_T_tcp_matrix, np.asarray(_record(1).base_T_tcp))
    log.append(_record(3))  # the partial line is dropped, the new record is whole
    assert [r.index for r in log.read()] == [0, 1, 2, 3]


def test_frame_log_corrupt_middle_line_names_line(tmp_path: Path) -> None:
    log = FrameLog(tmp_path / "frames.jsonl")
    log.append(_record(0))
    with open(log.path, "ab") as handle:
        handle.write(b"garbage\n")
    log.append(_record(1))
    with pytest.raises(DataError, match=r"frames.jsonl:2: not a JSON record"):
        log.read()


def test_frame_record_rejects_non_rigid_pose(tmp_path: Path) -> None:
    rec = _record(0).model_dump()
    rec["base_T_tcp"][0][0] = 2.0
    path = tmp_path / "frames.jsonl"
    path.write_text(json.dumps(rec) + "\n")
    with pytest.raises(DataError, match=r"frames.jsonl:1: field 'base_T_tcp'.*not orthonormal"):
        FrameLog(path).read()


def test_png_round_trips(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    write_png(tmp_path / "rgb.png", rgb)
    np.testing.assert_array_equal(read_png(tmp_path / "rgb.png", "rgb"), rgb)
    depth = np.array([[0.0, 0.2345, np.nan], [np.inf, -1.0, 70.0]])
    mm = depth_m_to_mm_u16(depth)
    assert mm.tolist() == [[0, 234, 0], [0, 0, 65535]]  # 0.2345 m rounds half to even; 70 m saturates
    write_png(tmp_path / "d.png", mm)
    np.testing.assert_array_equal(read_png(tmp_path / "d.png", "depth"), mm)
    np.testing.assert_allclose(depth_mm_u16_to_m(mm)[0, 1], 0.234, atol=1e-7)
    with pytest.raises(DataError, match="expected a uint16 depth"):
        read_png(tmp_path / "rgb.png", "depth")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(DataError, match="broken.png: not an image this program reads"):
        read_png(tmp_path / "broken.png")


def test_init_scene_dir_is_self_contained(demo_spec_path: Path, tmp_path: Path) -> None:
    scene = init_scene_dir(tmp_path / "scene", demo_spec_path)
    spec = scene.load_spec()
    for obj in [*spec.objects, *spec.static_meshes]:
        path = spec.resolve(obj.mesh)
        assert path.is_file() and tmp_path in path.parents
    original = load_scene_spec(demo_spec_path)
    assert spec.capture == original.capture and spec.simulation == original.simulation
    table = spec.resolve(spec.static_meshes[0].mesh)
    assert table.with_suffix(".png").is_file() and table.with_suffix(".mtl").is_file()
    assert SceneDir(scene.root).frames() == []


def _spec_with_meshes(tmp_path: Path, demo_spec_path: Path, meshes: list[str]) -> Path:
    """The demo spec, its objects' meshes replaced by ``meshes`` (relative to ``tmp_path``), written there."""
    import yaml

    data = yaml.safe_load(demo_spec_path.read_text())
    data["static_meshes"] = []
    data["objects"] = [{**obj, "mesh": mesh} for obj, mesh in zip(data["objects"], meshes, strict=False)]
    spec_file = tmp_path / "scene.yaml"
    spec_file.write_text(yaml.safe_dump(data, sort_keys=False))
    return spec_file


def test_init_gives_meshes_of_the_same_file_name_their_own_assets(demo_spec_path: Path, tmp_path: Path) -> None:
    """a/cube.obj, b/cube.obj (other content) and c/cube.obj (same as a) from three folders: every object
    gets its own mesh and sidecars back, identical meshes share one copy, and names do not depend on the run."""
    demo = demo_spec_path.parent / "meshes"
    for folder, stem in (("a", "book"), ("b", "notepad"), ("c", "book")):
        (tmp_path / folder).mkdir()
        for ext in (".obj", ".mtl", ".png"):
            (tmp_path / folder / f"cube{ext}").write_bytes((demo / f"{stem}{ext}").read_bytes())
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "vial.ply").write_bytes((demo / "sample_vial.ply").read_bytes())
    spec_file = _spec_with_meshes(tmp_path, demo_spec_path, ["a/cube.obj", "b/cube.obj", "c/cube.obj", "d/vial.ply"])
    scene = init_scene_dir(tmp_path / "scene", spec_file)
    spec = scene.load_spec()
    for obj, folder in zip(spec.objects, "abcd", strict=True):
        source = tmp_path / folder / Path(obj.mesh).name
        copied = spec.resolve(obj.mesh)
        for ext in ((".obj", ".mtl", ".png") if source.suffix == ".obj" else (source.suffix,)):
            assert copied.with_suffix(ext).read_bytes() == source.with_suffix(ext).read_bytes(), (obj.name, ext)
    meshes = [obj.mesh.as_posix() for obj in spec.objects]
    assert meshes[0] != meshes[1] and meshes[0] == meshes[2]
    assert meshes[3] == "assets/vial.ply"  # a mesh whose name no other mesh uses keeps it
    again = init_scene_dir(tmp_path / "scene2", spec_file).load_spec()
    assert [obj.mesh.as_posix() for obj in again.objects] == meshes


def test_scene_dir_paths_follow_design(tmp_path: Path) -> None:
    scene = SceneDir(tmp_path)
    rel = {p.relative_to(tmp_path).as_posix() for p in (
        scene.plan_path, scene.frames_path, scene.intrinsics_path, scene.handeye_path,
        scene.sparse_dir, scene.splat_dir, scene.bop_dir, scene.bundle_dir)}
    assert rel == {"capture/plan.json", "capture/frames.jsonl", "calibration/intrinsics.json",
                   "calibration/handeye.json", "sparse", "splat", "annotation/bop", "bundle"}

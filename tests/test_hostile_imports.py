"""Hostile import sources and the smaller holes of issue #44 (classes 2 and 6).

A capture made elsewhere is a download like a release: every path a ``transforms.json`` or a
COLMAP model names must lie inside its folder (``brave6d.core.names.contained_path``: no ``..``,
no absolute path, no symbolic link), a PLY header is checked against the file before anything is
allocated (``brave6d.core.ply_check``), and every number that becomes a pose or a point is finite
and within ``MAX_COORDINATE``. Each case is one line naming the file and the frame or field (CLI
exit status 2), and nothing is written: no scene folder, no ``capture/rgb/``. Also: a scene spec
names mesh files only, and ``brave6d init`` leaves nothing behind when it fails.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy.spatial.transform import Rotation
from test_import_capture import CAMERA, H, W, gl_camera_to_world, object_capture, ring, write_ply, write_transforms
from test_input_messages import _one_line_error

from brave6d.annotation import read_ply_mesh
from brave6d.core.errors import DataError
from brave6d.core.names import contained_path
from brave6d.core.ply_check import MAX_PLY_ELEMENTS, check_ply_header
from brave6d.training import ImportOptions, ScaleChoice, UpChoice, import_capture, read_ply, read_source

SECRET = b"the key to the lab's cluster"
IMPORT = ("--scale", "1", "--up", "0,0,1")


@pytest.fixture()
def outside(tmp_path: Path) -> Path:
    """A PNG and a secret outside every source folder."""
    folder = tmp_path / "outside"
    folder.mkdir()
    Image.fromarray(np.full((H, W, 3), 7, np.uint8)).save(folder / "stolen.png")
    (folder / "secret").write_bytes(SECRET)
    return folder


def _import_refused(capsys: pytest.CaptureFixture[str], source: Path, scene: Path, *extra: str) -> str:
    """``brave6d import``: one line, exit 2, and no scene folder at all (nothing copied)."""
    line = _one_line_error(capsys, "import", str(source), str(scene), *IMPORT, *extra)
    assert not scene.exists(), sorted(scene.rglob("*"))
    return line


def _edit(path: Path, change) -> Path:  # type: ignore[no-untyped-def]
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    return path


# ============================================================================= class 2: paths an import names
@pytest.mark.parametrize("case", ["dot-dot", "absolute", "linked image", "linked folder", "extensionless link"])
def test_a_transforms_file_path_outside_its_folder_is_refused(tmp_path: Path, outside: Path,
                                                              capsys: pytest.CaptureFixture[str], case: str) -> None:
    source, _ = object_capture(tmp_path / "src")
    images = tmp_path / "src" / "images"
    if case == "dot-dot":
        _edit(source, lambda d: d["frames"][0].update(file_path="../outside/stolen.png"))
        expected = r"a '\.\.' path part"
    elif case == "absolute":
        _edit(source, lambda d: d["frames"][0].update(file_path=str(outside / "stolen.png")))
        expected = "an absolute path"
    elif case == "linked image":
        (images / "f000.png").unlink()
        (images / "f000.png").symlink_to(outside / "stolen.png")
        expected = r"images/f000.png is a symbolic link"
    elif case == "linked folder":
        for p in images.iterdir():
            (outside / p.name).write_bytes(p.read_bytes())
            p.unlink()
        images.rmdir()
        images.symlink_to(outside)
        expected = r"src/images is a symbolic link"
    else:  # a name without an extension, the file beside it a link
        _edit(source, lambda d: d["frames"][0].update(file_path="images/f000"))
        (images / "f000.png").unlink()
        (images / "f000.png").symlink_to(outside / "stolen.png")
        expected = r"images/f000.png is a symbolic link"
    line = _import_refused(capsys, source, tmp_path / "scene")
    assert re.search(rf"{source}: field 'frames\[0\]'\.file_path: .*{expected}", line), line


def test_points_files_outside_the_folder_are_refused(tmp_path: Path, outside: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    source, _ = object_capture(tmp_path / "src")
    for hostile, expected in [("/etc/passwd", "an absolute path"), ("../outside/secret", r"a '\.\.' path part")]:
        _edit(source, lambda d: d.update(ply_file_path=hostile))  # noqa: B023 - used at once
        line = _import_refused(capsys, source, tmp_path / "scene")
        assert re.search(rf"{source}: field 'ply_file_path': .*{expected}", line), line
    (tmp_path / "src" / "points.ply").unlink()
    (tmp_path / "src" / "points.ply").symlink_to(outside / "secret")
    _edit(source, lambda d: d.update(ply_file_path="points.ply"))
    assert "points.ply is a symbolic link" in _import_refused(capsys, source, tmp_path / "scene")


def _colmap_text_model(folder: Path, names: list[str], image_dir: Path | None = None) -> Path:
    """A COLMAP text model of a ring of cameras around the origin (no points), and its images."""
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(f"1 PINHOLE {W} {H} 40 41 24.5 15.25\n")
    lines = []
    for i, (name, T) in enumerate(zip(names, ring(len(names), 0.5)), start=1):
        cam_T_world = np.linalg.inv(T)
        x, y, z, w = Rotation.from_matrix(cam_T_world[:3, :3]).as_quat()
        t = cam_T_world[:3, 3]
        lines += [f"{i} {w} {x} {y} {z} {t[0]} {t[1]} {t[2]} 1 {name}", ""]
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("")
    images = image_dir or folder / "images"
    images.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name in names:
        if not name.startswith("/") and ".." not in name:
            Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(images / name)
    return folder


def test_colmap_image_names_outside_the_images_folder_are_refused(tmp_path: Path, outside: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    names = [f"v{i:02d}.png" for i in range(8)]
    good = _colmap_text_model(tmp_path / "good", names)
    assert len(read_source(good).frames) == 8  # the model itself imports
    for hostile, expected in [(str(outside / "stolen.png"), "an absolute path"),
                              ("../../outside/stolen.png", r"a '\.\.' path part")]:
        source = _colmap_text_model(tmp_path / f"src{len(hostile)}", [hostile, *names[1:]])
        line = _import_refused(capsys, source, tmp_path / "scene")
        assert re.search(rf"sparse/0: image 1: name: .*{expected}", line), line
    (good / "images" / "v03.png").unlink()
    (good / "images" / "v03.png").symlink_to(outside / "stolen.png")
    line = _import_refused(capsys, good, tmp_path / "scene")
    assert re.search(r"sparse/0: image 4: name: .*images/v03.png is a symbolic link", line), line


@pytest.mark.parametrize("linked", ["images folder", "cameras.txt", "sparse folder", "transforms.json"])
def test_a_linked_model_file_or_folder_in_the_source_is_refused(tmp_path: Path, outside: Path,
                                                                capsys: pytest.CaptureFixture[str], linked: str) -> None:
    if linked == "transforms.json":
        source, _ = object_capture(tmp_path / "src")
        real = outside / "transforms.json"
        source.rename(real)
        source.symlink_to(real)
        source, expected = tmp_path / "src", "src/transforms.json is a symbolic link"
    else:
        source = _colmap_text_model(tmp_path / "src", [f"v{i:02d}.png" for i in range(8)])
        victim = {"images folder": source / "images", "cameras.txt": source / "sparse" / "0" / "cameras.txt",
                  "sparse folder": source / "sparse"}[linked]
        victim.rename(outside / victim.name)
        victim.symlink_to(outside / victim.name)
        expected = {"images folder": "src/images: the images folder is a symbolic link",
                    "cameras.txt": "sparse/0/cameras.txt is a symbolic link",
                    "sparse folder": "src/sparse is a symbolic link"}[linked]
    assert expected in _import_refused(capsys, source, tmp_path / "scene")


@settings(max_examples=60, deadline=None)
@given(name=st.one_of(
    st.lists(st.sampled_from(["..", ".", "", "a", "b.png", "/", "\\", "c:", "d\x00", "e ", "f."]), min_size=1,
             max_size=5).map("/".join),
    st.text(min_size=1, max_size=30)))
def test_contained_path_never_leads_outside(tmp_path_factory: pytest.TempPathFactory, name: str) -> None:
    """Whatever the name, the path the rule gives lies inside the folder, or the rule names the field."""
    root = tmp_path_factory.mktemp("root") / "inside"
    root.mkdir()
    try:
        path = contained_path(root, name, "transforms.json: field 'frames[0].file_path'")
    except DataError as exc:
        assert str(exc).startswith("transforms.json: field 'frames[0].file_path': ") and "\n" not in str(exc)
        return
    assert path.resolve().is_relative_to(root.resolve()) and path != root


# ============================================================================= class 2: PLY headers
def _ply_header(count: int, fmt: str = "binary_little_endian") -> bytes:
    return (f"ply\nformat {fmt} 1.0\nelement vertex {count}\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n").encode()


@pytest.mark.parametrize("count", [4_000_000_000, 3])
def test_a_points_ply_claiming_billions_of_vertices_is_refused_from_its_header(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], count: int) -> None:
    source, _ = object_capture(tmp_path / "src")
    (tmp_path / "src" / "points.ply").write_bytes(_ply_header(count) + bytes(12 * 2))  # 2 vertices' worth
    line = _import_refused(capsys, source, tmp_path / "scene")
    assert "points.ply" in line and (f"{count} 'vertex' elements" in line), line


@pytest.mark.parametrize("reader", [check_ply_header, read_ply, read_ply_mesh])
@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_every_ply_reader_checks_the_header_before_allocating(tmp_path: Path, reader, fmt: str) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "huge.ply"
    path.write_bytes(_ply_header(4_000_000_000, fmt) + b"0 0 0\n")
    with pytest.raises(DataError, match=rf"huge.ply: .*PLY header line 3: declares 4000000000 'vertex' elements, "
                                        rf"more than the {MAX_PLY_ELEMENTS} read"):
        reader(path)
    path.write_bytes(_ply_header(1000, fmt) + b"0 0 0\n")
    with pytest.raises(DataError, match=r"huge.ply: .*its PLY header declares 1000 'vertex' elements"):
        reader(path)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(0, 30), faces=st.integers(0, 10), text=st.booleans(), cut=st.integers(0, 400),
       garbage=st.binary(max_size=40))
def test_ply_headers_of_real_files_pass_and_truncated_or_garbled_ones_are_one_line(
        tmp_path: Path, n: int, faces: int, text: bool, cut: int, garbage: bytes) -> None:
    """A file plyfile writes passes with its counts; the same file cut short or with garbage in its
    header is accepted only when it still holds its rows, otherwise one line naming it."""
    from plyfile import PlyData, PlyElement

    vertex = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    face = np.empty(faces, dtype=[("vertex_indices", "O")])
    for i in range(faces):
        face["vertex_indices"][i] = np.array([0, 0, 0], np.int32)
    path = tmp_path / "m.ply"
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")], text=text).write(str(path))
    assert check_ply_header(path) == {"vertex": n, "face": faces}
    data = path.read_bytes()
    path.write_bytes(data[:max(len(data) - cut, 0)])
    try:
        counts = check_ply_header(path)
    except DataError as exc:
        assert str(exc).startswith(f"{path}: ") and "\n" not in str(exc)
    else:
        assert counts == {"vertex": n, "face": faces}
    head = data.index(b"end_header")
    path.write_bytes(data[:head] + garbage + data[head:])
    try:
        check_ply_header(path)
    except DataError as exc:
        assert "\n" not in str(exc)


# ============================================================================= class 2: absurd numbers
def test_translations_of_1e150_are_refused_and_nothing_is_written(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    source, _ = object_capture(tmp_path / "src")
    _edit(source, lambda d: [row.__setitem__(3, 1e150) for row in d["frames"][2]["transform_matrix"][:3]])
    line = _import_refused(capsys, source, tmp_path / "scene", "--skip-pose-check")  # before: exit 0, inf in the PLY
    assert re.search(r"frame 'images/f002.png': the camera position \(1e\+150, 1e\+150, 1e\+150\) has a coordinate "
                     r"beyond \+-1e\+06 source units \(MAX_COORDINATE\)", line), line


def test_a_scale_that_throws_the_cameras_beyond_the_bound_is_refused(tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    source, _ = object_capture(tmp_path / "src")
    line = _one_line_error(capsys, "import", str(source), str(tmp_path / "scene"), "--scale", "1e300", "--up", "0,0,1")
    assert "after the world change (--scale 1e+300 (given))" in line and "metres (MAX_COORDINATE)" in line, line
    assert not (tmp_path / "scene").exists()


def test_points_beyond_the_bound_are_dropped_and_counted(tmp_path: Path) -> None:
    folder = tmp_path / "src"
    source, _ = object_capture(folder)
    points = np.vstack([np.random.default_rng(2).normal(0, 0.1, (50, 3)), [[1e30, 0, 0], [0, -1e7, 0]]])
    write_ply(folder / "points.ply", points)
    capture = read_source(source)
    assert len(capture.points) == 50 and capture.details["points_dropped"].startswith("2 points")
    import_capture(source, tmp_path / "scene", ImportOptions(scale=ScaleChoice(factor=1.0), up=UpChoice((0, 0, 1))))
    from plyfile import PlyData

    vertex = PlyData.read(str(tmp_path / "scene" / "capture" / "imported_points.ply"))["vertex"]
    assert len(vertex) == 50 and all(np.isfinite(vertex[c]).all() for c in "xyz")


def test_a_camera_larger_than_the_pixel_limit_is_refused_before_anything_is_allocated(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Most frames declare 100000x100000 (their images are never read: frame 0's is, and the
    resampling maps into the most common camera would have been 10^10 pixels)."""
    source, _ = object_capture(tmp_path / "src", per_frame={i: {"w": 100000, "h": 100000} for i in range(1, 12)})
    line = _import_refused(capsys, source, tmp_path / "scene", "--skip-pose-check")
    assert re.search(r"frames\[1\]'? \(images/f001.png\): camera OPENCV: image size 100000x100000 is more than the "
                     r"67108864 pixels", line), line


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=st.floats(allow_nan=False, allow_infinity=False), row=st.integers(0, 2), frame=st.integers(0, 11),
       scale=st.sampled_from([1e-3, 1.0, 1e3, 1e9]))
def test_any_translation_imports_finite_or_is_refused_naming_the_frame(tmp_path_factory: pytest.TempPathFactory,
                                                                       value: float, row: int, frame: int,
                                                                       scale: float) -> None:
    folder = tmp_path_factory.mktemp("pose")
    poses = [gl_camera_to_world(T[:3, 3], np.zeros(3)) for T in ring(12, 0.5)]
    poses[frame][row, 3] = value
    source = write_transforms(folder / "src", poses, CAMERA)
    try:
        import_capture(source, folder / "scene", ImportOptions(scale=ScaleChoice(factor=scale), up=UpChoice((0, 0, 1)),
                                                               pose_check=False))
    except DataError as exc:
        assert "\n" not in str(exc) and str(source) in str(exc)
        assert not (folder / "scene").exists()
        return
    from brave6d.core.calibration_io import camera_poses
    from brave6d.core.layout import SceneDir

    for _, T in camera_poses(SceneDir(folder / "scene")):
        assert np.isfinite(T).all() and np.abs(T[:3, 3]).max() <= 1e6
    assert math.isfinite(value)


# ============================================================================= class 6: spec and init
def _spec(folder: Path, mesh: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "spec.yaml"
    path.write_text(
        "name: evil\ncapture: {target: [0.45, 0, 0.01], distances_m: [0.3], views_per_distance: 10}\n"
        "workspace: {min: [0, -0.6, 0.02], max: [0.9, 0.6, 0.9]}\n"
        f"objects:\n  - {{name: pw, category: industry, mesh: {mesh}, scale: 0.001, pose: {{xyz: [0.43, 0, 0]}}}}\n")
    return path


def test_a_spec_naming_a_file_that_is_no_mesh_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = _spec(tmp_path, "/etc/passwd")
    line = _one_line_error(capsys, "spec", str(spec))
    assert "field 'objects[0].mesh': '/etc/passwd' is not a mesh file" in line, line
    _one_line_error(capsys, "init", str(spec), str(tmp_path / "scene"))
    assert not (tmp_path / "scene").exists()


def test_init_that_fails_leaves_nothing_behind(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A mesh link to a file without an extension: no sidecar shares its stem, the copy misses it and
    the copied spec fails its check, after assets/ was made. Nothing of it must remain."""
    (tmp_path / "secret").write_bytes(SECRET)
    (tmp_path / "spec").mkdir()
    (tmp_path / "spec" / "cube.ply").symlink_to(tmp_path / "secret")
    spec = _spec(tmp_path / "spec", "cube.ply")
    line = _one_line_error(capsys, "init", str(spec), str(tmp_path / "scene"))
    assert "assets/secret" in line, line
    assert not (tmp_path / "scene").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no staging folder either
    existing = tmp_path / "existing"
    (existing / "capture").mkdir(parents=True)
    (existing / "capture" / "frames.jsonl").write_text("")
    _one_line_error(capsys, "init", str(spec), str(existing))
    assert sorted(p.relative_to(existing).as_posix() for p in existing.rglob("*")) == ["capture", "capture/frames.jsonl"]


"""Hostile files, round 3 (issue #65, classes 2, 3 and 7): every file OpenCV would parse is read by
our own bounded reader first, FIFOs and devices are refused unread, every path field of a shared
dataset resolves inside its folder before anything is read, and a points PLY is read in one pass.

Each case is one line naming the file and the field (CLI exit status 2), within the command's usual
time: no segfault (OpenCV's parser crashed on an ArUco dictionary file nested 100,000 deep), no
hang (a FIFO), no MemoryError (``/dev/zero``), no traceback.
"""

from __future__ import annotations

import os
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_hostile_imports import _import_refused
from test_import_capture import object_capture
from test_input_messages import _one_line_error

from brave6d.core.aruco_dictionary import MAX_FILE_MARKERS, read_dictionary_file, write_dictionary_file
from brave6d.core.dataset_spec import load_dataset_spec
from brave6d.core.errors import DataError, SpecError
from brave6d.core.json_input import read_json_file
from brave6d.core.npy_check import npy_header
from brave6d.core.ply_check import check_ply_header, read_ply_vertices
from brave6d.core.png_check import image_header_problem
from brave6d.core.yaml_io import read_yaml

DEMO = Path(__file__).resolve().parent.parent / "data" / "demo"
DEEP = 100_000


def _within(seconds: float, fn: Callable[[], object], fifo: Path | None = None) -> BaseException | None:
    """The exception ``fn`` raises, which it must do within ``seconds`` (a reader that waits on a
    FIFO fails the test instead of hanging it: the FIFO is then opened for writing, which frees it)."""
    outcome: list[BaseException | None] = []

    def run() -> None:
        try:
            fn()
            outcome.append(None)
        except BaseException as exc:  # noqa: BLE001 - the outcome is what is checked
            outcome.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    if thread.is_alive():
        if fifo is not None:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail(f"the reader still runs after {seconds} s (it waits on a FIFO or reads without end)")
    return outcome[0]


# ============================================================================= class 2: ArUco dictionary files
NESTED = {
    "yml": "%YAML:1.0\n---\nnmarkers: 17\n" + "".join(" " * i + f"k{i}:\n" for i in range(1, 2000))
           + "a: " + "[" * DEEP + "]" * DEEP + "\n",
    "json": '{"nmarkers": 17, "a": ' + "[" * DEEP + "]" * DEEP + "}",
    "xml": '<?xml version="1.0"?>\n<opencv_storage>\n' + "<a>" * DEEP + "</a>" * DEEP + "\n</opencv_storage>\n",
}


@pytest.mark.parametrize("fmt", sorted(NESTED))
def test_a_dictionary_file_nested_100000_deep_is_one_line_not_a_crash(tmp_path: Path, fmt: str) -> None:
    """OpenCV's FileStorage segfaulted on these (exit -11, in ``spec``, ``dataset run``, ``calibrate
    folder``); our reader refuses any nesting in one linear pass."""
    path = tmp_path / f"deep.{fmt}"
    path.write_text(NESTED[fmt])
    t0 = time.perf_counter()
    with pytest.raises(ValueError) as info:
        read_dictionary_file(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and time.perf_counter() - t0 < 5
    assert "nested too deeply" in message or "not an OpenCV YAML/JSON/XML dictionary file" in message


def test_a_dictionary_of_100000_markers_is_refused_from_its_count(tmp_path: Path) -> None:
    path = tmp_path / "many.yml"
    path.write_text("%YAML:1.0\n---\nnmarkers: 100000\nmarkersize: 4\n"
                    + "".join(f'marker_{i}: "{"01" * 8}"\n' for i in range(100_000)))
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=rf"{path}: more than \d+ entries \(a dictionary of at most {MAX_FILE_MARKERS}"):
        read_dictionary_file(path)
    assert time.perf_counter() - t0 < 5


@pytest.mark.parametrize("fmt", ["yml", "json", "xml"])
def test_opencvs_own_files_still_read_as_opencv_reads_them(tmp_path: Path, fmt: str) -> None:
    made = cv2.aruco.extendDictionary(40, 6, randomSeed=7)
    ours = read_dictionary_file(write_dictionary_file(made, tmp_path / f"d.{fmt}"))
    assert np.array_equal(ours.bytesList, made.bytesList) and ours.markerSize == 6
    assert ours.maxCorrectionBits == made.maxCorrectionBits


def test_a_fifo_or_a_device_named_as_a_file_is_refused_unread(tmp_path: Path) -> None:
    """A FIFO made ``open`` wait for a writer forever; ``/dev/zero`` ran out of memory."""
    fifo = tmp_path / "dict.yml"
    os.mkfifo(fifo)
    for reader in (read_dictionary_file, read_json_file, read_yaml, npy_header, check_ply_header):
        exc = _within(10, lambda r=reader: r(fifo), fifo)  # type: ignore[misc]
        assert isinstance(exc, (ValueError, DataError)) and "FIFO" in str(exc) and "\n" not in str(exc), (reader, exc)
    assert "FIFO" in str(image_header_problem(fifo))
    exc = _within(10, lambda: read_dictionary_file("/dev/zero"))
    assert isinstance(exc, ValueError) and "character device" in str(exc), exc


def test_spec_and_calibrate_refuse_a_nested_dictionary_file_in_one_line(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "deep.json").write_text(NESTED["json"])
    spec = yaml.safe_load((DEMO / "scene.yaml").read_text())
    spec["board"] = {k: v for k, v in spec.get("board", {}).items() if k != "dictionary"}
    spec["board"]["dictionary_file"] = "deep.json"
    (tmp_path / "meshes").symlink_to(DEMO / "meshes")
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(spec))
    line = _one_line_error(capsys, "spec", str(tmp_path / "scene.yaml"))
    assert "field 'board'" in line and "deep.json" in line and "nested too deeply" in line, line
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "00.png"), np.full((48, 64), 128, np.uint8))
    np.save(tmp_path / "poses.npy", np.eye(4)[None])
    line = _one_line_error(capsys, "calibrate", "folder", str(tmp_path / "images"), "--poses",
                           str(tmp_path / "poses.npy"), "--dictionary-file", str(tmp_path / "deep.json"),
                           "--out", str(tmp_path / "out"))
    assert "deep.json" in line and "nested too deeply" in line, line


# ============================================================================= class 3: a dataset's path fields
@pytest.fixture()
def shared_dataset(tmp_path: Path) -> Path:
    """The demo dataset copied, its meshes beside it, and a valid dictionary file outside its folder."""
    root = tmp_path / "dataset"
    root.mkdir()
    for item in DEMO.iterdir():
        if item.is_dir():
            shutil.copytree(item, root / item.name)
        else:
            (root / item.name).write_bytes(item.read_bytes())
    write_dictionary_file(cv2.aruco.extendDictionary(40, 5, randomSeed=1), tmp_path / "outside.yml")
    return root


def _board_file(dataset: Path, name: str) -> None:
    spec = yaml.safe_load((dataset / "scene.yaml").read_text())
    spec["board"] = {k: v for k, v in spec.get("board", {}).items() if k != "dictionary"}
    spec["board"]["dictionary_file"] = name
    (dataset / "scene.yaml").write_text(yaml.safe_dump(spec))


@pytest.mark.parametrize("name", ["../outside.yml", "ABSOLUTE", "/dev/zero"])
def test_a_dataset_scene_naming_a_dictionary_file_outside_its_folder_is_refused(shared_dataset: Path,
                                                                               name: str) -> None:
    """The file was read and copied into ``scenes/<scene>/assets/board/``; /dev/zero gave a
    MemoryError traceback after 3.4 GB."""
    name = str(shared_dataset.parent / "outside.yml") if name == "ABSOLUTE" else name
    _board_file(shared_dataset, name)
    with pytest.raises(SpecError) as info:
        load_dataset_spec(shared_dataset / "dataset.yaml")
    message = str(info.value)
    assert "field 'board.dictionary_file'" in message and "lies outside" in message and "\n" not in message, message


def test_a_dataset_scene_naming_a_dictionary_file_inside_its_folder_loads(shared_dataset: Path) -> None:
    (shared_dataset / "board.yml").write_bytes((shared_dataset.parent / "outside.yml").read_bytes())
    _board_file(shared_dataset, "board.yml")
    dataset = load_dataset_spec(shared_dataset / "dataset.yaml")
    board = next(s for s in dataset.scenes if s.spec_file.name == "scene.yaml").spec.board
    assert board.dictionary_file == shared_dataset / "board.yml"


# ============================================================================= class 7: points PLY
def test_a_points_ply_with_a_list_property_is_refused_at_once(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """A 10 MB file took minutes and 1.2 GB in plyfile's row-by-row reader before it was refused."""
    source, _ = object_capture(tmp_path / "src")
    rows = 10 * 2**20 // 13
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {rows}\nproperty float x\nproperty float y\n"
            "property float z\nproperty list uchar int extra\nend_header\n").encode()
    (tmp_path / "src" / "points.ply").write_bytes(head + bytes(13 * rows))
    t0 = time.perf_counter()
    line = _import_refused(capsys, source, tmp_path / "scene")
    assert "points.ply: vertex property 'extra' is a list" in line and time.perf_counter() - t0 < 30, line


def test_a_face_list_claiming_4e9_indices_after_the_points_is_never_read(tmp_path: Path) -> None:
    """plyfile read the faces too: a list length of 4e9 was a traceback. A point cloud's reader reads
    its vertex rows and stops."""
    path = tmp_path / "points.ply"
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uint int vertex_indices\nend_header\n")
    path.write_bytes(head + np.arange(6, dtype="<f4").tobytes() + np.uint32(4_000_000_000).tobytes() + bytes(12))
    columns = read_ply_vertices(path)
    assert sorted(columns) == ["x", "y", "z"] and columns["z"].tolist() == [2.0, 5.0]


@pytest.mark.parametrize("body, says", [
    (b"0 0 0\n1 1\n", "vertex rows unreadable"),
    (b"0 0 0\n", "vertex rows unreadable"),
])
def test_short_or_ragged_ascii_points_are_one_line(tmp_path: Path, body: bytes, says: str) -> None:
    path = tmp_path / "p.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                     b"property float z\nend_header\n" + body + b"          ")
    with pytest.raises(DataError, match=says) as info:
        read_ply_vertices(path)
    assert "\n" not in str(info.value)


@given(fmt=st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]), rows=st.integers(0, 5),
       body=st.binary(max_size=120), extra=st.sampled_from(["", "property list uchar int idx\n", "property uchar red\n"]))
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_any_points_ply_body_reads_or_is_one_line(tmp_path: Path, fmt: str, rows: int, body: bytes, extra: str) -> None:
    path = tmp_path / "p.ply"
    path.write_bytes(f"ply\nformat {fmt} 1.0\nelement vertex {rows}\nproperty float x\nproperty float y\n"
                     f"property float z\n{extra}end_header\n".encode() + body)
    try:
        columns = read_ply_vertices(path)
    except DataError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    assert all(len(c) == rows for c in columns.values()) and {"x", "y", "z"} <= set(columns)

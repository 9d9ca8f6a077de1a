"""Hostile inputs for the readers (issue #44, classes 1 and 3): the one JSON reader
(:mod:`brave6d.core.json_input`: size, depth and number limits), image headers held to the pixel
limit before any decode (:mod:`brave6d.core.png_check`) and ``.npy`` headers checked before any
allocation (:mod:`brave6d.core.npy_check`). Every case is one line naming the file (CLI exit 2,
HTTP 4xx/503), never a traceback or a 500."""

from __future__ import annotations

import hashlib
import json
import math
import re
import struct
import tracemalloc
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from test_input_messages import _one_line_error
from test_release import release, workdir  # noqa: F401  (module fixtures: a release of two scenes)

from brave6d.cli import main
from brave6d.core.atomic import read_png, write_png
from brave6d.core.errors import DataError
from brave6d.core.json_input import JsonInputError, JsonLimits, parse_json
from brave6d.core.npy_check import npy_header
from brave6d.core.png_check import MAX_PIXELS, image_header_problem

HUGE = "9" * 5000  # CPython refuses int() of more than 4300 digits with a ValueError


def _png(width: int, height: int, depth: int = 16, colour: int = 0, body: bytes | None = None) -> bytes:
    """A PNG whose IHDR claims ``width`` x ``height`` (valid CRCs), with a tiny IDAT or ``body``."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + (body if body is not None else chunk(b"IDAT", zlib.compress(bytes(64))))
            + chunk(b"IEND", b""))


def _resign_bundle(bundle: Path, rel: str) -> None:
    """Re-sign one file of a bundle in its manifest (a hostile author re-signs what they change)."""
    manifest = json.loads((bundle / "manifest.json").read_text())
    data = (bundle / rel).read_bytes()
    manifest["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    (bundle / "manifest.json").write_text(json.dumps(manifest))


# ============================================================================= class 1: JSON
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-10**30, 10**30) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=30)


@given(value=JSON_VALUES)
def test_valid_json_reads_as_json_loads_does(value: object) -> None:
    text = json.dumps(value)
    assert parse_json(text, "doc.json") == json.loads(text)
    assert parse_json(text.encode(), "doc.json") == json.loads(text)


@st.composite
def _with_a_hostile_number(draw: st.DrawFn) -> tuple[str, str, str]:
    """A JSON document with one hostile number at a random place: (text, its field, what is said)."""
    keys = draw(st.lists(st.one_of(st.integers(0, 3), st.from_regex(r"[a-z]{1,6}", fullmatch=True)), min_size=1,
                         max_size=6))
    literal, says = draw(st.sampled_from([(HUGE, "5000 characters"), ("-" + HUGE, "5001 characters"),
                                          ("1" + "0" * 150 + ".5", "characters"), ("1e999", "overflows"),
                                          ("-1e400", "overflows"), ("NaN", "NaN"), ("Infinity", "Infinity"),
                                          ("-Infinity", "-Infinity")]))
    text, field = literal, ""
    for key in reversed(keys):
        if isinstance(key, int):
            text = "[" + "0, " * key + text + "]"
        else:
            text = json.dumps({key: "x"})[:-5] + text + "}"
    for key in keys:
        field += f"[{key}]" if isinstance(key, int) else (f".{key}" if field else key)
    return text, field, says


@given(case=_with_a_hostile_number())
def test_a_hostile_number_anywhere_is_one_line_naming_the_field(case: tuple[str, str, str]) -> None:
    text, field, says = case
    with pytest.raises(JsonInputError) as info:
        parse_json(text, "scene.json")
    message = str(info.value)
    assert message.startswith(f"scene.json: field '{field}': ") and says in message and "\n" not in message, message


@given(data=st.binary(max_size=300))
@settings(max_examples=300)
def test_any_bytes_are_json_or_a_json_input_error(data: bytes) -> None:
    try:
        parse_json(data, "message")
    except JsonInputError as exc:
        assert str(exc).startswith("message: ") and "\n" not in str(exc)


@pytest.mark.parametrize("text, says", [
    ("[" * 65 + "]" * 65, "nested too deeply (65 levels"),
    ('{"a": ' * 100 + "1" + "}" * 100, "nested too deeply (100 levels"),
    ("[" * 200_000, "nested too deeply"),
])
def test_depth_is_refused_before_parsing(text: str, says: str) -> None:
    with pytest.raises(JsonInputError, match=r"^doc\.json: JSON " + re.escape(says)):
        parse_json(text, "doc.json")


def test_brackets_inside_strings_do_not_count_as_nesting() -> None:
    text = json.dumps({"a": "[" * 1000, "b": ["]{\"" * 50]})
    assert parse_json(text, "doc.json") == json.loads(text)
    assert parse_json("[" * 64 + "]" * 64, "doc.json") is not None


def test_size_is_refused_before_reading(tmp_path: Path) -> None:
    path = tmp_path / "big.json"
    path.write_text("[" + "0," * 600 + "0]")
    with pytest.raises(JsonInputError, match=rf"{path}: 1203 bytes of JSON \(at most 1024 are read\)"):
        from brave6d.core.json_input import read_json_file

        read_json_file(path, JsonLimits(max_bytes=1024))


def test_non_finite_numbers_pass_when_the_caller_checks_them_itself() -> None:
    value = parse_json('[NaN, Infinity, 1e999]', "body", JsonLimits(finite=False))
    assert math.isnan(value[0]) and value[1] == value[2] == math.inf


def test_release_verify_refuses_a_5000_digit_integer_in_its_manifest(tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Before the one reader: a ValueError traceback (int() of more than 4300 digits)."""
    root = tmp_path / "release"
    root.mkdir()
    (root / "manifest.json").write_text('{"format": "brave6d-release/1", "name": "x", "version": ' + HUGE + "}")
    digest = hashlib.sha256((root / "manifest.json").read_bytes()).hexdigest()
    (root / "SHA256SUMS").write_text(f"{digest}  manifest.json\n")
    line = _one_line_error(capsys, "release", "verify", str(root))
    assert f"{root / 'manifest.json'}: field 'version': a number of 5000 characters" in line, line


def test_bop_scene_gt_with_a_5000_digit_obj_id_names_the_file_and_field(tmp_path: Path) -> None:
    from brave6d.annotation import read_scene_gt

    path = tmp_path / "scene_gt.json"
    path.write_text('{"1": [{"cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,500], "obj_id": ' + HUGE + "}]}")
    with pytest.raises(DataError, match=rf"{path}: field '\['1'\]\[0\]\.obj_id': a number of 5000 characters"):
        read_scene_gt(path)


@pytest.mark.parametrize("value, says", [(HUGE, "a number of 5000 characters"), ("NaN", "NaN is not a JSON number")])
def test_transforms_json_fl_x_with_5000_digits_or_nan_is_refused_at_import(tmp_path: Path, value: str,
                                                                          says: str) -> None:
    from brave6d.training.importing.transforms_source import read_transforms

    (tmp_path / "transforms.json").write_text('{"fl_x": ' + value + ', "frames": []}')
    with pytest.raises(DataError, match=rf"transforms\.json: field 'fl_x': {says}"):
        read_transforms(tmp_path)


def test_a_yaml_integer_of_5000_digits_is_one_line(tmp_path: Path) -> None:
    from brave6d.core.yaml_io import read_yaml

    path = tmp_path / "poses.yaml"
    path.write_text("pose:\n  x: " + HUGE + "\n")
    with pytest.raises(DataError, match=rf"{path}:2:6: invalid YAML: a number of 5000 characters"):
        read_yaml(path)


@pytest.fixture(scope="module")
def bundle_copy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.serve import make_synthetic_bundle

    return make_synthetic_bundle(tmp_path_factory.mktemp("hostile"), n_gaussians=2000)


def _bundle(bundle_copy: Path, tmp_path: Path) -> Path:
    import shutil

    return Path(shutil.copytree(bundle_copy, tmp_path / "bundle"))


def _episode_status(bundle: Path, tmp_path: Path, tamper: Callable[[], None] | None = None) -> tuple[int, str]:
    """(status, error) of the first reset on a server of ``bundle``; ``tamper`` runs after the server
    started (a file changed under a running server, as a release's cache can be)."""
    from fastapi.testclient import TestClient

    from brave6d.serve import create_app, open_scenes

    app = create_app(open_scenes(bundle, device="cpu", warm_up=False), device="cpu", log_dir=tmp_path / "episodes")
    if tamper is not None:
        tamper()
    with TestClient(app, base_url="http://localhost", raise_server_exceptions=False) as client:
        r = client.post("/episodes", json={})
        return r.status_code, r.json()["error"] if r.status_code >= 400 else ""


@pytest.mark.slow
def test_serve_answers_503_not_500_for_a_5000_digit_integer_in_a_bundle_manifest(bundle_copy: Path,
                                                                                 tmp_path: Path) -> None:
    """Before the one reader: HTTP 500 (a ValueError out of the catalog's load, which re-reads the
    manifest when the scene is first needed, as it does for a release's unpacked bundle)."""
    bundle = _bundle(bundle_copy, tmp_path)

    def tamper() -> None:
        text = (bundle / "manifest.json").read_text()
        (bundle / "manifest.json").write_text(re.sub(r'"bytes": \d+', f'"bytes": {HUGE}', text, count=1))

    status, error = _episode_status(bundle, tmp_path, tamper)
    assert status == 503 and "manifest.json: field 'files['" in error and "a number of 5000" in error, (status, error)


@pytest.mark.slow
def test_serve_start_with_a_5000_digit_integer_in_the_manifest_is_one_line(bundle_copy: Path, tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Before the one reader: a traceback at start (core/atomic.py read_json)."""
    bundle = _bundle(bundle_copy, tmp_path)
    text = (bundle / "manifest.json").read_text()
    (bundle / "manifest.json").write_text(re.sub(r'"bytes": \d+', f'"bytes": {HUGE}', text, count=1))
    line = _one_line_error(capsys, "serve", str(bundle), "--port", "0", "--device", "cpu")
    assert "manifest.json: field 'files['" in line and "'].bytes': a number of 5000 characters" in line, line


def test_http_and_websocket_bodies_with_5000_digits_or_deep_nesting_are_400(bundle_copy: Path,
                                                                           tmp_path: Path) -> None:
    from fastapi.testclient import TestClient

    from brave6d.serve import create_app

    app = create_app(bundle_copy, device="cpu", log_dir=tmp_path / "episodes")
    with TestClient(app, base_url="http://localhost") as client:
        for body in ('{"seed": ' + HUGE + "}", '{"seed": ' + "[" * 100 + "]" * 100 + "}"):
            r = client.post("/episodes", content=body, headers={"content-type": "application/json"})
            assert r.status_code == 400 and r.json()["error"].startswith("malformed JSON: "), r.text
        eid = client.post("/episodes", json={}).json()["episode_id"]
        with client.websocket_connect(f"ws://localhost/episodes/{eid}/ws") as ws:
            ws.send_text('{"op": "get", "request_id": ' + HUGE + "}")
            reply = json.loads(ws.receive_text())
        assert reply["status"] == 400 and "a number of 5000 characters" in reply["error"], reply


# ============================================================================= class 3: images and arrays
def test_estimate_frame_with_a_depth_png_claiming_100000_squared_is_one_line(tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Before the header check: a cv2.error traceback from cv2.imread."""
    depth = tmp_path / "depth.png"
    depth.write_bytes(_png(100_000, 100_000))
    model = next(Path(__file__).parent.glob("data/real/*/models_eval/*.ply"))
    line = _one_line_error(capsys, "estimate", "frame", "--depth", str(depth), "--K", "500,500,320,240",
                           "--model", str(model), "--pixel", "10,10")
    assert f"{depth}: declares 100000x100000 pixels" in line, line


@pytest.mark.parametrize("kind", ["png", "jpg"])
def test_an_imported_image_bomb_is_one_line_naming_the_frame(tmp_path: Path, kind: str) -> None:
    """Before the header check: Pillow's DecompressionBombError, which is no OSError."""
    from PIL import Image

    from brave6d.training.importing.image_io import read_frame_image

    path = tmp_path / f"bomb.{kind}"
    if kind == "png":
        path.write_bytes(_png(100_000, 100_000, depth=8, colour=2))
    else:
        Image.new("RGB", (8, 8)).save(path)
        data = bytearray(path.read_bytes())
        at = data.find(b"\xff\xc0")
        data[at + 5:at + 9] = struct.pack(">HH", 60_000, 60_000)
        path.write_bytes(bytes(data))
    with pytest.raises(DataError, match=rf"frame f1: {path}: declares"):
        read_frame_image(path, (640, 480), "f1")


def test_read_png_checks_the_header_before_decoding(tmp_path: Path) -> None:
    path = tmp_path / "x.png"
    path.write_bytes(_png(9000, 9000, depth=8, colour=2))
    with pytest.raises(DataError, match=rf"{path}: declares 9000x9000 pixels \(at most {MAX_PIXELS} are read\)"):
        read_png(path)
    ok = write_png(tmp_path / "ok.png", np.zeros((4, 5, 3), np.uint8))
    assert read_png(ok, "rgb").shape == (4, 5, 3)


@given(width=st.integers(0, 2**31 - 1), height=st.integers(0, 2**31 - 1))
def test_a_png_header_is_refused_exactly_when_it_claims_too_many_pixels(width: int, height: int) -> None:
    problem = image_header_problem(_png(width, height))
    assert (problem is None) == (0 < width * height <= MAX_PIXELS), problem


@given(data=st.binary(max_size=200), png=st.booleans())
@settings(max_examples=200)
def test_any_bytes_give_an_image_header_verdict_not_an_exception(data: bytes, png: bool) -> None:
    problem = image_header_problem((b"\x89PNG\r\n\x1a\n" if png else b"") + data)
    assert problem is None or "\n" not in problem


def test_calibrate_folder_npy_header_declaring_12_gib_is_refused_before_allocating(tmp_path: Path) -> None:
    """Before the header check: np.load allocates 11.9 GiB first (_ArrayMemoryError where memory is not
    overcommitted)."""
    from brave6d.calibration.pose_files import PoseFileError, read_pose_collection

    path = tmp_path / "poses.npy"
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": "<f8", "fortran_order": False,
                                                      "shape": (100_000_000, 4, 4)})
        handle.write(bytes(128))
    tracemalloc.start()
    try:
        with pytest.raises(PoseFileError, match=rf"{path}: its header declares an array of shape \(100000000, 4, 4\)"):
            read_pose_collection(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, peak


@given(shape=st.lists(st.integers(0, 2**20), max_size=4), extra=st.integers(-16, 16),
       dtype=st.sampled_from(["<f8", "<i4", "|u1", "|O"]))
@settings(max_examples=60, deadline=None)
def test_an_npy_header_is_read_only_when_it_matches_its_data(tmp_path_factory: pytest.TempPathFactory,
                                                             shape: list[int], extra: int, dtype: str) -> None:
    path = tmp_path_factory.mktemp("npy") / "a.npy"
    itemsize = np.dtype(dtype).itemsize
    nbytes = math.prod(shape) * itemsize
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": dtype, "fortran_order": False, "shape": tuple(shape)})
        written = handle.write(bytes(max(0, min(nbytes, 1 << 16) + extra)))
    good = dtype != "|O" and nbytes <= 1 << 16 and written == nbytes
    try:
        assert npy_header(path) == (tuple(shape), np.dtype(dtype)) and good
    except DataError as exc:
        assert not good and str(exc).startswith(f"{path}: ") and "\n" not in str(exc)


def test_a_bundle_whose_holdout_png_is_random_bytes_is_503_not_201(bundle_copy: Path, tmp_path: Path) -> None:
    """Before the holdout check: ``serve`` answered 201 (the re-signed image was never looked at)."""
    bundle = _bundle(bundle_copy, tmp_path)
    image = sorted((bundle / "holdout").glob("*.png"))[0]
    image.write_bytes(b"\x89PNG\r\n\x1a\n" + np.random.default_rng(0).bytes(5000))
    _resign_bundle(bundle, f"holdout/{image.name}")
    status, error = _episode_status(bundle, tmp_path)
    assert status == 503 and f"holdout/{image.name}: holdout image" in error, (status, error)


@pytest.mark.slow
def test_release_verify_refuses_a_bundle_whose_holdout_png_is_random_bytes(release: Path, tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Before: ``release verify`` passed (only the bundle's JSON files and hashes were checked)."""
    import shutil

    from test_release import NAME, _resum, _rewrite_zip

    copy = Path(shutil.copytree(release, tmp_path / "copy"))
    zip_path = copy / f"{NAME}_bundle_000001.zip"
    with zipfile.ZipFile(zip_path) as zf:
        member = next(n for n in zf.namelist() if "/holdout/" in n and n.endswith(".png"))
        manifest = json.loads(zf.read("bundles/000001/manifest.json"))
    junk = b"\x89PNG\r\n\x1a\n" + np.random.default_rng(1).bytes(4000)
    manifest["files"][member.removeprefix("bundles/000001/")] = {"sha256": hashlib.sha256(junk).hexdigest(),
                                                                  "bytes": len(junk)}
    _rewrite_zip(zip_path, replace={member: junk, "bundles/000001/manifest.json": json.dumps(manifest).encode()})
    _resum(copy)
    line = _one_line_error(capsys, "release", "verify", str(copy))
    assert f"{zip_path.name}:{member}: not a PNG" in line, line

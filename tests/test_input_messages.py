"""Bad inputs end in one line naming the file and the field: YAML nested thousands deep or with a
duplicate key, a captured PNG of the wrong size, NaN/inf anywhere in stored intrinsics."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from brave6d.annotation.threedat import ThreeDatError, read_threedat
from brave6d.core.atomic import read_png, write_png
from brave6d.core.calibration_io import read_camera_json
from brave6d.core.camera import PinholeCamera
from brave6d.cli import main
from brave6d.core.errors import DataError, SpecError
from brave6d.core.spec import load_scene_spec
from brave6d.core.yaml_io import MAX_DEPTH, parse_yaml

FIXTURE = Path(__file__).parent / "fixtures" / "threedat"
KEYS = st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True).filter(
    lambda k: k not in {"y", "n", "yes", "no", "on", "off", "true", "false", "null"})
SCALARS = st.one_of(st.integers(-1000, 1000), st.from_regex(r"[a-z]{1,6}", fullmatch=True))


def _one_line_error(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """Run the CLI in-process; it must fail with status 2 and exactly one line on stderr."""
    status = main(list(argv))
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2 and len(lines) == 1, err[-2000:]
    return lines[0]


# ----------------------------------------------------------------------------- nesting
@pytest.mark.parametrize("style", ["flow", "block"])
def test_yaml_nested_thousands_deep_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                style: str) -> None:
    """`brave6d spec` on a spec nested 5,000 deep: one line with file:line, not a RecursionError traceback."""
    depth = 5000
    if style == "flow":
        text = "name: x\ncapture: " + "[" * depth + "]" * depth + "\n"
    else:
        text = "name: x\ncapture:\n" + "".join(" " * i + f"k{i}:\n" for i in range(1, depth)) + " " * depth + "v: 1\n"
    spec = tmp_path / "scene.yaml"
    spec.write_text(text)
    line = _one_line_error(capsys, "spec", str(spec))
    row = 2 if style == "flow" else MAX_DEPTH + 1  # where the node one level too deep starts
    assert f"{spec}:{row}:" in line and f"nested deeper than {MAX_DEPTH} levels" in line, line


def test_yaml_at_the_depth_limit_still_loads() -> None:
    """The cap refuses only what is deeper than MAX_DEPTH (the outermost mapping counts as one)."""
    text = "[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1)
    assert parse_yaml(f"a: {text}")["a"] is not None
    with pytest.raises(yaml.YAMLError, match="nested deeper"):
        parse_yaml(f"a: [{text}]")


def test_cli_turns_any_recursion_error_into_one_line(monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Whatever else recurses without end (a deep JSON, a cyclic structure) is one line, status 2."""
    import brave6d.spec_cli

    def endless(args: object) -> int:
        return endless(args)

    monkeypatch.setattr(brave6d.spec_cli, "run", endless)
    line = _one_line_error(capsys, "spec", "any.yaml")
    assert line.startswith("brave6d spec: error:") and "nested too deeply" in line, line


def test_json_nested_thousands_deep_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "intrinsics.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(DataError, match=rf"{re.escape(str(path))}: JSON nested too deeply"):
        read_camera_json(path, "camera")


# ----------------------------------------------------------------------------- duplicate keys
@given(data=st.dictionaries(KEYS, SCALARS, min_size=1, max_size=8), pick=st.integers(0, 7), other=SCALARS)
def test_duplicate_yaml_key_is_refused_with_its_line(data: dict, pick: int, other: object) -> None:
    """Any mapping with one key repeated: refused at the second occurrence's line; without it, as safe_load."""
    text = yaml.safe_dump(data, sort_keys=False)
    assert parse_yaml(text) == yaml.safe_load(text)
    keys = list(data)
    key = keys[pick % len(keys)]
    doubled = text + yaml.safe_dump({key: other})
    with pytest.raises(yaml.YAMLError) as info:
        parse_yaml(doubled)
    assert info.value.problem_mark.line + 1 == len(keys) + 1  # the appended line
    assert f"duplicate key {key!r} (first at line {keys.index(key) + 1})" in str(info.value)


def test_duplicate_key_in_a_spec_names_file_and_line(tmp_path: Path, demo_spec_path: Path) -> None:
    lines = demo_spec_path.read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("name:"))
    lines.insert(at + 1, "name: second_name")
    spec = tmp_path / "scene.yaml"
    spec.write_text("\n".join(lines) + "\n")
    with pytest.raises(SpecError) as info:
        load_scene_spec(spec, check_files=False)
    assert str(info.value) == (f"{spec}:{at + 2}:1: invalid YAML: duplicate key 'name' (first at line {at + 1})")


def test_merge_keys_may_still_override(tmp_path: Path) -> None:
    """``<<`` merges are not duplicates: explicit keys override merged ones, as YAML says."""
    assert parse_yaml("base: &b {a: 1, b: 2}\nuse: {<<: *b, b: 3}\n")["use"] == {"a": 1, "b": 3}


def test_duplicate_key_in_a_threedat_file_names_file_and_line(tmp_path: Path) -> None:
    dat = Path(shutil.copytree(FIXTURE, tmp_path / "dat"))
    lib = dat / "objects" / "object_library.yaml"
    lib.write_text("- id: cube\n  id: bar\n")
    with pytest.raises(ThreeDatError, match=r"object_library.yaml:2:3: invalid YAML: duplicate key 'id' \(first at line 1\)"):
        read_threedat(dat)


# ----------------------------------------------------------------------------- image size
def test_read_png_checks_the_size_and_names_the_file(tmp_path: Path) -> None:
    path = write_png(tmp_path / "f.png", np.zeros((10, 12, 3), np.uint8))
    assert read_png(path, "rgb", (12, 10)).shape == (10, 12, 3)
    with pytest.raises(DataError, match=rf"^{re.escape(str(path))}: image is 12x10, the camera in x.json is 64x48$"):
        read_png(path, "rgb", (64, 48), "the camera in x.json")


def test_wrong_size_capture_png_names_the_file_and_the_camera(tmp_path: Path) -> None:
    """Training on a capture with one frame of the wrong size: the message names that file and the
    intrinsics it disagrees with; --skip-bad-frames trains without it."""
    from brave6d.training.views import load_scene
    from brave6d.training.toy_scenes import plane_views, write_scene

    camera = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    scene = write_scene(tmp_path / "scene", camera, plane_views(camera, [0.4, 0.5], 6))
    bad = scene.capture_dir / "rgb" / "000005.png"
    write_png(bad, np.zeros((10, 12, 3), np.uint8))
    with pytest.raises(DataError) as info:
        load_scene(scene)
    assert f"{bad}: image is 12x10, the camera in {scene.intrinsics_path} is 64x48" in str(info.value)
    assert [s.index for s in load_scene(scene, skip_bad_frames=True).skipped] == [5]


# ----------------------------------------------------------------------------- NaN intrinsics
CAMERA = {"width": 64, "height": 48, "K": [[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]],
          "dist": [0.1, -0.05, 0.001, 0.002, 0.01]}
NUMBERS = [("width",), ("height",), *((("K", i, j) for i in range(3) for j in range(3))),
           *((("dist", k) for k in range(5)))]


def _field_name(where: tuple) -> str:
    return where[0] + "".join(f"[{i}]" for i in where[1:])


@given(where=st.sampled_from(NUMBERS), bad=st.sampled_from([math.nan, math.inf, -math.inf]))
def test_nan_or_inf_anywhere_in_intrinsics_names_file_and_field(tmp_path_factory: pytest.TempPathFactory,
                                                                where: tuple, bad: float) -> None:
    camera = json.loads(json.dumps(CAMERA))
    target = camera
    for step in where[:-1]:
        target = target[step]
    target[where[-1]] = bad
    path = tmp_path_factory.mktemp("cal") / "intrinsics.json"
    path.write_text(json.dumps({"camera": camera}))
    with pytest.raises(DataError) as info:
        read_camera_json(path, "camera")
    message = str(info.value)
    assert message.startswith(f"{path}: field 'camera.{_field_name(where)}': ") and "\n" not in message, message
    assert ("finite" in message) or ("whole number" in message), message


def test_valid_intrinsics_still_read(tmp_path: Path) -> None:
    path = tmp_path / "intrinsics.json"
    path.write_text(json.dumps({"camera": CAMERA}))
    camera = read_camera_json(path, "camera")
    assert (camera.width, camera.height, camera.cx, camera.dist[4]) == (64, 48, 31.5, 0.01)


@pytest.mark.parametrize(("edit", "field", "fragment"), [
    (lambda c: c.pop("K"), "camera.K", "is missing"),
    (lambda c: c.update(K=[[50.0, 0.0, 31.5], [0.0, 50.0, 23.5]]), "camera.K", "3x3"),
    (lambda c: c["K"][1].__setitem__(0, 0.5), "camera.K[1][0]", "must be 0"),
    (lambda c: c["K"][0].__setitem__(0, -5.0), "camera.fx", "positive"),
    (lambda c: c.update(width=64.5), "camera.width", "whole number"),
    (lambda c: c.update(dist=[0.1, 0.2]), "camera.dist", "coefficients"),
    (lambda c: c.update(dist=["a"]), "camera.dist", "numbers"),
])
def test_malformed_intrinsics_name_file_and_field(tmp_path: Path, edit, field: str, fragment: str) -> None:
    camera = json.loads(json.dumps(CAMERA))
    edit(camera)
    path = tmp_path / "intrinsics.json"
    path.write_text(json.dumps({"camera": camera}))
    with pytest.raises(DataError, match=rf"^{re.escape(str(path))}: field '{re.escape(field)}': .*{fragment}"):
        read_camera_json(path, "camera")

"""Scene spec validation: the demo spec is valid; every bad value gives one line naming the
file and the field."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from brave6d.core.errors import SpecError
from brave6d.core.spec import load_scene_spec, parse_scene_spec, spec_to_yaml


@pytest.fixture()
def demo_data(demo_spec_path: Path) -> dict:
    return yaml.safe_load(demo_spec_path.read_text())


def test_demo_spec_is_valid(demo_spec_path: Path) -> None:
    spec = load_scene_spec(demo_spec_path)
    assert {o.category.value for o in spec.objects} >= {"industry", "household", "laboratory", "toys_office"}
    assert spec.robot.model == "ur5e"
    assert spec.simulation is not None
    for item in [*spec.objects, *spec.static_meshes]:
        assert spec.resolve(item.mesh).is_file()
    cam = spec.camera.pinhole()
    assert (cam.width, cam.height) == (640, 400) and abs(cam.hfov_deg - 70) < 1e-9


def test_demo_objects_are_small_at_50cm(demo_spec_path: Path) -> None:
    """The paper's 'small' objects: under 32x32 px at 50 cm."""
    import trimesh

    spec = load_scene_spec(demo_spec_path)
    f = spec.camera.pinhole().fx
    for obj in spec.objects:
        mesh = trimesh.load(spec.resolve(obj.mesh), force="mesh")
        extent_m = float(max(mesh.extents)) * obj.scale
        assert extent_m * f / 0.5 < 32.0, f"{obj.name} spans {extent_m * f / 0.5:.1f} px at 50 cm"


def test_spec_yaml_round_trip(demo_spec_path: Path, tmp_path: Path) -> None:
    spec = load_scene_spec(demo_spec_path)
    again = parse_scene_spec(yaml.safe_load(spec_to_yaml(spec)), demo_spec_path, check_files=False)
    assert again.model_dump(exclude={"source"}) == spec.model_dump(exclude={"source"})


def _set(data: dict, dotted: str, value: object) -> dict:
    out = copy.deepcopy(data)
    node = out
    keys = dotted.split(".")
    for key in keys[:-1]:
        node = node[int(key)] if isinstance(node, list) else node[key]
    last = keys[-1]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return out


@pytest.mark.parametrize(
    ("dotted", "value", "field"),
    [
        ("capture.distances_m", [0.2, -0.3], "capture.distances_m[1]"),
        ("capture.views_per_distance", "many", "capture.views_per_distance"),
        ("capture.target", [0.4, 0.0], "capture.target"),
        ("camera.hfov_deg", 200, "camera.hfov_deg"),
        ("camera.width", 0, "camera.width"),
        ("collision_boxes.0.size", [0.8, 0.0, 0.7], "collision_boxes[0].size[1]"),
        ("objects.1.category", "kitchen", "objects[1].category"),
        ("objects.0.scale", 0, "objects[0].scale"),
        ("objects.2.mesh", "meshes/missing.ply", "objects[2].mesh"),
        ("robot.model", "ur7", "robot.model"),
        ("board.dictionary", "DICT_NOPE", "board"),
        ("board.marker_length_m", 0.05, "board"),
        ("simulation.effects.sensor_noise", {"sigma": -1}, "simulation.effects.sensor_noise.sigma"),
        ("simulation.effects.sensor_noise", {"sigmaa": 1}, "simulation.effects.sensor_noise.sigmaa"),
        ("simulation.true_tcp_T_camera", {"xyz": [0, 0, ".nan"]}, "simulation.true_tcp_T_camera.xyz[2]"),
        ("workspace.min", [1.0, 0.0, 0.0], "workspace"),
        ("name", "bad name with spaces", "name"),
    ],
)
def test_bad_values_name_file_and_field(demo_data: dict, demo_spec_path: Path, tmp_path: Path,
                                        dotted: str, value: object, field: str) -> None:
    bad = _set(demo_data, dotted, value)
    path = tmp_path / "scene.yaml"
    text = yaml.safe_dump(bad).replace("'.nan'", ".nan")
    path.write_text(text)
    # relative meshes must resolve like the original spec's
    (tmp_path / "meshes").symlink_to(demo_spec_path.parent / "meshes")
    with pytest.raises(SpecError) as info:
        load_scene_spec(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path)), message
    assert f"field '{field}" in message, message


def test_unknown_top_level_key_is_named(tmp_path: Path) -> None:
    path = tmp_path / "s.yaml"
    path.write_text("name: x\ncapture: {target: [0, 0, 0]}\nworkspace: {min: [0, 0, 0], max: [1, 1, 1]}\ncolour: red\n")
    with pytest.raises(SpecError, match=r"field 'colour': Extra inputs"):
        load_scene_spec(path)


def test_duplicate_object_names_rejected(demo_data: dict, demo_spec_path: Path) -> None:
    bad = copy.deepcopy(demo_data)
    bad["objects"][1]["name"] = bad["objects"][0]["name"]
    with pytest.raises(SpecError, match="duplicate names"):
        parse_scene_spec(bad, demo_spec_path)


@pytest.mark.parametrize(("text", "fragment"), [
    ("name: [unclosed\n", "invalid YAML"),
    ("- just\n- a list\n", "YAML mapping"),
])
def test_malformed_yaml_is_one_line(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "s.yaml"
    path.write_text(text)
    with pytest.raises(SpecError, match=fragment) as info:
        load_scene_spec(path)
    assert "\n" not in str(info.value)


def test_missing_spec_file(tmp_path: Path) -> None:
    with pytest.raises(SpecError, match="not found"):
        load_scene_spec(tmp_path / "nope.yaml")


def test_effects_enabled_lists_only_given(demo_data: dict, demo_spec_path: Path) -> None:
    data = copy.deepcopy(demo_data)
    data["simulation"]["effects"] = {"vignetting": {"strength": 0.2}}
    spec = parse_scene_spec(data, demo_spec_path)
    assert spec.simulation is not None and spec.simulation.effects.enabled() == ["vignetting"]

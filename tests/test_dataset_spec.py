"""The dataset spec (brave6d.core.dataset_spec): library merge, ids by position, one-line errors."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from brave6d.core.dataset_spec import load_dataset_spec, scene_fingerprint
from brave6d.core.errors import SpecError

ROOT = Path(__file__).resolve().parent.parent
DEMO_DATASET = ROOT / "data" / "demo" / "dataset.yaml"
MESHES = ROOT / "data" / "demo" / "meshes"


def _library() -> list[dict[str, Any]]:
    """Meshes beside dataset.yaml (:func:`_write` copies them there: a dataset names files in its folder)."""
    return [
        {"name": "nut", "category": "industry", "mesh": "hex_nut.ply", "scale": 0.001},
        {"name": "vial", "category": "laboratory", "mesh": "sample_vial.ply", "scale": 0.001,
         "symmetry": {"continuous_axes": [[0, 0, 1]]}},
    ]


def _scene(name: str, objects: list[dict[str, Any]]) -> dict[str, Any]:
    return {"name": name, "capture": {"target": [0.45, 0, 0]},
            "workspace": {"min": [0, -0.5, 0], "max": [0.9, 0.5, 0.9]}, "objects": objects}


def _write(tmp: Path, scene_specs: list[dict[str, Any]], **top: Any) -> Path:
    for mesh in ("hex_nut.ply", "sample_vial.ply"):
        shutil.copy(MESHES / mesh, tmp / mesh)
    refs = []
    for i, scene in enumerate(scene_specs):
        (tmp / f"s{i}.yaml").write_text(yaml.safe_dump(scene))
        refs.append({"spec": f"s{i}.yaml"})
    data = {"name": "ds", "version": "1", "license": "CC-BY-4.0", "citation": "@misc{x}", "objects": _library(),
            "scenes": refs, **top}
    path = tmp / "dataset.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


POSE = {"xyz": [0.45, 0, 0]}


def test_demo_dataset_two_scenes_share_objects_and_their_ids() -> None:
    ds = load_dataset_spec(DEMO_DATASET)
    tabletop, workbench = ds.scenes
    assert [s.scene_id for s in ds.scenes] == [1, 2]
    # the tabletop keeps the single demo's ids (sorted names: what the importer assigns on its own)
    assert tabletop.obj_ids == {"espresso_cup": 1, "hex_nut": 2, "sample_vial": 3, "toy_brick": 4}
    shared = set(tabletop.obj_ids) & set(workbench.obj_ids)
    assert shared == {"hex_nut", "sample_vial"}
    assert all(tabletop.obj_ids[n] == workbench.obj_ids[n] for n in shared)
    # the workbench gives only name and pose; the rest comes from the library
    nut = next(o for o in workbench.spec.objects if o.name == "hex_nut")
    lib = next(o for o in ds.spec.objects if o.name == "hex_nut")
    assert nut.category == lib.category and nut.scale == lib.scale and nut.symmetry == lib.symmetry
    assert workbench.spec.resolve(nut.mesh).resolve() == (MESHES / "hex_nut.ply").resolve()
    assert scene_fingerprint(tabletop.spec, tabletop.obj_ids) != scene_fingerprint(workbench.spec, workbench.obj_ids)


def test_name_and_pose_only_and_ids_by_library_position(tmp_path: Path) -> None:
    path = _write(tmp_path, [_scene("a", [{"name": "vial", "pose": POSE}]),
                             _scene("b", [{"name": "nut", "pose": POSE}, {"name": "vial", "pose": POSE}])])
    ds = load_dataset_spec(path)
    assert [s.obj_ids for s in ds.scenes] == [{"vial": 2}, {"nut": 1, "vial": 2}]
    assert ds.scenes[0].spec.objects[0].symmetry is not None


def test_unknown_object_names_the_scene_file_and_field(tmp_path: Path) -> None:
    path = _write(tmp_path, [_scene("a", [{"name": "vial", "pose": POSE}, {"name": "anvil", "pose": POSE}])])
    with pytest.raises(SpecError, match=r"s0\.yaml: field 'objects\[1\]\.name': unknown object 'anvil'"):
        load_dataset_spec(path)


@pytest.mark.parametrize(("field", "value"), [("scale", 0.002), ("category", "household"),
                                              ("description", "another"), ("symmetry", None)])
def test_a_field_that_differs_from_the_library_is_refused(tmp_path: Path, field: str, value: Any) -> None:
    path = _write(tmp_path, [_scene("a", [{"name": "vial", "pose": POSE, field: value}])])
    with pytest.raises(SpecError, match=rf"s0\.yaml: field 'objects\[0\]\.{field}': differs from the library"):
        load_dataset_spec(path)


def test_a_repeated_equal_field_is_accepted_and_a_mesh_is_compared_by_content(tmp_path: Path) -> None:
    copy = Path(shutil.copy(MESHES / "sample_vial.ply", tmp_path / "vial_copy.ply"))
    path = _write(tmp_path, [_scene("a", [{"name": "vial", "pose": POSE, "scale": 0.001, "category": "laboratory",
                                           "mesh": copy.name}])])
    assert load_dataset_spec(path).scenes[0].obj_ids == {"vial": 2}
    other = Path(shutil.copy(MESHES / "hex_nut.ply", tmp_path / "other.ply"))
    path = _write(tmp_path, [_scene("a", [{"name": "vial", "pose": POSE, "mesh": other.name}])])
    with pytest.raises(SpecError, match=r"field 'objects\[0\]\.mesh': other\.ply is not the library's mesh"):
        load_dataset_spec(path)


def test_duplicate_library_and_scene_names(tmp_path: Path) -> None:
    path = _write(tmp_path, [_scene("a", [])], objects=[*_library(), _library()[0]])
    with pytest.raises(SpecError, match=r"dataset\.yaml: field 'objects': duplicate names \['nut'\]"):
        load_dataset_spec(path)
    path = _write(tmp_path, [_scene("a", []), _scene("a", [])])
    with pytest.raises(SpecError, match=r"field 'scenes\[1\]\.spec': scene name 'a' .* already used by scenes\[0\]"):
        load_dataset_spec(path)


@pytest.mark.parametrize(("top", "field"), [({"license": ""}, "license"), ({"scenes": []}, "scenes"),
                                            ({"objects": []}, "objects"), ({"name": ".."}, "name"),
                                            ({"extra": 1}, "extra"), ({"cluster": {"executor": "pbs"}}, "cluster.executor")])
def test_bad_top_level_fields_are_named(tmp_path: Path, top: dict[str, Any], field: str) -> None:
    path = _write(tmp_path, [_scene("a", [])], **top)
    with pytest.raises(SpecError, match=rf"dataset\.yaml: field '{field}'"):
        load_dataset_spec(path)


def test_missing_files_are_named(tmp_path: Path) -> None:
    path = _write(tmp_path, [_scene("a", [])])
    (tmp_path / "s0.yaml").unlink()
    with pytest.raises(SpecError, match=r"field 'scenes\[0\]\.spec': scene spec not found"):
        load_dataset_spec(path)
    with pytest.raises(SpecError, match="dataset spec not found"):
        load_dataset_spec(tmp_path / "nope.yaml")


@given(name=st.text(max_size=12))
def test_any_dataset_name_validates_or_is_named(tmp_path_factory: pytest.TempPathFactory, name: str) -> None:
    tmp = tmp_path_factory.mktemp("name")
    path = _write(tmp, [_scene("a", [])], name=name)
    try:
        ds = load_dataset_spec(path)
    except SpecError as exc:
        assert "dataset.yaml: field 'name'" in str(exc)
    else:  # the one rule of brave6d.core.names (tests/test_names_as_paths.py tries it on every field)
        assert ds.spec.name == name and name not in ("", ".", "..") and name[0] not in ".-"
        assert all(c.isascii() and (c.isalnum() or c in "_.+-") for c in name)


@given(scale=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.just(0.001)))
def test_any_scene_scale_equals_the_library_or_is_refused(tmp_path_factory: pytest.TempPathFactory,
                                                           scale: float) -> None:
    tmp = tmp_path_factory.mktemp("scale")
    path = _write(tmp, [_scene("a", [{"name": "nut", "pose": POSE, "scale": scale}])])
    if scale == 0.001:
        assert load_dataset_spec(path).scenes[0].spec.objects[0].scale == 0.001
    else:
        with pytest.raises(SpecError, match=r"s0\.yaml: field 'objects\[0\]\.scale'"):
            load_dataset_spec(path)

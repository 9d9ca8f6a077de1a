"""Names that become path parts (issue #32, item 2): one rule (``brave6d.core.names``) for the dataset's
``name`` and ``version``, library and scene object names, scene names and a downloaded release's
name, version and scene names; an accepted name is always a direct child of the folder it is
joined to, a refused one is an error naming the file and the field."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.dataset_spec import load_dataset_spec, parse_dataset_spec
from brave6d.core.errors import BraveError, DataError, SpecError
from brave6d.core.names import check_folder_name, folder_name_problem
from brave6d.core.spec import parse_scene_spec
from brave6d.dataset.release.formats import FORMAT, MANIFEST, SUMS
from brave6d.dataset.release.manifest import read_manifest
from brave6d.dataset.release.source import ReleaseError

ROOT = Path(__file__).resolve().parent.parent
MESHES = ROOT / "data" / "demo" / "meshes"

#: Characters that make names interesting as path parts, plus ordinary ones and some unicode.
_ALPHABET = st.sampled_from(list("/\\.-_+ :*?\0\n\tAbz09") + ["é", "字", "\u202e", "\u2215", "\uff0e"])
NAMES = st.one_of(
    st.text(_ALPHABET, max_size=12),
    st.text(max_size=12),
    st.sampled_from(["", ".", "..", "../x", "../../../x", "a/b", "/abs", "a\\b", "C:x", ".hidden", "-flag",
                     "ok", "ok.v1", "1.0", "a" * 100, "a" * 101, "x" * 5000]),
    st.builds(lambda a, b: a + b, st.sampled_from(["", ".", "..", "/", "-"]), st.text(_ALPHABET, max_size=120)),
)


def _dataset_data(**top: Any) -> dict[str, Any]:
    return {"name": "ds", "version": "1.0", "license": "CC-BY-4.0", "citation": "@misc{x}",
            "objects": [{"name": "nut", "category": "industry", "mesh": "nut.ply"}],
            "scenes": [{"spec": "s.yaml"}], **top}


def _scene_data(**top: Any) -> dict[str, Any]:
    return {"name": "s", "capture": {"target": [0.45, 0, 0]},
            "workspace": {"min": [0, -0.5, 0], "max": [0.9, 0.5, 0.9]}, **top}


def _refused_naming(call: Any, where: str) -> bool:
    """True when ``call()`` raises a one-line BraveError naming ``where``; False when it accepts."""
    try:
        call()
    except BraveError as exc:
        assert where in str(exc), f"{exc} does not name {where}"
        assert "\n" not in str(exc), f"{exc!r} is not one line"
        return True
    return False


@settings(max_examples=300, deadline=None)
@given(name=NAMES)
def test_an_accepted_name_is_a_direct_child_and_every_reader_agrees(tmp_path_factory: pytest.TempPathFactory,
                                                                    name: str) -> None:
    tmp = tmp_path_factory.mktemp("n")
    accepted = folder_name_problem(name) is None
    if accepted:
        child = tmp / name
        assert child.parent == tmp and child.name == name
        child.mkdir()  # really a folder of its own, right under tmp
        assert [p.name for p in tmp.iterdir()] == [name] and child.resolve().parent == tmp.resolve()
        assert check_folder_name(name, "x") == name
    else:
        with pytest.raises(DataError, match="^here: "):
            check_folder_name(name, "here")
    # every field whose value becomes a path part follows the one rule, naming file and field
    src = tmp / "dataset.yaml"
    cases = [
        (lambda: parse_dataset_spec(_dataset_data(name=name), src), "dataset.yaml: field 'name'"),
        (lambda: parse_dataset_spec(_dataset_data(version=name), src), "dataset.yaml: field 'version'"),
        (lambda: parse_dataset_spec(_dataset_data(objects=[{"name": name, "category": "industry", "mesh": "a.ply"}]),
                                    src), "dataset.yaml: field 'objects[0].name'"),
        (lambda: parse_scene_spec(_scene_data(name=name), tmp / "s.yaml", check_files=False), "s.yaml: field 'name'"),
        (lambda: parse_scene_spec(_scene_data(objects=[{"name": name, "category": "mixed", "mesh": "a.ply"}]),
                                  tmp / "s.yaml", check_files=False), "s.yaml: field 'objects[0].name'"),
    ]
    for field in ("name", "version", "scene"):
        manifest = {"format": FORMAT, "name": "ds", "version": "1.0", "objects": [],
                    "scenes": [{"scene_id": 1, "name": "s", "views": 1, "depth": False}]}
        if field == "scene":
            manifest["scenes"][0]["name"] = name
        else:
            manifest[field] = name
        path = tmp / f"manifest_{field}.json"
        path.write_text(json.dumps(manifest))
        where = f"{path}: field '{'scenes[0].name' if field == 'scene' else field}'"
        cases.append((lambda p=path: read_manifest(p), where))
    for call, where in cases:
        assert _refused_naming(call, where) is not accepted, (name, where)


# ----------------------------------------------------------------------------- the cases
def _dataset_folder(root: Path, **top: Any) -> Path:
    """A dataset folder of its own (meshes copied in) with one scene using the first object."""
    root.mkdir(parents=True)
    for n in ("hex_nut", "sample_vial"):
        shutil.copy(MESHES / f"{n}.ply", root / f"{n}.ply")
    (root / "s.yaml").write_text(yaml.safe_dump(_scene_data(objects=[{"name": "nut", "pose": {"xyz": [0.45, 0, 0]}}])))
    data = _dataset_data(objects=[{"name": "nut", "category": "industry", "mesh": "hex_nut.ply", "scale": 0.001},
                                  {"name": "vial", "category": "laboratory", "mesh": "sample_vial.ply",
                                   "scale": 0.001}], **top)
    (root / "dataset.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return root / "dataset.yaml"


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*")}


@pytest.mark.parametrize("field", ["name", "version"])
def test_a_dataset_name_or_version_that_climbs_is_refused(tmp_path: Path, field: str) -> None:
    path = _dataset_folder(tmp_path / "ds", **{field: "../../../x"})
    with pytest.raises(SpecError, match=rf"dataset\.yaml: field '{field}': '\.\./\.\./\.\./x' is not a folder-safe"):
        load_dataset_spec(path)


@pytest.mark.parametrize("field", ["name", "version", "scenes[0].name"])
def test_a_hand_edited_release_manifest_is_refused_before_any_cache_folder(tmp_path: Path, field: str) -> None:
    """The server reads name and version from a downloaded manifest.json into its cache folder's name."""
    from brave6d.dataset.release import release_scene_sources

    release, cache = tmp_path / "release", tmp_path / "a" / "b" / "cache"
    release.mkdir()
    manifest = {"format": FORMAT, "name": "ds", "version": "1.0", "objects": [],
                "scenes": [{"scene_id": 1, "name": "s", "views": 1, "depth": False}]}
    if field == "scenes[0].name":
        manifest["scenes"][0]["name"] = "../../../x"
    else:
        manifest[field] = "../../../x"
    (release / MANIFEST).write_text(json.dumps(manifest))
    (release / SUMS).write_text("")
    before = _files(tmp_path)
    with pytest.raises(ReleaseError, match=rf"manifest\.json: field '{re.escape(field)}': '\.\./\.\./\.\./x' is not"):
        release_scene_sources(release, cache)
    with pytest.raises(ReleaseError, match=rf"field '{re.escape(field)}'"):
        read_manifest(release / MANIFEST)
    assert _files(tmp_path) == before


def test_a_library_object_name_that_climbs_writes_nothing_outside_the_work_directory(tmp_path: Path) -> None:
    from brave6d.dataset.workdir import prepare_workdir

    path = _dataset_folder(tmp_path / "src")
    data = yaml.safe_load(path.read_text())
    data["objects"][1]["name"] = "../../x"  # not used by the scene: only the work directory's objects/ sees it
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    work = tmp_path / "runs" / "deep" / "work"
    before = _files(tmp_path)
    with pytest.raises(SpecError, match=r"dataset\.yaml: field 'objects\[1\]\.name': '\.\./\.\./x' is not a folder"):
        prepare_workdir(path, work, quick=True)
    assert {p for p in _files(tmp_path) - before if not p.is_relative_to(work)} == set()
    assert not (tmp_path / "runs" / "deep" / "x").exists()  # where objects/../../x would land


@pytest.mark.parametrize("name", ["-rf", ".hidden", "a" * 101])
def test_a_scene_name_follows_the_same_rule(tmp_path: Path, name: str) -> None:
    path = _dataset_folder(tmp_path / "ds")
    (path.parent / "s.yaml").write_text(yaml.safe_dump(_scene_data(
        name=name, objects=[{"name": "nut", "pose": {"xyz": [0.45, 0, 0]}}])))
    with pytest.raises(SpecError, match=r"s\.yaml: field 'name': .* is not a folder-safe name"):
        load_dataset_spec(path)


def test_an_object_name_in_a_scene_spec_follows_the_rule(tmp_path: Path) -> None:
    from brave6d.core.spec import load_scene_spec

    shutil.copy(MESHES / "hex_nut.ply", tmp_path / "hex_nut.ply")
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(_scene_data(
        objects=[{"name": "../../x", "category": "industry", "mesh": "hex_nut.ply"}])))
    with pytest.raises(SpecError, match=r"s\.yaml: field 'objects\[0\]\.name': '\.\./\.\./x' is not a folder-safe"):
        load_scene_spec(tmp_path / "s.yaml")


@pytest.mark.parametrize("name", ["..", ".", "../x", "-x"])
def test_the_3ddat_writer_takes_the_same_rule_for_its_scene_folder(tmp_path: Path, name: str) -> None:
    import numpy as np

    from brave6d.annotation import read_threedat, write_threedat_folder
    from brave6d.core.camera import PinholeCamera

    cube = read_threedat(ROOT / "tests" / "fixtures" / "threedat").library[0]
    out = tmp_path / "dat"
    with pytest.raises(DataError, match=r"3D-DAT writer: scene name: .* is not a folder-safe name"):
        write_threedat_folder(out, name, [(cube, np.eye(4))], PinholeCamera.from_hfov(64, 48, 60.0), {0: np.eye(4)})
    assert not out.exists()

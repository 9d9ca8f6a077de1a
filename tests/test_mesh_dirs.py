"""Mesh paths confined to the dataset's folder (issue #32, item 2): a shared ``dataset.yaml`` (or a
scene spec it lists) must not make ``dataset run`` copy a file from elsewhere into the work
directory and on into a release. Only the user widens that, with ``mesh_dirs`` (``--mesh-dir``),
never a field of the file itself."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml

from brave6d.core.dataset_spec import load_dataset_spec
from brave6d.core.errors import SpecError

ROOT = Path(__file__).resolve().parent.parent
MESHES = ROOT / "data" / "demo" / "meshes"
POSE = {"xyz": [0.45, 0, 0]}


def _scene(objects: list[dict[str, Any]], **top: Any) -> dict[str, Any]:
    return {"name": "s", "capture": {"target": [0.45, 0, 0]},
            "workspace": {"min": [0, -0.5, 0], "max": [0.9, 0.5, 0.9]}, "objects": objects, **top}


def _dataset(folder: Path, nut_mesh: str = "hex_nut.ply", scene: dict[str, Any] | None = None,
             scene_ref: str = "s.yaml", **top: Any) -> Path:
    """``folder/dataset.yaml``: library nut (mesh ``nut_mesh``), one scene ``s.yaml`` using it."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(MESHES / "hex_nut.ply", folder / "hex_nut.ply")
    (folder / "s.yaml").write_text(yaml.safe_dump(scene or _scene([{"name": "nut", "pose": POSE}])))
    data = {"name": "ds", "version": "1.0", "license": "CC-BY-4.0", "citation": "@misc{x}",
            "objects": [{"name": "nut", "category": "industry", "mesh": nut_mesh, "scale": 0.001}],
            "scenes": [{"spec": scene_ref}], **top}
    (folder / "dataset.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return folder / "dataset.yaml"


@pytest.fixture()
def outside(tmp_path: Path) -> Path:
    """A folder beside the dataset's, holding a copy of the nut's mesh (``secret.ply``)."""
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    shutil.copy(MESHES / "hex_nut.ply", folder / "secret.ply")
    return folder


def _outside_error(file: str, field: str) -> str:
    return rf"{re.escape(file)}: field '{re.escape(field)}': .* lies outside .* \(the dataset's folder\)"


@pytest.mark.skipif(not Path("/etc/passwd").is_file(), reason="needs /etc/passwd")
def test_the_issues_etc_passwd_mesh_is_refused(tmp_path: Path) -> None:
    path = _dataset(tmp_path / "ds", nut_mesh="/etc/passwd")
    with pytest.raises(SpecError, match=_outside_error("dataset.yaml", "objects[0].mesh")):
        load_dataset_spec(path)


@pytest.mark.parametrize("how", ["absolute", "relative", "symlink"])
def test_a_library_mesh_outside_the_folder_is_refused_unless_its_folder_is_given(
        tmp_path: Path, outside: Path, how: str) -> None:
    folder = tmp_path / "ds"
    mesh = {"absolute": str(outside / "secret.ply"), "relative": "../elsewhere/secret.ply", "symlink": "link.ply"}[how]
    path = _dataset(folder, nut_mesh=mesh)
    if how == "symlink":
        (folder / "link.ply").symlink_to(outside / "secret.ply")
    with pytest.raises(SpecError, match=_outside_error("dataset.yaml", "objects[0].mesh")) as info:
        load_dataset_spec(path)
    assert str(folder.resolve()) in str(info.value) and "--mesh-dir" in str(info.value)
    assert "\n" not in str(info.value)
    ds = load_dataset_spec(path, mesh_dirs=[outside])  # the user says otherwise
    assert ds.spec.resolve(ds.spec.objects[0].mesh).resolve() == (outside / "secret.ply").resolve()
    # a shared file cannot widen its own access
    widened = _dataset(folder, nut_mesh=mesh, mesh_dirs=[str(outside)])
    with pytest.raises(SpecError, match=r"dataset\.yaml: field 'mesh_dirs'"):
        load_dataset_spec(widened)


@pytest.mark.parametrize("key", ["static_meshes", "objects"])
def test_a_scene_specs_mesh_outside_the_dataset_folder_is_refused(tmp_path: Path, outside: Path, key: str) -> None:
    item = {"name": "nut", "pose": POSE, "mesh": str(outside / "secret.ply")}  # same content as the library's
    if key == "static_meshes":
        scene = _scene([{"name": "nut", "pose": POSE}],
                       static_meshes=[{"name": "clutter", "mesh": "../elsewhere/secret.ply"}])
    else:
        scene = _scene([item])
    path = _dataset(tmp_path / "ds", scene=scene)
    with pytest.raises(SpecError, match=_outside_error("s.yaml", f"{key}[0].mesh")):
        load_dataset_spec(path)
    assert load_dataset_spec(path, mesh_dirs=[outside]).scenes[0].name == "s"


def test_a_sidecar_that_links_out_of_the_folder_is_refused(tmp_path: Path, outside: Path) -> None:
    """A mesh travels with the files that share its stem (OBJ .mtl, textures): they too stay inside."""
    folder = tmp_path / "ds"
    path = _dataset(folder)
    (folder / "hex_nut.ply.txt").symlink_to(outside / "secret.ply")
    with pytest.raises(SpecError, match=_outside_error("dataset.yaml", "objects[0].mesh")) as info:
        load_dataset_spec(path)
    assert "hex_nut.ply.txt" in str(info.value)
    load_dataset_spec(path, mesh_dirs=[outside])


def test_a_scene_spec_outside_the_folder_is_refused(tmp_path: Path, outside: Path) -> None:
    (outside / "s.yaml").write_text(yaml.safe_dump(_scene([{"name": "nut", "pose": POSE}])))
    path = _dataset(tmp_path / "ds", scene_ref="../elsewhere/s.yaml")
    with pytest.raises(SpecError, match=_outside_error("dataset.yaml", "scenes[0].spec")):
        load_dataset_spec(path)
    assert load_dataset_spec(path, mesh_dirs=[outside]).scenes[0].spec_file.resolve().parent == outside.resolve()


def test_mesh_dirs_must_be_folders(tmp_path: Path) -> None:
    path = _dataset(tmp_path / "ds")
    with pytest.raises(SpecError, match=r"--mesh-dir .*nope: not a folder"):
        load_dataset_spec(path, mesh_dirs=[tmp_path / "nope"])


def test_a_work_directory_made_with_mesh_dirs_is_self_contained(tmp_path: Path, outside: Path) -> None:
    """``dataset run --mesh-dir`` copies the meshes into WORKDIR, whose dataset.yaml (what release build
    reads) then loads without any flag."""
    from brave6d.dataset.release.source import load_release_source
    from brave6d.dataset.workdir import prepare_workdir

    path = _dataset(tmp_path / "ds", nut_mesh=str(outside / "secret.ply"))
    work = tmp_path / "work"
    with pytest.raises(SpecError, match=_outside_error("dataset.yaml", "objects[0].mesh")):
        prepare_workdir(path, work, quick=True)
    assert not work.exists()
    dataset, results = prepare_workdir(path, work, quick=True, mesh_dirs=[outside])
    assert results == {"s": "done"}
    copied = load_dataset_spec(work / "dataset.yaml")
    assert copied.spec.resolve(copied.spec.objects[0].mesh).resolve().is_relative_to(work.resolve())
    assert load_release_source(work).name == "ds"


def test_synth_takes_mesh_dirs_for_a_dataset(tmp_path: Path, outside: Path) -> None:
    from brave6d.synth import load_synth_source

    path = _dataset(tmp_path / "ds", nut_mesh=str(outside / "secret.ply"))
    with pytest.raises(SpecError, match=_outside_error("dataset.yaml", "objects[0].mesh")):
        load_synth_source(path)
    source = load_synth_source(path, mesh_dirs=[outside])
    assert [o.mesh for o in source.objects] == [(outside / "secret.ply").resolve()]


def test_symlinked_dataset_folder_inside_is_fine(tmp_path: Path) -> None:
    """Symlinks are resolved on both sides: a dataset reached through a linked folder still reads its own meshes."""
    path = _dataset(tmp_path / "ds")
    os.symlink(tmp_path / "ds", tmp_path / "linked")
    assert load_dataset_spec(tmp_path / "linked" / path.name).scenes[0].obj_ids == {"nut": 1}


def test_dataset_run_takes_mesh_dir_flags(tmp_path: Path, outside: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``brave6d dataset run DATASET WORK`` refuses an outside mesh in one line (exit 2, nothing written);
    with ``--mesh-dir`` it gets past loading into init (stopped by an unknown ``--scenes`` name, before any job)."""
    from brave6d.cli import main

    path = _dataset(tmp_path / "ds", nut_mesh=str(outside / "secret.ply"))
    work = tmp_path / "work"
    argv = ["dataset", "run", str(path), str(work), "--quick", "--executor", "local", "--scenes", "nope"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(_outside_error("dataset.yaml", "objects[0].mesh"), err[0]), err
    assert not work.exists()
    assert main([*argv, "--mesh-dir", str(tmp_path / "unrelated"), "--mesh-dir", str(outside)]) == 2
    assert "--mesh-dir" in capsys.readouterr().err  # the first folder does not exist: named
    (tmp_path / "unrelated").mkdir()
    assert main([*argv, "--mesh-dir", str(tmp_path / "unrelated"), "--mesh-dir", str(outside)]) == 2
    assert "--scenes: ['nope'] are not scenes of" in capsys.readouterr().err
    copied = load_dataset_spec(work / "dataset.yaml")  # the work directory is self-contained
    assert copied.spec.resolve(copied.spec.objects[0].mesh).resolve().is_relative_to(work.resolve())


def test_synth_takes_mesh_dir_flags_into_its_workers(tmp_path: Path, outside: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.cli import main

    path = _dataset(tmp_path / "ds", nut_mesh=str(outside / "secret.ply"))
    argv = ["synth", str(path), str(tmp_path / "out"), "--images", "2", "--width", "32", "--height", "24"]
    assert main(argv) == 2
    assert re.search(_outside_error("dataset.yaml", "objects[0].mesh"), capsys.readouterr().err)
    assert main([*argv, "--workers", "2", "--mesh-dir", str(outside)]) == 0  # spawned workers load it again
    assert len(list((tmp_path / "out" / "train_pbr").rglob("*.png"))) >= 2

"""``dataset.yaml`` scenes that are captured scene directories (issue 33, item 4): ``{dir: path}``
beside ``{spec: file}``, validated like the rest (one kind per entry, folder-safe names, objects
from the library, confined to the dataset's folder unless the user passes ``--scene-dir``), the
work directory's record of where they lie, and the training preset a run gives every scene."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brave6d.core.dataset_spec import load_dataset_spec
from brave6d.core.errors import BraveError, SpecError
from brave6d.core.layout import init_scene_dir
from brave6d.core.names import folder_name_problem

ROOT = Path(__file__).resolve().parent.parent
MESHES = ROOT / "data" / "demo" / "meshes"
POSE = {"xyz": [0.45, 0, 0]}


def _scene_spec(name: str = "lab_a", objects: list[str] | None = None) -> dict[str, Any]:
    return {"name": name, "capture": {"target": [0.45, 0, 0]},
            "workspace": {"min": [0, -0.5, 0], "max": [0.9, 0.5, 0.9]},
            "objects": [{"name": o, "category": "industry", "mesh": "hex_nut.ply", "scale": 0.001, "pose": POSE}
                        for o in (objects or ["nut"])]}


def _captured(folder: Path, **spec: Any) -> Path:
    """A scene directory made by ``brave6d init`` (its mesh copied into ``assets/``), as at the robot."""
    src = folder.parent / f".{folder.name}-src"
    src.mkdir(parents=True)
    shutil.copy(MESHES / "hex_nut.ply", src / "hex_nut.ply")
    (src / "scene.yaml").write_text(yaml.safe_dump(_scene_spec(**spec)))
    return init_scene_dir(folder, src / "scene.yaml").root


def _dataset(folder: Path, scenes: list[dict[str, Any]], **top: Any) -> Path:
    """``folder/dataset.yaml`` with a one-object library (``nut``) and ``scenes``."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(MESHES / "hex_nut.ply", folder / "hex_nut.ply")
    data = {"name": "ds", "version": "1.0", "license": "CC-BY-4.0", "citation": "@misc{x}",
            "objects": [{"name": "nut", "category": "industry", "mesh": "hex_nut.ply", "scale": 0.001}],
            "scenes": scenes, **top}
    (folder / "dataset.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return folder / "dataset.yaml"


def test_a_scene_directory_inside_the_dataset_folder_is_a_captured_scene(tmp_path: Path) -> None:
    folder = tmp_path / "ds"
    captured = _captured(folder / "captures" / "a")
    (folder / "sim.yaml").parent.mkdir(parents=True, exist_ok=True)
    (folder / "sim.yaml").write_text(yaml.safe_dump(_scene_spec("sim_scene")))
    shutil.copy(MESHES / "hex_nut.ply", folder / "hex_nut.ply")
    ds = load_dataset_spec(_dataset(folder, [{"spec": "sim.yaml"}, {"dir": "captures/a"}]))
    sim, lab = ds.scenes
    assert (sim.name, sim.captured, sim.dir) == ("sim_scene", False, None)
    assert (lab.name, lab.captured, lab.dir, lab.scene_id) == ("lab_a", True, captured.resolve(), 2)
    assert lab.spec_file == captured.resolve() / "scene.yaml" and lab.obj_ids == {"nut": 1}


@settings(max_examples=20, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.fixed_dictionaries({}, optional={"spec": st.just("s.yaml"), "dir": st.just("captures/a"),
                                           "path": st.just("x")}))
def test_each_scene_entry_is_exactly_one_kind(tmp_path_factory: pytest.TempPathFactory, entry: dict[str, str]) -> None:
    folder = tmp_path_factory.mktemp("ds")
    _captured(folder / "captures" / "a")
    (folder / "s.yaml").write_text(yaml.safe_dump(_scene_spec("s")))
    path = _dataset(folder, [entry])
    if set(entry) in ({"spec"}, {"dir"}):
        assert load_dataset_spec(path).scenes[0].captured == ("dir" in entry)
        return
    with pytest.raises(SpecError, match=r"dataset\.yaml: field 'scenes\[0\]") as info:
        load_dataset_spec(path)
    assert "\n" not in str(info.value)
    if "path" not in entry:  # neither or both kinds: the message says what to give
        assert "exactly one of 'spec'" in str(info.value)


@settings(max_examples=25, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.one_of(st.from_regex(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,20}", fullmatch=True),
                 st.sampled_from(["..", ".hidden", "a/b", "-flag", "x" * 101, "", "é"])))
def test_a_scene_directorys_name_follows_the_name_rule(tmp_path_factory: pytest.TempPathFactory, name: str) -> None:
    """Its ``scene.yaml`` names the scene (``status/<name>.json``, ``report/<name>/``, the release):
    one rule for every name that becomes a path part (brave6d.core.names)."""
    folder = tmp_path_factory.mktemp("ds")
    captured = _captured(folder / "captures" / "a")
    spec = yaml.safe_load((captured / "scene.yaml").read_text())
    (captured / "scene.yaml").write_text(yaml.safe_dump({**spec, "name": name}))  # edited by hand
    path = _dataset(folder, [{"dir": "captures/a"}])
    if folder_name_problem(name) is None:
        assert load_dataset_spec(path).scenes[0].name == name
    else:
        with pytest.raises(SpecError, match=r"scene\.yaml: field 'name'"):
            load_dataset_spec(path)


def test_its_objects_must_be_the_librarys(tmp_path: Path) -> None:
    folder = tmp_path / "ds"
    _captured(folder / "captures" / "a", objects=["bolt"])
    with pytest.raises(SpecError, match=r"a/scene\.yaml: field 'objects\[0\]\.name': unknown object 'bolt'"):
        load_dataset_spec(_dataset(folder, [{"dir": "captures/a"}]))


def test_a_scene_directory_outside_the_folder_needs_scene_dir(tmp_path: Path) -> None:
    captured = _captured(tmp_path / "lab" / "a")
    path = _dataset(tmp_path / "ds", [{"dir": "../lab/a"}])
    with pytest.raises(SpecError, match=r"field 'scenes\[0\]\.dir': .* lies outside .*allow its folder with "
                                        r"--scene-dir DIR"):
        load_dataset_spec(path)
    with pytest.raises(SpecError, match="--scene-dir"):  # a mesh folder is read, a scene directory written into
        load_dataset_spec(path, mesh_dirs=[tmp_path / "lab"])
    assert load_dataset_spec(path, scene_dirs=[tmp_path / "lab"]).scenes[0].dir == captured.resolve()
    with pytest.raises(SpecError, match=r"--scene-dir .*nope: not a folder"):
        load_dataset_spec(path, scene_dirs=[tmp_path / "nope"])
    # a link inside the folder to a scene elsewhere is where it points
    (tmp_path / "ds" / "link").symlink_to(captured)
    with pytest.raises(SpecError, match=r"link \(that is .*lab/a\) lies outside"):
        load_dataset_spec(_dataset(tmp_path / "ds", [{"dir": "link"}]))


def test_a_dir_that_is_no_scene_directory_is_named(tmp_path: Path) -> None:
    (tmp_path / "ds" / "empty").mkdir(parents=True)
    with pytest.raises(SpecError, match=r"'scenes\[0\]\.dir': scene directory not found: .*gone"):
        load_dataset_spec(_dataset(tmp_path / "ds", [{"dir": "gone"}]))
    with pytest.raises(SpecError, match=r"'scenes\[0\]\.dir': .*empty is not a scene directory \(no scene\.yaml\)"):
        load_dataset_spec(_dataset(tmp_path / "ds", [{"dir": "empty"}]))


def test_scene_names_stay_unique_across_both_kinds(tmp_path: Path) -> None:
    folder = tmp_path / "ds"
    _captured(folder / "captures" / "a", name="same")
    (folder / "s.yaml").write_text(yaml.safe_dump(_scene_spec("same")))
    with pytest.raises(SpecError, match=r"'scenes\[1\]\.dir': scene name 'same' .* already used by scenes\[0\]"):
        load_dataset_spec(_dataset(folder, [{"spec": "s.yaml"}, {"dir": "captures/a"}]))


def test_the_work_directory_records_where_a_captured_scene_lies(tmp_path: Path) -> None:
    """Not copied (a capture is gigabytes): the work directory's dataset.yaml names it, and its
    readers (status, report, release build) find it without the user's --scene-dir again."""
    from brave6d.dataset import load_workdir_dataset, prepare_workdir, scene_root

    captured = _captured(tmp_path / "lab" / "a")
    work = tmp_path / "work"
    dataset, inits = prepare_workdir(_dataset(tmp_path / "ds", [{"dir": "../lab/a"}]), work,
                                     scene_dirs=[tmp_path / "lab"])
    assert inits == {"lab_a": "missing"}  # nothing captured yet: see below
    assert yaml.safe_load((work / "dataset.yaml").read_text())["scenes"] == [{"dir": str(captured.resolve())}]
    assert not (work / "scenes").exists()
    again = load_workdir_dataset(work)
    assert scene_root(work, again.scenes[0]).root == captured.resolve() == dataset.scenes[0].dir
    shutil.move(str(captured), str(tmp_path / "moved"))
    with pytest.raises(SpecError, match=r"work/dataset\.yaml: field 'scenes\[0\]\.dir': scene directory not found"):
        load_workdir_dataset(work)


def test_a_captured_scene_missing_its_rig_stages_is_named_with_what_it_misses(tmp_path: Path) -> None:
    from brave6d.dataset import read_scene_status
    from brave6d.dataset.workdir import prepare_workdir

    captured = _captured(tmp_path / "ds" / "lab" / "a")
    _, inits = prepare_workdir(_dataset(tmp_path / "ds", [{"dir": "lab/a"}]), tmp_path / "work")
    assert inits == {"lab_a": "missing"}
    status = read_scene_status(tmp_path / "work", "lab_a")
    assert status.done("init")
    errors = {s: status.stages[s]["error"] for s in ("calibrate", "capture", "annotate")}
    assert all(status.state(s) == "failed" for s in errors)
    assert errors["calibrate"] == (f"scene lab_a: no calibration (calibration/intrinsics.json); calibrate it at "
                                   f"the robot with 'brave6d calibrate all {captured.resolve()} --robot ur:HOST "
                                   "--camera oak' before the cluster can train it")
    assert errors["capture"].startswith("scene lab_a: no capture (capture/frames.jsonl); capture it at the robot "
                                        f"with 'brave6d capture run {captured.resolve()} --robot ur:HOST --camera oak'")
    assert errors["annotate"] == (f"scene lab_a: no annotation (annotation/); annotate it in 3D-DAT and import it "
                                  f"with 'brave6d annotate import-3ddat DAT_DIR {captured.resolve()} --dataset "
                                  f"{(tmp_path / 'ds' / 'dataset.yaml').resolve()}' (3D-DAT object ids = the "
                                  "library's names) before the cluster can train it")
    (captured / "annotation").mkdir()  # a folder without its commit point: the annotation's own reader says so
    prepare_workdir(tmp_path / "ds" / "dataset.yaml", tmp_path / "work")
    error = read_scene_status(tmp_path / "work", "lab_a").stages["annotate"]["error"]
    assert error.startswith("scene lab_a: ") and "objects.json: no imported annotation" in error
    assert status.state("train") == "pending"


def test_the_flag_chooses_the_preset_else_the_cluster_block(tmp_path: Path) -> None:
    from brave6d.dataset.runner import scene_preset

    _captured(tmp_path / "ds" / "captures" / "a")
    plain = load_dataset_spec(_dataset(tmp_path / "ds", [{"dir": "captures/a"}]))
    assert scene_preset(plain, None) is None  # the training stage's default (fast)
    gpu = load_dataset_spec(_dataset(tmp_path / "ds", [{"dir": "captures/a"}], cluster={"preset": "default"}))
    assert gpu.spec.cluster.preset == "default"
    assert scene_preset(gpu, None) == "default" and scene_preset(gpu, "quality") == "quality"
    with pytest.raises(BraveError, match=r"^--preset: unknown preset 'fastest'; choose one of"):
        scene_preset(gpu, "fastest")
    bad = load_dataset_spec(_dataset(tmp_path / "ds", [{"dir": "captures/a"}], cluster={"preset": "turbo"}))
    with pytest.raises(BraveError, match=r"dataset\.yaml: field 'cluster\.preset': unknown preset 'turbo'"):
        scene_preset(bad, None)


def test_the_executor_takes_the_cluster_block_without_its_preset() -> None:
    from brave6d.core.dataset_spec import ClusterSpec
    from brave6d.dataset import ExecutorOptions

    options = ExecutorOptions.from_cluster(ClusterSpec(preset="default", partition="gpu"))
    assert options.partition == "gpu" and not hasattr(options, "preset")


def test_synth_takes_scene_dir_for_captured_scenes_outside_the_dataset(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """``brave6d synth DATASET`` reads the same dataset ``dataset run`` does: a captured scene outside
    its folder needs the user's ``--scene-dir`` there too (refused in one line, exit 2, nothing written)."""
    from brave6d.cli import main
    from brave6d.synth import load_synth_source

    captured = _captured(tmp_path / "captures" / "lab_a")
    path = _dataset(tmp_path / "ds", [{"dir": str(captured)}])
    out = tmp_path / "synth"
    assert main(["synth", str(path), str(out), "--images", "1", "--width", "32", "--height", "24"]) == 2
    assert "--scene-dir" in capsys.readouterr().err and not out.exists()
    source = load_synth_source(path, scene_dirs=[tmp_path / "captures"])
    assert [o.name for o in source.objects] == ["nut"]
    assert main(["synth", str(path), str(out), "--images", "1", "--width", "32", "--height", "24",
                 "--scene-dir", str(tmp_path / "captures")]) == 0
    assert len(list((out / "train_pbr").rglob("rgb/*.png"))) == 1

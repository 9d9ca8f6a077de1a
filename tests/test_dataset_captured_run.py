"""A lab's dataset of captured scenes through ``brave6d dataset run`` (issue 33, item 4, acceptance).

The scene directories are made as a lab makes them, with the commands themselves on the simulated
rig (``brave6d init``, ``calibrate all``, ``capture run``, the demo's 3D-DAT annotator and ``annotate
import-3ddat --dataset``), in a folder beside the dataset's. A ``dataset.yaml`` names them (``dir:``),
with a third scene that was captured and calibrated but not annotated. ``dataset run --preset
default`` trains and exports the two annotated ones where they lie, never touching their rig
stages, and names the third with what it misses; once annotated, a re-run trains it alone, and
the release finds every scene.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

from brave6d.annotation.demo import write_demo_threedat
from brave6d.cli import main
from brave6d.core.dataset_spec import load_dataset_spec
from brave6d.core.layout import SceneDir, write_spec
from brave6d.core.run_context import QUICK_CAPTURE
from brave6d.core.spec import spec_to_yaml
from brave6d.dataset import SCENE_STAGES, read_scene_status

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "data" / "demo"
pytestmark = pytest.mark.slow


def _annotate(scene: Path, dat: Path, dataset: Path | None) -> None:
    """The annotator's 3D-DAT folder (the demo's truth), imported as a lab imports it."""
    write_demo_threedat(scene, dat)
    extra = ["--dataset", str(dataset)] if dataset is not None else []
    assert main(["annotate", "import-3ddat", str(dat), str(scene), *extra]) == 0


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``ds/`` (the demo dataset's library) and ``captures/lab_{a,b,c}``: a and b annotated, c not."""
    base = tmp_path_factory.mktemp("lab")
    ds = Path(shutil.copytree(DEMO, base / "ds", ignore=shutil.ignore_patterns("*.py", "__pycache__")))
    demo = load_dataset_spec(ds / "dataset.yaml")
    for name, demo_scene in (("lab_a", "demo_tabletop"), ("lab_b", "demo_workbench")):
        spec = demo.scene(demo_scene).spec  # every object field given, as a lab's own scene spec
        capture = spec.capture.model_copy(update=QUICK_CAPTURE)  # the --quick miniature: 15 views
        (ds / f"{name}.yaml").write_text(spec_to_yaml(spec.model_copy(update={"name": name, "capture": capture})))
        scene = base / "captures" / name
        assert main(["init", str(ds / f"{name}.yaml"), str(scene)]) == 0
        assert main(["calibrate", "all", str(scene), "--views", "12"]) == 0
        assert main(["capture", "run", str(scene)]) == 0
        if name == "lab_a":  # c: a's capture and calibration, never annotated
            c = SceneDir(shutil.copytree(scene, base / "captures" / "lab_c"))
            write_spec(c, c.load_spec().model_copy(update={"name": "lab_c"}))
        _annotate(scene, base / f"dat_{name}", ds / "dataset.yaml")
    data = yaml.safe_load((ds / "dataset.yaml").read_text())
    data["scenes"] = [{"dir": f"../captures/{n}"} for n in ("lab_a", "lab_b", "lab_c")]
    (ds / "lab.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return base


def _rig_files(scene: Path) -> dict[str, bytes]:
    s = SceneDir(scene)
    return {p.name: p.read_bytes() for p in (s.frames_path, s.intrinsics_path, s.handeye_path)}


def test_captured_scenes_train_and_export_where_they_lie(lab: Path, capsys: pytest.CaptureFixture[str]) -> None:
    work, captures = lab / "work", lab / "captures"
    before = {n: _rig_files(captures / n) for n in ("lab_a", "lab_b", "lab_c")}
    argv = ["dataset", "run", str(lab / "ds" / "lab.yaml"), str(work), "--preset", "default", "--quick",
            "--device", "cpu", "--executor", "local", "--scene-dir", str(captures), "--no-learn"]
    assert main(argv) == 1  # lab_c is not ready ...
    out = capsys.readouterr()
    line = next(x for x in out.out.splitlines() if x.startswith("NOT READY"))
    assert line == (f"NOT READY lab_c (annotate): scene lab_c: no annotation (annotation/); annotate it in "
                    f"3D-DAT and import it with 'brave6d annotate import-3ddat DAT_DIR {captures.resolve() / 'lab_c'} "
                    f"--dataset {lab.resolve() / 'ds' / 'lab.yaml'}' (3D-DAT object ids = the library's names) "
                    "before the cluster can train it")
    assert "FAILED lab" not in out.out
    for name in ("lab_a", "lab_b"):  # ... while the other two train and export
        status = read_scene_status(work, name)
        assert all(status.done(s) for s in SCENE_STAGES), (name, status.stages)
        scene = SceneDir(captures / name)
        assert json.loads((scene.splat_dir / "metrics.json").read_text())["preset"] == "default-quick"
        from brave6d.serve import load_bundle

        assert load_bundle(scene.bundle_dir).objects  # a bundle, with its objects, where the scene lies
        assert status.stages["capture"]["figures"] == {"frames": 15}
    c = read_scene_status(work, "lab_c")
    assert c.state("annotate") == "failed" and c.state("train") == "pending" and c.done("capture")
    assert not SceneDir(captures / "lab_c").splat_dir.exists()
    # the rig stages ran at the "robot" only: the run read them, never wrote them
    assert {n: _rig_files(captures / n) for n in before} == before
    assert not (work / "scenes").exists()  # used in place, not copied
    assert "lab_c / annotate: scene lab_c: no annotation (annotation/)" in out.out  # under the table

    # the lab annotates lab_c and runs again: only lab_c's stages run
    stamps = {n: {s: r["at"] for s, r in read_scene_status(work, n).stages.items()} for n in ("lab_a", "lab_b")}
    _annotate(captures / "lab_c", lab / "dat_lab_c", lab / "ds" / "dataset.yaml")
    assert main(argv) == 0
    assert "NOT READY" not in capsys.readouterr().out
    assert {n: {s: r["at"] for s, r in read_scene_status(work, n).stages.items()} for n in stamps} == stamps
    assert all(read_scene_status(work, "lab_c").done(s) for s in SCENE_STAGES)

    # the release finds every scene where it lies, and is never written into one
    assert main(["release", "build", str(work), str(captures / "lab_a" / "release")]) == 2
    assert "inside the scene directory" in capsys.readouterr().err and not (captures / "lab_a" / "release").exists()
    assert main(["release", "build", str(work), str(lab / "release")]) == 0
    manifest = json.loads((lab / "release" / "manifest.json").read_text())
    assert [s["name"] for s in manifest["scenes"]] == ["lab_a", "lab_b", "lab_c"]
    assert main(["release", "verify", str(lab / "release")]) == 0


def test_an_annotation_with_other_obj_ids_than_the_librarys_is_named(lab: Path) -> None:
    """lab_b's objects imported without --dataset are numbered by the scene (block_blue 1, ...),
    not by the library (block_blue 6): the dataset would give one object two obj_ids."""
    from brave6d.dataset.workdir import prepare_workdir

    scene = Path(shutil.copytree(lab / "captures" / "lab_b", lab / "captures2" / "lab_b",
                                 ignore=shutil.ignore_patterns("annotation", "splat", "sparse", "bundle")))
    _annotate(scene, lab / "dat_own_ids", None)
    data = yaml.safe_load((lab / "ds" / "lab.yaml").read_text())
    data["scenes"] = [{"dir": "../captures2/lab_b"}]
    (lab / "ds" / "own_ids.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    _, inits = prepare_workdir(lab / "ds" / "own_ids.yaml", lab / "work_own_ids", scene_dirs=[lab / "captures2"])
    assert inits == {"lab_b": "missing"}
    error = read_scene_status(lab / "work_own_ids", "lab_b").stages["annotate"]["error"]
    assert error.startswith(f"scene lab_b: the annotation in {scene.resolve() / 'annotation'} gives 'block_blue' "
                            "obj_id 1, the library of ")
    assert "gives 6; import it again with 'brave6d annotate import-3ddat DAT_DIR" in error and "--dataset" in error

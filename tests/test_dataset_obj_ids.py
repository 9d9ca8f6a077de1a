"""A dataset's library fixes the BOP obj_ids of a scene's import (brave6d.annotation.import_threedat(obj_ids=...))."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from brave6d.annotation import (
    BopLayout,
    export_bop,
    import_threedat,
    load_annotation,
    make_synthetic_scene,
    read_scene_gt,
    read_threedat,
)
from brave6d.core.errors import DataError

FIXTURE = Path(__file__).parent / "fixtures" / "threedat"


def _scene(tmp_path: Path):
    dat = read_threedat(FIXTURE)
    poses = {int(p.frame_id): p.world_T_cam for p in dat.camera_poses}
    return make_synthetic_scene(tmp_path / "scene", dat.camera.pinhole(), poses)


def test_explicit_obj_ids_reach_the_bop_export(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    import_threedat(FIXTURE, scene.root)  # on its own: sorted ids, bar = 1, cube = 2
    assert load_annotation(scene).id_map == {"bar": 1, "cube": 2}
    import_threedat(FIXTURE, scene.root, obj_ids={"cube": 5, "bar": 9, "unused": 1})
    annotation = load_annotation(scene)
    assert annotation.id_map == {"bar": 9, "cube": 5}
    assert sorted(o.obj_id for o in annotation.objects) == [5, 9]
    export_bop(scene.root)
    gt = read_scene_gt(BopLayout.of_scene(scene).scene_gt_path)
    assert {g.obj_id for poses in gt.values() for g in poses} == {5, 9}


@pytest.mark.parametrize(("obj_ids", "problem"), [({"cube": 1}, r"library ids \['bar'\] have no obj_id"),
                                                  ({"cube": 1, "bar": 1}, "the same obj_id"),
                                                  ({"cube": 0, "bar": 1}, "positive integers")])
def test_an_incomplete_or_ambiguous_map_is_refused_before_writing(tmp_path: Path, obj_ids: dict[str, int],
                                                                   problem: str) -> None:
    scene = _scene(tmp_path)
    with pytest.raises(DataError, match=problem):
        import_threedat(FIXTURE, scene.root, obj_ids=obj_ids)
    assert not scene.annotation_dir.exists()


def test_cli_takes_the_obj_ids_from_a_dataset_library(tmp_path: Path) -> None:
    """``brave6d annotate import-3ddat DAT SCENE --dataset DATASET.yaml``: ids = library positions."""
    import yaml

    from brave6d.cli import main

    meshes = Path(__file__).resolve().parent.parent / "data" / "demo" / "meshes"
    scene_spec = {"name": "s", "capture": {"target": [0.45, 0, 0]},
                  "workspace": {"min": [0, -0.5, 0], "max": [0.9, 0.5, 0.9]},
                  "objects": [{"name": "cube", "pose": {"xyz": [0.45, 0, 0]}}]}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(scene_spec))
    shutil.copy(meshes / "hex_nut.ply", tmp_path / "hex_nut.ply")  # a dataset names files in its folder
    library = [{"name": n, "category": "industry", "mesh": "hex_nut.ply", "scale": 0.001}
               for n in ("unused", "cube", "bar")]
    dataset = tmp_path / "dataset.yaml"
    dataset.write_text(yaml.safe_dump({"name": "ds", "version": "1", "license": "CC-BY-4.0", "citation": "@misc{x}",
                                       "objects": library, "scenes": [{"spec": "s.yaml"}]}))
    scene = _scene(tmp_path)
    assert main(["annotate", "import-3ddat", str(FIXTURE), str(scene.root), "--dataset", str(dataset)]) == 0
    assert load_annotation(scene).id_map == {"cube": 2, "bar": 3}
    other = _scene(tmp_path / "other")
    demo = Path(__file__).resolve().parent.parent / "data" / "demo" / "dataset.yaml"
    assert main(["annotate", "import-3ddat", str(FIXTURE), str(other.root), "--dataset", str(demo)]) == 2
    assert not other.annotation_dir.exists()  # a library without the fixture's objects: refused, nothing written


def test_cli_reads_only_the_library_order_of_a_dataset_whose_meshes_lie_elsewhere(tmp_path: Path) -> None:
    """``import-3ddat --dataset`` needs the library's names and order, not its meshes: a lab's
    dataset.yaml whose meshes lie outside its folder (allowed by ``dataset run --mesh-dir``) still
    gives the ids here, while its names are still checked."""
    import yaml

    from brave6d.cli import main

    library = [{"name": n, "category": "industry", "mesh": "/elsewhere/meshes/nut.ply"} for n in ("bar", "cube")]
    dataset = tmp_path / "ds" / "dataset.yaml"
    dataset.parent.mkdir()
    head = {"name": "ds", "version": "1", "license": "CC-BY-4.0", "citation": "@misc{x}", "scenes": [{"spec": "s.yaml"}]}
    dataset.write_text(yaml.safe_dump({**head, "objects": library}))
    scene = _scene(tmp_path)
    assert main(["annotate", "import-3ddat", str(FIXTURE), str(scene.root), "--dataset", str(dataset)]) == 0
    assert load_annotation(scene).id_map == {"bar": 1, "cube": 2}
    dataset.write_text(yaml.safe_dump({**head, "objects": [*library, {**library[0], "name": "../x"}]}))
    other = _scene(tmp_path / "other")
    assert main(["annotate", "import-3ddat", str(FIXTURE), str(other.root), "--dataset", str(dataset)]) == 2
    assert not other.annotation_dir.exists()

"""``brave6d dataset report`` and ``brave6d report --scene/--out``: one report per scene of a dataset
work directory and the index comparing them, from fabricated measurements (the sections' own
measuring is tested in tests/test_report.py)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from brave6d.cli import main as cli_main
from brave6d.core.errors import BraveError
from brave6d.dataset.report import gap_by_ring, pooled_ar, report_dataset
from brave6d.dataset.workdir import prepare_workdir
from brave6d.evaluation.report import Measurement, MeasurementStore

ROOT = Path(__file__).resolve().parent.parent
DEMO_DATASET = ROOT / "data" / "demo" / "dataset.yaml"
MACHINE = {"cpu": "Test CPU", "cores": 2, "gpu": None, "device": "cpu"}


def _save(folder: Path, name: str, points: list[dict], summary: dict) -> None:
    MeasurementStore(folder / "measurements").save(Measurement(
        name=name, key={"test": True}, settings={"fixture": name}, machine=MACHINE, status="complete",
        points=points, summary=summary, seconds=1.0))


def _fabricate_scene_report(out: Path, psnr: float, ar: float) -> None:
    _save(out, "training", [{"source": "scene", "step": 10, "time_s": 1.0, "gaussians": 100, "psnr": psnr}],
          {"steps": 10, "train_s": 1.0, "total_s": 1.0, "gaussians": 100, "psnr": psnr, "ssim": 0.8})
    _save(out, "distance", [
        {"id": "a", "obj_id": 1, "object": "cup", "distance_m": 0.2, "target": True, "found": True, "ar": ar},
        {"id": "b", "obj_id": 1, "object": "cup", "distance_m": 0.5, "target": True, "found": True, "ar": ar / 2},
        {"id": "c", "obj_id": 1, "object": "cup", "distance_m": 0.5, "target": False, "ar": None}], {})
    _save(out, "realism", [
        {"id": "im0", "level": 0, "distance_m": 0.2, "objects": [{"obj_id": 1, "real_ar": 0.8, "splat_ar": 0.6},
                                                                 {"obj_id": 2, "real_ar": 0.4, "splat_ar": 0.4}]},
        {"id": "im1", "level": 1, "distance_m": 0.45, "objects": [{"obj_id": 1, "real_ar": 0.5, "splat_ar": 0.7}]}],
        {})


def test_pooled_ar_and_gap_by_ring_use_only_finite_targets() -> None:
    points = [{"target": True, "ar": 0.6}, {"target": True, "ar": None}, {"target": False, "ar": 1.0},
              {"target": True, "ar": float("nan")}, {"target": True, "ar": 0.2}]
    assert pooled_ar(points) == (pytest.approx(0.4), 2)
    assert math.isnan(pooled_ar([{"target": True, "ar": None}])[0])
    gaps = gap_by_ring([{"distance_m": 0.45, "objects": [{"real_ar": 0.5, "splat_ar": 0.7}]},
                        {"distance_m": 0.2, "objects": [{"real_ar": 0.8, "splat_ar": 0.6},
                                                        {"real_ar": 0.4, "splat_ar": None}]},
                        {"distance_m": 0.3, "objects": [{"real_ar": None, "splat_ar": 0.5}]}])
    assert [d for d, _ in gaps] == [0.2, 0.45]  # the ring without a real AR has no gap
    assert gaps[0][1] == pytest.approx(0.6 - 0.6) and gaps[1][1] == pytest.approx(-0.2)


def test_dataset_report_writes_each_scene_and_the_index(tmp_path: Path) -> None:
    work = tmp_path / "work"
    dataset, results = prepare_workdir(DEMO_DATASET, work, quick=True)
    assert set(results.values()) == {"done"}
    names = [s.name for s in dataset.scenes]
    for k, name in enumerate(names):
        _fabricate_scene_report(work / "report" / name, psnr=20.0 + k, ar=0.8 - 0.2 * k)
    # baseline: a cheap section (no evaluation file: a note); the fabricated ones come from the caches
    assert cli_main(["dataset", "report", str(work), "--mode", "quick", "--only", "baseline"]) == 0
    index = (work / "report" / "README.md").read_text()
    for k, name in enumerate(names):
        page = work / "report" / name / "report.md"
        assert page.is_file() and f"]({name}/report.md)" in index
        assert f"`{work / 'scenes' / name}`" in page.read_text()  # measured on the dataset's scene directory
    first, second = names
    assert re.search(rf"\| \[{first}\]\({first}/report\.md\) +\| 20\.00 +\| 0\.600 \(2 views\) +\| "
                     r"20 cm: \+0\.100; 45 cm: -0\.200 +\|", index)
    assert re.search(rf"\| \[{second}\]\({second}/report\.md\) +\| 21\.00 +\| 0\.450 \(2 views\) ", index)
    assert "distance.png" in {p.name for p in (work / "report" / first).iterdir()}
    assert not (work / "scenes" / first / "report").exists()  # nothing written into the scene


def test_dataset_report_errors_name_the_cause(tmp_path: Path) -> None:
    with pytest.raises(BraveError, match=r"dataset\.yaml: not found"):
        report_dataset(tmp_path, quick=True)
    work = tmp_path / "work"
    prepare_workdir(DEMO_DATASET, work, quick=True)
    with pytest.raises(BraveError, match="--only nonsense: no such section"):
        report_dataset(work, quick=True, only=("nonsense",))


def test_report_on_any_scene_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    work = tmp_path / "work"
    prepare_workdir(DEMO_DATASET, work, quick=True)
    scene = next(p for p in sorted((work / "scenes").iterdir()))
    out = tmp_path / "elsewhere"
    _fabricate_scene_report(out, psnr=23.5, ar=0.5)
    assert cli_main(["report", "--scene", str(scene), "--out", str(out), "--no-measure"]) == 0
    page = (out / "report.md").read_text()
    assert f"# What accuracy costs in time: scenes/{scene.name}" in page and "holdout PSNR 23.50 dB" in page
    assert (out / "distance.png").is_file() and not (work / "report").exists()
    assert cli_main(["report", "--scene", str(scene)]) != 0  # --out missing: a one-line error
    assert "--scene and --out go together" in capsys.readouterr().err

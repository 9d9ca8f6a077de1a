"""The training stage end to end on a small synthetic scene: CLI, outputs, metrics, resume."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from plyfile import PlyData

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.layout import SceneDir
from brave6d.training import cli, run_outcome
from brave6d.training.ply import inria_attribute_names, read_ply
from brave6d.training.toy_scenes import plane_views, write_scene

CAM = PinholeCamera(160, 100, 125.0, 125.0, 79.5, 49.5)


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    cli.configure(parser)
    return parser.parse_args(list(argv))


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> SceneDir:
    root = tmp_path_factory.mktemp("pipe") / "scene"
    scene = write_scene(root, CAM, plane_views(CAM, [0.45, 0.6], 8))
    (scene.capture_dir / "rgb" / "000003.png").write_bytes(b"corrupt")
    assert cli.run(parse(str(root), "--preset", "fast", "--steps", "20", "--device", "cpu",
                         "--skip-bad-frames")) == 0
    return scene


def test_outputs_and_metrics(trained: SceneDir) -> None:
    splat = trained.splat_dir
    metrics = json.loads((splat / "metrics.json").read_text())
    for key in ("steps", "train_time_s", "total_time_s", "num_gaussians", "memory", "holdout", "skipped_frames",
                "images", "init", "curve"):
        assert key in metrics, key
    assert metrics["steps"] == 20 and metrics["device"] == "cpu"
    assert metrics["memory"]["peak_rss_mb"] > 10
    assert metrics["images"]["undistorted_once"] is True
    assert [s["index"] for s in metrics["skipped_frames"]] == [3]
    hold = metrics["holdout"]
    assert hold["n_views"] == 2 and set(hold["per_level"]) == {"0", "1"}
    assert np.isfinite(hold["psnr"]) and hold["psnr"] > 10
    for level in hold["per_level"].values():
        assert {"psnr", "ssim", "n_views", "distance_m"} <= set(level)
    assert metrics["init"]["source"] in ("colmap", "depth")
    assert len(list((splat / "holdout").glob("*.png"))) == 2
    # the split is recorded once, beside the metrics: exactly the views scored (frame 3 was skipped)
    from brave6d.training import holdout_split, read_holdout

    split = read_holdout(trained)
    assert split.recorded and trained.holdout_split_path.is_file()
    assert [(v.index, v.view_id) for v in split.views] == [(s["index"], s["view_id"]) for s in hold["per_view"]]
    assert split.indices == holdout_split(trained.frames())[1]
    assert (splat / "curves.png").stat().st_size > 1000
    names = [p.name for p in PlyData.read(str(splat / "point_cloud.ply"))["vertex"].properties]
    assert names == inria_attribute_names() + ["filter_3d"]  # Inria's layout + the mip 3D filter of `fast`
    assert read_ply(splat / "point_cloud.ply").num_gaussians == metrics["num_gaussians"]
    # beside it, the viewer PLY: the same Gaussians with the filter baked in, Inria's layout only (issue 45)
    viewer = PlyData.read(str(splat / "point_cloud_viewer.ply"))["vertex"]
    assert [p.name for p in viewer.properties] == inria_attribute_names()
    assert len(viewer.data) == metrics["num_gaussians"]
    pycolmap.Reconstruction(str(trained.sparse_dir / "0"))  # loads


def test_resume_continues_from_the_last_checkpoint(trained: SceneDir) -> None:
    assert cli.run(parse(str(trained.root), "--preset", "fast", "--steps", "30", "--device", "cpu",
                         "--skip-bad-frames", "--resume")) == 0
    metrics = json.loads((trained.splat_dir / "metrics.json").read_text())
    assert metrics["resumed_from_step"] == 20 and metrics["steps"] == 30
    assert metrics["init"]["source"] == "checkpoint"


def test_a_run_its_budget_stops_says_how_far_short_and_how_to_continue(tmp_path: Path, capsys) -> None:
    """The budget counts the whole command: a budget spent before the first step (on loading the images and
    making the initial points) trains no step, and says so in one line with the command that continues; that
    command (--resume with more time) finishes the schedule."""
    scene = write_scene(tmp_path / "s", CAM, plane_views(CAM, [0.45, 0.6], 5))
    assert cli.run(parse(str(scene.root), "--preset", "fast", "--steps", "12", "--device", "cpu", "--init", "depth",
                         "--time-budget", "0.001")) == 0
    out = capsys.readouterr().out
    metrics = json.loads(scene.metrics_path.read_text())
    assert (metrics["steps"], metrics["planned_steps"], metrics["stopped_by"]) == (0, 12, "time budget")
    assert metrics["time_budget"]["used_s"] >= metrics["init_time_s"] > 0.001
    assert "0 of 12 planned steps (stopped by the time budget: 0 s, the whole command)" in out
    lines = [line for line in out.splitlines() if line.startswith("stopped by the time budget")]
    assert len(lines) == 1 and "after 0 of 12 steps, 12 short (loading and the initial points took" in lines[0], out
    command = lines[0].split("continue with ")[1].split(" (another")[0].split()
    assert command[:4] == ["brave6d", "train", str(scene.root), "--preset"] and "--resume" in command
    assert cli.run(parse(*command[2:], "--device", "cpu")) == 0  # the line's own command, as printed
    resumed = capsys.readouterr().out
    metrics = json.loads(scene.metrics_path.read_text())
    assert (metrics["steps"], metrics["stopped_by"], metrics["resumed_from_step"]) == (12, "steps", 0)
    assert "12 of 12 planned steps (all planned steps)" in resumed and "stopped by the time budget" not in resumed


def test_the_budget_line_gives_the_time_the_steps_left_need() -> None:
    metrics = {"steps": 631, "planned_steps": 2000, "stopped_by": "time budget", "train_time_s": 631 * 1.2,
               "init_time_s": 60.0, "time_budget": {"budget_s": 840.0}}
    line = run_outcome.budget_stop_line(metrics, "S", "fast")
    assert line == ("stopped by the time budget (840 s) after 631 of 2000 steps, 1369 short (about 27 min more at "
                    "1.20 s per step): continue with brave6d train S --preset fast --resume --time-budget 1920")
    assert run_outcome.budget_stop_line({**metrics, "steps": 2000, "stopped_by": "steps"}, "S") is None
    near = run_outcome.budget_stop_line({**metrics, "steps": 1990, "train_time_s": 1990 * 1.2}, "S", "fast", 2000)
    assert near == ("stopped by the time budget (840 s) after 1990 of 2000 steps, 10 short (about 12 s more at "
                    "1.20 s per step): continue with brave6d train S --preset fast --steps 2000 --resume "
                    "--time-budget 120")
    assert run_outcome.steps_text(metrics) == ("631 of 2000 planned steps (stopped by the time budget: 840 s, "
                                               "the whole command)")


def test_bad_frame_stops_without_the_flag(trained: SceneDir) -> None:
    with pytest.raises(BraveError, match=r"000003\.png"):
        cli.run(parse(str(trained.root), "--preset", "fast", "--steps", "5", "--device", "cpu"))


def test_missing_calibration_is_named(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "s", CAM, plane_views(CAM, [0.5], 3))
    scene.handeye_path.unlink()
    with pytest.raises(BraveError, match="handeye.json"):
        cli.run(parse(str(scene.root), "--device", "cpu"))


def test_cuda_without_gpu_is_a_clear_error(trained: SceneDir) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    with pytest.raises(BraveError, match="no CUDA GPU"):
        cli.run(parse(str(trained.root), "--device", "cuda", "--steps", "1"))


@pytest.mark.slow
def test_demo_stage_quick(tmp_path: Path, demo_spec_path: Path) -> None:
    from brave6d.core.run_context import RunContext
    from brave6d.core.spec import load_scene_spec
    from brave6d.training.demo import QUICK, stage_train

    scene = write_scene(tmp_path / "demo", CAM, plane_views(CAM, [0.45, 0.6], 6))
    # the training stage reads the scene directory only; the spec is any valid one
    ctx = RunContext(workdir=tmp_path, scene=scene, spec=load_scene_spec(demo_spec_path), quick=True, device="cpu")
    result = stage_train(ctx)
    assert result.name == "train" and result.status == "ok"
    assert result.figures["steps"] == result.figures["planned steps"] == QUICK.steps
    assert result.figures["stopped by"] == "steps"
    assert "holdout PSNR" in result.figures and "PSNR@0.45m" in result.figures and "PSNR@0.60m" in result.figures
    assert (scene.splat_dir / "point_cloud.ply").is_file()


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def kept_aside(splat: Path) -> dict[str, bytes]:
    """The ``<name>.old-<stamp>`` entries of ``splat`` under their original names (as in :func:`snapshot`)."""
    out: dict[str, bytes] = {}
    for path in splat.iterdir():
        name, sep, _ = path.name.partition(".old-")
        if sep and path.is_dir():
            out.update({f"{name}/{k}": v for k, v in snapshot(path).items()})
        elif sep:
            out[name] = path.read_bytes()
    return out


def test_a_new_training_never_leaves_the_user_without_the_previous_one(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from brave6d.training.trainer import Trainer

    scene = write_scene(tmp_path / "s", CAM, plane_views(CAM, [0.45, 0.6], 4))
    args = ("--preset", "fast", "--steps", "8", "--device", "cpu", "--init", "depth")  # a checkpoint every 2 steps
    assert cli.run(parse(str(scene.root), *args)) == 0
    splat = scene.splat_dir
    first = snapshot(splat)
    assert {"checkpoints/ckpt_000008.pt", "point_cloud.ply", "holdout.json", "metrics.json", "curves.png"} <= set(first)
    assert any(k.startswith("holdout/") for k in first)

    # a corrupt frames.jsonl line: stops naming the line, before anything of the training is touched
    good = scene.frames_path.read_bytes()
    lines = good.split(b"\n")
    lines[2] = lines[2][:30]
    scene.frames_path.write_bytes(b"\n".join(lines))
    with pytest.raises(BraveError, match=r"frames\.jsonl:3: not a JSON record"):
        cli.run(parse(str(scene.root), *args))
    assert snapshot(splat) == first
    scene.frames_path.write_bytes(good)

    # a failure before the new run's first checkpoint: the previous training stays as it was
    real_step = Trainer.train_step
    fail_at = {"step": 1}

    def failing_step(self: Trainer) -> dict[str, float]:
        if self.step == fail_at["step"]:
            raise RuntimeError("power cut")
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", failing_step)
    with pytest.raises(RuntimeError, match="power cut"):
        cli.run(parse(str(scene.root), *args))
    assert snapshot(splat) == first
    assert sorted(p.name for p in splat.iterdir()) == sorted({k.split("/")[0] for k in first})  # no leftovers

    # a failure after it: the previous training is kept aside, byte for byte, and the new one resumes
    fail_at["step"] = 3
    with pytest.raises(RuntimeError, match="power cut"):
        cli.run(parse(str(scene.root), *args))
    assert kept_aside(splat) == first
    assert [p.name for p in (splat / "checkpoints").iterdir()] == ["ckpt_000002.pt"]
    assert not [p.name for p in splat.iterdir() if p.name in ("point_cloud.ply", "holdout.json", "metrics.json")]
    monkeypatch.setattr(Trainer, "train_step", real_step)
    assert cli.run(parse(str(scene.root), *args, "--resume")) == 0
    metrics = json.loads((splat / "metrics.json").read_text())
    assert metrics["resumed_from_step"] == 2 and metrics["steps"] == 8
    assert kept_aside(splat) == first

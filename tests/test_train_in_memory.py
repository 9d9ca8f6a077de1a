"""``brave6d.training.train``: a run in memory (nothing written), scored on the holdout during training,
and the same numbers as ``brave6d train`` (``train_scene`` trains through it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from brave6d.core.camera import PinholeCamera
from brave6d.core.layout import SceneDir
from brave6d.training import evaluate_holdout, get_preset, load_scene, read_ply, train, train_scene
from brave6d.training.toy_scenes import plane_views, write_scene

CAM = PinholeCamera.from_hfov(64, 48, 60.0)
PRESET = get_preset("fast").with_steps(12).with_overrides(name="tiny", downscale=1, eval_every=4, max_gaussians=2000,
                                                          max_init_points=1000, time_budget_s=None)


@pytest.fixture()
def scene(tmp_path: Path) -> SceneDir:
    return write_scene(tmp_path / "scene", CAM, plane_views(CAM, [0.3, 0.45], per_ring=5))


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_train_in_memory_writes_nothing_and_scores_the_holdout_on_schedule(scene: SceneDir) -> None:
    data = load_scene(scene, PRESET.downscale)
    before = files_of(scene.root)
    run = train(data, PRESET, "cpu", init_method="depth")
    assert files_of(scene.root) == before  # no splat/, no sparse/, no checkpoints
    assert run.steps == 12 and run.result.stopped_by == "steps"
    assert run.init["source"] == "depth" and run.init["points"] <= PRESET.initialisation.max_init_points
    assert [p.step for p in run.holdout_curve] == [4, 8, 12]
    assert [p.gaussians for p in run.holdout_curve][-1] == run.num_gaussians == run.to_splat().num_gaussians
    final = run.holdout()  # in the training frame, where the curve's scores were taken
    assert run.holdout_curve[-1].psnr == final.psnr and run.holdout_curve[-1].ssim == final.ssim
    world = evaluate_holdout(run.model, data)  # the model back in the world renders the same images
    assert world.psnr == pytest.approx(final.psnr, abs=1e-3) and world.ssim == pytest.approx(final.ssim, abs=1e-5)
    assert [c.get("holdout_psnr") for c in run.result.curve if c["step"] in (4.0, 8.0, 12.0)] == \
        [p.psnr for p in run.holdout_curve]


def test_train_scene_gives_the_numbers_of_train_in_memory(scene: SceneDir) -> None:
    data = load_scene(scene, PRESET.downscale)
    run = train(data, PRESET, "cpu", init_method="depth")
    metrics = train_scene(scene, PRESET, device="cpu", init_method="depth", show_progress=False)
    assert metrics["num_gaussians"] == run.num_gaussians and metrics["steps"] == run.steps
    assert metrics["holdout"]["psnr"] == run.holdout_curve[-1].psnr
    written, in_memory = read_ply(scene.splat_dir / "point_cloud.ply"), run.to_splat()
    for field in ("means", "sh0", "opacities", "scales", "quats"):
        np.testing.assert_array_equal(getattr(written, field), getattr(in_memory, field), err_msg=field)

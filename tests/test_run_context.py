"""The typed orchestrator (issue 33, item 3): ``RunContext.for_scene`` is how the demo, a dataset's
scene job and the rig's commands build a run's context; the stages read what the run chose (rig,
training preset) from it, and a run that chooses nothing trains as the demo always has."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from brave6d.core.errors import BraveError
from brave6d.core.layout import init_scene_dir
from brave6d.pipeline import DEVICES, SIM_RIG, Rig, RunContext
from brave6d.training.presets import PRESETS, get_preset


@pytest.fixture()
def scene_root(tmp_path: Path, demo_spec_path: Path) -> Path:
    return init_scene_dir(tmp_path / "runs" / "scene", demo_spec_path).root


def test_for_scene_reads_the_scene_and_carries_the_choices(scene_root: Path) -> None:
    ctx = RunContext.for_scene(scene_root)
    assert ctx.scene.root == scene_root and ctx.spec.name == "demo_tabletop"
    assert ctx.workdir == scene_root.parent  # the demo's layout: WORKDIR/scene
    assert (ctx.rig, ctx.preset, ctx.quick, ctx.device, ctx.obj_ids, ctx.resume, ctx.results) == \
        (SIM_RIG, None, False, "auto", None, False, [])
    ids = {"hex_nut": 2}
    rig = Rig("ur:10.0.0.9", "oak")
    chosen = RunContext.for_scene(scene_root, workdir=scene_root / "w", rig=rig, preset="default", quick=True,
                                  device="cpu", obj_ids=ids, resume=True)
    ids["hex_nut"] = 7  # the context keeps its own copy
    assert (chosen.workdir, chosen.rig, chosen.preset, chosen.quick, chosen.device, chosen.obj_ids, chosen.resume) \
        == (scene_root / "w", rig, "default", True, "cpu", {"hex_nut": 2}, True)


def test_for_scene_refuses_a_folder_that_is_no_scene_and_an_unknown_device(tmp_path: Path, scene_root: Path) -> None:
    with pytest.raises(BraveError, match=r"nowhere: not a scene directory \(no scene\.yaml\).*brave6d init"):
        RunContext.for_scene(tmp_path / "nowhere")
    with pytest.raises(BraveError, match="device 'tpu': expected one of auto, cpu, cuda"):
        RunContext.for_scene(scene_root, device="tpu")
    assert DEVICES == ("auto", "cpu", "cuda")


@given(st.sampled_from(["sim", "ur:10.0.0.9", "oak", ""]), st.sampled_from(["sim", "oak", "ur:h"]))
def test_a_rig_is_simulated_only_when_robot_and_camera_are(robot: str, camera: str) -> None:
    rig = Rig(robot, camera)
    assert rig.simulated == (robot == "sim" and camera == "sim")
    assert str(rig) == f"--robot {robot} --camera {camera}"


def test_a_run_that_chooses_no_preset_trains_as_the_demo_did() -> None:
    from brave6d.training.demo import QUICK, run_preset

    fast = get_preset("fast")
    assert run_preset(None) == fast
    # the miniature of `brave6d demo --quick`, as it was defined before the run could choose
    assert QUICK == run_preset(None, quick=True) == fast.with_steps(150).with_overrides(
        name="fast-quick", downscale=4, time_budget_s=180.0, max_gaussians=30_000, max_init_points=20_000)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_the_chosen_preset_is_the_one_trained(name: str) -> None:
    from brave6d.training.demo import run_preset

    assert run_preset(name) == get_preset(name)
    quick = run_preset(name, quick=True)
    assert quick.name == f"{name}-quick" and quick.steps == 150 and quick.downscale == 4


def test_an_unknown_preset_fails_before_training_naming_the_known_ones(scene_root: Path) -> None:
    from brave6d.training.demo import stage_train

    with pytest.raises(BraveError, match=r"unknown preset 'fastest'.*'default'.*'fast'"):
        stage_train(RunContext.for_scene(scene_root, preset="fastest"))


def test_the_rig_stages_use_the_runs_rig(scene_root: Path) -> None:
    """Before, the capture and calibrate stages always opened the simulated rig, whatever the run's."""
    from brave6d.calibration.demo import stage_calibrate
    from brave6d.capture.demo import stage_capture

    ctx = RunContext.for_scene(scene_root, rig=Rig("ur:10.0.0.9", "sim"))  # refused by the rig, before any motion
    for stage in (stage_calibrate, stage_capture):
        with pytest.raises(BraveError, match=r"--robot ur:10\.0\.0\.9 --camera sim: a simulated camera cannot film"):
            stage(ctx)
    assert not ctx.scene.frames_path.exists() and not ctx.scene.board_capture.frames_path.exists()


def test_the_annotate_stage_refuses_a_real_rig(scene_root: Path) -> None:
    """It writes the simulator's true poses: a real capture has none and is annotated by a person."""
    from brave6d.annotation.demo import stage_annotation

    with pytest.raises(BraveError, match=r"--robot ur:h --camera oak has none.*brave6d annotate import-3ddat"):
        stage_annotation(RunContext.for_scene(scene_root, rig=Rig("ur:h", "oak")))


def test_the_demo_builds_its_context_with_the_constructor(tmp_path: Path) -> None:
    from brave6d.core.run_context import QUICK_CAPTURE
    from brave6d.pipeline.demo import prepare

    ctx = prepare(tmp_path / "demo", quick=True, device="cpu")
    assert ctx.workdir == tmp_path / "demo" and ctx.scene.root == tmp_path / "demo" / "scene"
    assert (ctx.rig, ctx.preset, ctx.quick, ctx.device) == (SIM_RIG, None, True, "cpu")
    assert ctx.spec.name == "demo_tabletop_quick"
    assert ctx.spec.capture.views_per_distance == QUICK_CAPTURE["views_per_distance"]

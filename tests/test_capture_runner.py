"""The capture runner with the simulated robot and camera: resume after a kill, refusals, faults."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from brave6d.core.atomic import read_json, read_png
from brave6d.core.errors import DataError
from brave6d.capture.backends import open_rig
from brave6d.capture.cli import make_plan
from brave6d.capture.protocols import RobotError
from brave6d.capture.runner import CaptureExistsError, CaptureOptions, run_capture

from capture_helpers import small_scene


def test_capture_writes_frames_and_refuses_overwrite(tmp_path: Path, demo_spec_path: Path) -> None:
    scene = small_scene(tmp_path, demo_spec_path)
    plan = make_plan(scene)
    spec = scene.load_spec()
    with open_rig(spec) as rig:
        summary = run_capture(scene.capture, plan.views, rig.robot, rig.camera)
    records = scene.frames()
    assert summary.written == len(plan.views) == len(records) > 0
    assert [r.index for r in records] == list(range(len(records)))
    for record in records:
        rgb = read_png(scene.capture_dir / record.rgb, "rgb")
        depth = read_png(scene.capture_dir / str(record.depth), "depth")
        assert rgb.shape == (100, 160, 3) and depth.shape == (100, 160)
        assert 150 < np.median(depth[depth > 0]) < 800  # millimetres: the table at 0.3-0.45 m
    assert read_json(scene.capture.camera_path)["intrinsics"]["width"] == 160
    with open_rig(spec) as rig, pytest.raises(CaptureExistsError, match="complete capture exists.*--force"):
        run_capture(scene.capture, plan.views, rig.robot, rig.camera)
    with open_rig(spec) as rig:  # --force keeps the old capture aside, never deletes it
        run_capture(scene.capture, plan.views[:1], rig.robot, rig.camera, CaptureOptions(force=True))
    aside = [p for p in scene.root.iterdir() if p.name.startswith("capture.old-")]
    assert len(aside) == 1 and len((aside[0] / "frames.jsonl").read_text().splitlines()) == len(records)
    assert len(scene.frames()) == 1


def test_robot_fault_stops_arm_and_keeps_frames(tmp_path: Path, demo_spec_path: Path) -> None:
    scene = small_scene(tmp_path, demo_spec_path)
    plan = make_plan(scene)
    spec = scene.load_spec()
    with open_rig(spec) as rig:
        robot = rig.robot
        original = robot.move_joints
        stops: list[float] = []
        calls = {"n": 0}

        def faulty_move(q: np.ndarray) -> None:
            calls["n"] += 1
            if calls["n"] == 3:
                raise RobotError("protective stop (simulated fault)")
            original(q)

        original_stop = robot.stop
        robot.move_joints = faulty_move  # type: ignore[method-assign]
        robot.stop = lambda: (stops.append(robot.now()), original_stop())  # type: ignore[method-assign]
        with pytest.raises(RobotError, match="protective stop"):
            run_capture(scene.capture, plan.views, robot, rig.camera)
    assert len(stops) == 1, "the arm must be stopped on a fault"
    assert len(scene.frames()) == 2
    with open_rig(spec) as rig:
        summary = run_capture(scene.capture, plan.views, rig.robot, rig.camera, CaptureOptions(resume=True))
    assert summary.resumed_from == 2 and summary.total == len(plan.views)


def test_resume_refuses_other_camera(tmp_path: Path, demo_spec_path: Path) -> None:
    scene = small_scene(tmp_path, demo_spec_path)
    plan = make_plan(scene)
    spec = scene.load_spec()
    with open_rig(spec) as rig:
        run_capture(scene.capture, plan.views[:1], rig.robot, rig.camera)
    other = spec.model_copy(update={"camera": spec.camera.model_copy(update={"hfov_deg": 60.0})})
    with open_rig(other) as rig, pytest.raises(DataError, match="intrinsics differ"):
        run_capture(scene.capture, plan.views, rig.robot, rig.camera, CaptureOptions(resume=True))


@pytest.mark.slow
def test_killed_capture_resumes_without_loss_or_duplicates(tmp_path: Path, demo_spec_path: Path) -> None:
    scene = small_scene(tmp_path, demo_spec_path, views=8)
    plan = make_plan(scene)
    n = len(plan.views)
    cmd = [sys.executable, "-m", "brave6d.cli", "capture", "run", str(scene.root)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline:
        done = len(scene.frames_path.read_text().splitlines()) if scene.frames_path.exists() else 0
        if done >= 3:
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    kept = scene.frames()
    assert 3 <= len(kept) < n, "the kill must land mid-run"
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 2 and "--resume" in again.stderr  # refuses without --resume
    resumed = subprocess.run([*cmd, "--resume"], capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    records = scene.frames()
    assert sorted(r.view_id for r in records) == sorted(str(v.view_id) for v in plan.views)
    assert sorted(r.index for r in records) == list(range(n))  # no frame lost, none twice
    assert records[: len(kept)] == kept  # finished frames untouched
    for record in records:
        read_png(scene.capture_dir / record.rgb, "rgb")


def test_replanning_is_refused_while_frames_exist_and_force_keeps_a_plan_beside_the_new_frames(
        tmp_path: Path, demo_spec_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Frames are named by their index in the plan: a new plan under old frames could write over them."""
    from brave6d.cli import main

    scene = small_scene(tmp_path, demo_spec_path, views=2)
    assert main(["capture", "run", str(scene.root)]) == 0
    plan_before = scene.capture.plan_path.read_bytes()
    frames_before = scene.capture.frames_path.read_bytes()
    assert main(["capture", "plan", str(scene.root)]) != 0
    assert "frames exist" in capsys.readouterr().err
    assert scene.capture.plan_path.read_bytes() == plan_before
    assert scene.capture.frames_path.read_bytes() == frames_before

    assert main(["capture", "run", str(scene.root), "--force"]) == 0
    aside = [p for p in scene.root.iterdir() if p.name.startswith("capture.old-")]
    assert len(aside) == 1
    assert (aside[0] / "plan.json").read_bytes() == plan_before  # the old plan went with its frames
    assert (aside[0] / "frames.jsonl").read_bytes() == frames_before
    assert scene.capture.plan_path.is_file()  # and the new frames have their plan beside them
    new_plan = read_json(scene.capture.plan_path)
    assert [str(v["view_id"]) for v in new_plan["views"]] == [r.view_id for r in scene.frames()]

"""The scene-directory calibration pipeline, its CLI and its demo stage, on the demo scene.

One small simulated board capture (10 views, the demo camera shrunk to 480 x 300 for speed,
every simulation effect of the demo spec on) is made once per module; the other tests work on
copies of it or on hand-made board captures, so the file stays well under a minute.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.atomic import atomic_write_json, write_png
from brave6d.core.calibration_io import read_handeye, read_intrinsics
from brave6d.cli import main
from brave6d.core.run_context import RunContext
from brave6d.core.errors import DegenerateGeometryError
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir, init_scene_dir, write_spec
from brave6d.core.spec import load_scene_spec
from brave6d.core.transforms import rotation_distance, translation_distance
from brave6d.calibration.board_capture import BoardPlan, plan_board_capture

VIEWS = 10


def brave6d(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """Run the CLI in this process; (exit status, stdout, stderr without progress bars)."""
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip() and "frame/s]" not in line and "it/s]" not in line]
    return rc, out, "\n".join(lines)


def one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory, demo_spec_path: Path) -> SceneDir:
    """A demo scene directory after ``brave6d calibrate all`` (small camera, 10 board views); its
    tests are marked slow, so `-m "not slow"` never builds it."""
    scene = init_scene_dir(tmp_path_factory.mktemp("cal") / "scene", demo_spec_path)
    spec = scene.load_spec()
    write_spec(scene, spec.model_copy(update={"camera": spec.camera.model_copy(update={"width": 480, "height": 300})}))
    assert main(["calibrate", "all", str(scene.root), "--views", str(VIEWS)]) == 0
    return scene


def copy_scene(scene: SceneDir, dst: Path) -> SceneDir:
    shutil.copytree(scene.root, dst, symlinks=True)
    return SceneDir(dst)


# ----------------------------------------------------------------------------- the full pipeline
@pytest.mark.slow
def test_all_writes_what_later_stages_read(calibrated: SceneDir) -> None:
    spec = calibrated.load_spec()
    camera = read_intrinsics(calibrated)
    assert (camera.width, camera.height) == (480, 300) and len(camera.dist) == 5
    truth_cam = spec.camera.pinhole()
    assert abs(camera.fx - truth_cam.fx) < 1.5 and abs(camera.cx - truth_cam.cx) < 1.5
    X = read_handeye(calibrated)
    truth = spec.simulation.true_tcp_T_camera.matrix()
    mm, deg = 1000 * translation_distance(X, truth), np.degrees(rotation_distance(X, truth))
    details = json.loads(calibrated.handeye_path.read_text())
    unc = details["uncertainty"]
    assert mm < 2.0 and deg < 0.2, (mm, deg)
    assert mm < 3 * unc["translation_sigma_norm_mm"] + 0.1 and deg < 3 * unc["rotation_sigma_norm_deg"] + 0.01
    # every closed-form result, residuals, uncertainty and the check against the truth are recorded
    assert details["method"].startswith("refined")
    assert {m["method"] for m in details["methods"]} == {"tsai", "park", "daniilidis", "refined"}
    assert details["residuals"]["reprojection_rms_px"] < 1.0 and details["residuals"]["n_views"] == VIEWS
    check = details["simulation_check"]["errors"]["refined"]
    assert check["translation_mm"] == pytest.approx(mm, abs=1e-6)
    assert "truth" not in json.dumps({k: v for k, v in details.items() if k != "simulation_check"}).lower()
    intr = json.loads(calibrated.intrinsics_path.read_text())
    assert intr["source"] == "charuco" and intr["rms_px"] < 0.5 and "simulation_check" in intr
    report = (calibrated.calibration_dir / "report.md").read_text()
    assert "| refined |" in report and "| tsai |" in report and "error mm" in report
    assert (calibrated.calibration_dir / "report_residuals.png").stat().st_size > 1000
    plan = BoardPlan.load(calibrated.board_capture.plan_path)
    assert len(plan.views) == VIEWS and len(calibrated.board_capture.frames()) == VIEWS


@pytest.mark.slow
def test_rerun_refuses_without_resume_or_force(calibrated: SceneDir, capsys: pytest.CaptureFixture[str]) -> None:
    before = calibrated.handeye_path.stat().st_mtime_ns
    for action in ("all", "capture"):
        rc, _, err = brave6d(capsys, "calibrate", action, calibrated.root)
        line = one_error_line(err)
        assert rc == 2 and str(calibrated.board_capture.frames_path) in line and "--resume" in line
    rc, _, err = brave6d(capsys, "calibrate", "plan", calibrated.root)
    assert rc == 2 and "--force" in one_error_line(err)
    assert calibrated.handeye_path.stat().st_mtime_ns == before


@pytest.mark.slow
def test_resume_of_a_complete_capture_recalibrates_only(calibrated: SceneDir, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    scene = copy_scene(calibrated, tmp_path / "scene")
    frames_before = scene.board_capture.frames_path.read_bytes()
    rc, out, _ = brave6d(capsys, "calibrate", "all", scene.root, "--resume")
    assert rc == 0 and "0 frames captured now, 10 in all" in out and "error vs simulator truth" in out
    assert scene.board_capture.frames_path.read_bytes() == frames_before
    assert np.allclose(read_handeye(scene), read_handeye(calibrated), atol=1e-7)


@pytest.mark.slow
def test_interrupted_capture_resumes_with_its_plan(calibrated: SceneDir, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    scene = copy_scene(calibrated, tmp_path / "scene")
    log = scene.board_capture.frames_path
    log.write_text("".join(log.read_text().splitlines(keepends=True)[:VIEWS - 3]))
    rc, out, _ = brave6d(capsys, "calibrate", "capture", scene.root, "--resume")
    assert rc == 0 and f"3 frames captured now, {VIEWS} in all" in out
    assert [r.view_id for r in scene.board_capture.frames()] == [v.view_id for v in
                                                                 BoardPlan.load(scene.board_capture.plan_path).views]


@pytest.mark.slow
def test_factory_intrinsics_keep_the_capture_camera(calibrated: SceneDir, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    scene = copy_scene(calibrated, tmp_path / "scene")
    rc, out, _ = brave6d(capsys, "calibrate", "intrinsics", scene.root, "--factory-intrinsics")
    assert rc == 0 and "intrinsics (factory)" in out
    captured = json.loads(scene.board_capture.camera_path.read_text())["intrinsics"]
    assert np.allclose(read_intrinsics(scene).K, captured["K"])
    assert json.loads(scene.intrinsics_path.read_text())["rms_px"] < 0.3  # the simulator's camera is the truth


@pytest.mark.slow
def test_conditioning_failure_is_one_line(calibrated: SceneDir, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    scene = copy_scene(calibrated, tmp_path / "scene")
    records = scene.board_capture.frames()
    R0 = records[0].base_T_tcp_matrix[:3, :3]
    pure_translations = []
    for r in records:  # same robot rotation everywhere: the camera's rotation on the flange is undetermined
        T = r.base_T_tcp_matrix.copy()
        T[:3, :3] = R0
        pure_translations.append(r.model_copy(update={"base_T_tcp": T.tolist()}))
    scene.board_capture.frames_path.unlink()
    for r in pure_translations:
        FrameLog(scene.board_capture.frames_path).append(r)
    rc, _, err = brave6d(capsys, "calibrate", "handeye", scene.root)
    line = one_error_line(err)
    assert rc == 2 and str(scene.board_capture.root) in line
    assert "pure translations" in line or "robot and camera motions disagree" in line


@pytest.mark.slow
def test_demo_stage_reuses_results_newer_than_the_frames(calibrated: SceneDir, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import brave6d.calibration.demo as demo

    scene = copy_scene(calibrated, tmp_path / "scene")
    monkeypatch.setattr(demo, "QUICK_VIEWS", VIEWS)
    ctx = RunContext(workdir=tmp_path, scene=scene, spec=scene.load_spec(), quick=True)
    reused = demo.stage_calibrate(ctx)
    assert reused.status == "reused" and reused.figures["board views"] == VIEWS
    assert reused.figures["error vs truth mm"] < 2.0 and reused.figures["hand-eye RMS px"] < 1.0
    scene.board_capture.frames_path.touch()  # frames newer than the results: recalibrate, capture nothing
    again = demo.stage_calibrate(ctx)
    assert again.status == "ok" and again.figures["board views"] == VIEWS
    assert again.figures["error vs truth mm"] == pytest.approx(reused.figures["error vs truth mm"], abs=1e-3)


# ----------------------------------------------------------------------------- bad input, clear errors
def blank_board_capture(scene: SceneDir, n: int, board_frames: dict[int, Path] | None = None) -> None:
    """A board capture of ``n`` frames showing no board (except ``board_frames``: index -> image)."""
    layout = scene.board_capture
    cam = scene.load_spec().camera.pinhole()
    atomic_write_json(layout.camera_path, {"intrinsics": cam.to_json()})
    log = FrameLog(layout.frames_path)
    layout.rgb_dir.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        name = f"{i:06d}.png"
        src = (board_frames or {}).get(i)
        if src is not None:
            shutil.copy(src, layout.rgb_dir / name)
        else:
            write_png(layout.rgb_dir / name, np.full((cam.height, cam.width, 3), 180, np.uint8))
        T = np.eye(4)
        T[:3, 3] = [0.3 + 0.01 * i, -0.1, 0.4]
        log.append(FrameRecord(index=i, view_id=f"calib_{i:03d}", distance_level=0, distance_m=0.3, rgb=f"rgb/{name}",
                               base_T_tcp=T.tolist(), joints=[0.0] * 6, timestamp=float(i)))


def test_board_not_visible_names_the_cause(tmp_path: Path, demo_spec_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    scene = init_scene_dir(tmp_path / "scene", demo_spec_path)
    rc, _, err = brave6d(capsys, "calibrate", "intrinsics", scene.root)
    line = one_error_line(err)
    assert rc == 2 and "no board frames" in line and str(scene.board_capture.frames_path) in line
    blank_board_capture(scene, 4)
    rc, _, err = brave6d(capsys, "calibrate", "intrinsics", scene.root)
    line = one_error_line(err)
    assert rc == 2 and "detected in none of the 4 board frames" in line and "000000.png" in line


@pytest.mark.slow
def test_too_few_detections_names_the_frames(calibrated: SceneDir, tmp_path: Path, demo_spec_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    scene = init_scene_dir(tmp_path / "scene", demo_spec_path)
    write_spec(scene, calibrated.load_spec())
    rgb = calibrated.board_capture.rgb_dir
    blank_board_capture(scene, 6, {0: rgb / "000000.png", 1: rgb / "000001.png"})
    rc, _, err = brave6d(capsys, "calibrate", "intrinsics", scene.root)
    line = one_error_line(err)
    assert rc == 2 and str(scene.board_capture.root) in line
    assert "2 usable views of 6" in line and "rgb/000002.png: no board detected" in line


@pytest.mark.parametrize("args, expected", [
    (("calibrate", "all", "{missing}"), "not a scene directory"),
    (("calibrate", "plan", "{scene}", "--views", "2"), "at least 3 views"),
    (("calibrate", "plan", "{scene}", "--robot", "ur:10.0.0.9"), "a simulated camera cannot film a real arm"),
    (("calibrate", "plan", "{scene}", "--robot", "sim", "--camera", "oak"), "a real camera cannot see the simulated"),
    (("calibrate", "capture", "{scene}", "--resume", "--force"), "exclude each other"),
    (("calibrate", "intrinsics", "{scene}", "--distortion", "7"), "unknown model"),
])
def test_bad_input_is_one_line_and_status_2(args: tuple[str, ...], expected: str, tmp_path: Path,
                                            demo_spec_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = init_scene_dir(tmp_path / "scene", demo_spec_path)
    filled = [a.format(scene=scene.root, missing=tmp_path / "missing") for a in args]
    rc, _, err = brave6d(capsys, *filled)
    assert rc == 2 and expected in one_error_line(err)


# ----------------------------------------------------------------------------- distortion model choice
@pytest.mark.parametrize("p1, expected", [(0.0, "radial"), (0.004, "5")])
def test_auto_distortion_fits_tangential_terms_only_when_the_data_show_them(p1: float, expected: str) -> None:
    from brave6d.calibration import CharucoDetection, board_corner_points
    from brave6d.calibration.intrinsics import calibrate_intrinsics_auto
    from brave6d.calibration.known_truth import default_board, default_K, project_corners, random_board_views

    board, K, size = default_board(), default_K(), (640, 480)
    obj = board_corner_points(board)
    dist = np.array([-0.08, 0.03, p1, 0.0, 0.0])
    rng = np.random.default_rng(3)
    detections = []
    for board_T_cam in random_board_views(20, 35.0, 0.4, obj.mean(axis=0), rng):
        ids, uv = project_corners(obj, np.linalg.inv(board_T_cam), K, dist, size)
        detections.append(CharucoDetection(ids, uv + rng.normal(0.0, 0.1, uv.shape)))
    result = calibrate_intrinsics_auto(detections, obj, size)
    assert result.distortion_model == expected and len(result.notes) == 1
    assert result.dist[2] == pytest.approx(p1, abs=5e-4) and abs(result.K[0, 2] - K[0, 2]) < 4 * result.std["cx"]


# ----------------------------------------------------------------------------- planning (property)
class FakeRobot:
    """IK that refuses TCP poses below ``y_min`` and needs a flipped arm beyond ``x_flip``."""

    def __init__(self, y_min: float, x_flip: float) -> None:
        self.y_min, self.x_flip = y_min, x_flip

    def joints(self) -> np.ndarray:
        return np.zeros(6)

    def inverse_kinematics(self, T: np.ndarray, q_near: np.ndarray | None = None) -> np.ndarray | None:
        if T[1, 3] < self.y_min:
            return None
        q = 0.1 * np.r_[T[:3, 3], 0.0, 0.0, 0.0]
        if T[0, 3] > self.x_flip:
            q[1] += np.pi  # the other elbow
        return q


@settings(max_examples=25)
@given(n=st.integers(3, 16), y_min=st.floats(-0.6, -0.1), x_flip=st.floats(0.3, 0.9))
def test_plan_keeps_only_reachable_views(tmp_path_factory: pytest.TempPathFactory, demo_spec_path: Path, n: int,
                                         y_min: float, x_flip: float) -> None:
    spec = load_scene_spec(demo_spec_path)
    robot = FakeRobot(y_min, x_flip)
    try:
        plan = plan_board_capture(spec, robot, n)
    except DegenerateGeometryError as exc:
        assert "out of the robot's reach" in str(exc) or "at least 3 needed" in str(exc)
        return
    assert 3 <= len(plan.views) <= n
    assert len({v.base_T_tcp[0, 3] > x_flip for v in plan.views}) == 1  # one arm configuration
    for v in plan.views:
        assert v.base_T_tcp[1, 3] >= y_min
        assert np.allclose(v.base_T_cam[:3, 3], (v.base_T_tcp @ spec.robot.tcp_T_camera_guess.matrix())[:3, 3])
    for d in plan.dropped:
        assert "unreachable" in d["reason"] or "another arm configuration" in d["reason"] or "workspace" in d["reason"]
    examined = sorted([v.view_id for v in plan.views] + [d["view_id"] for d in plan.dropped])
    assert examined == [f"calib_{k:03d}" for k in range(len(examined))]  # nothing skipped, nothing twice
    if len(plan.views) < n:
        assert len(examined) == n + max(6, n // 2)  # every spare candidate was tried
    path = tmp_path_factory.mktemp("plan") / "plan.json"
    loaded = BoardPlan.load(plan.save(path))
    assert [v.view_id for v in loaded.views] == [v.view_id for v in plan.views]
    assert all(np.allclose(a.joints, b.joints) for a, b in zip(loaded.views, plan.views))

"""``brave6d calibrate folder``: a simulated eye-in-hand set (no real eye-in-hand set with a
permissive licence was found): images rendered by the project's board renderer with lens
distortion and sensor noise, robot poses with pose error in a UR pose-vector file. Checked
against the simulator's truth and OpenCV's calibrateHandEye; the command's errors."""

from __future__ import annotations

import json
import math
import re

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from brave6d.cli import main
from brave6d.core.calibration_io import read_camera_json
from brave6d.core.transforms import invert, make_transform
from brave6d.calibration import HandEyeResult, IntrinsicsCovariance, board_corner_points
from brave6d.calibration.known_truth import (
    default_board,
    default_tcp_T_cam,
    perturb_pose,
    random_board_views,
    render_board_view,
)

SPEC = default_board()  # the BoardSpec defaults: 7 x 5 squares of 30 mm, 22 mm markers, DICT_5X5_100
W = SPEC.pose.matrix()
X = default_tcp_T_cam()
K = np.array([[610.0, 0.0, 322.0], [0.0, 608.0, 236.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.08, 0.03, 0.0, 0.0, 0.0])
SIZE = (640, 480)


@pytest.fixture(scope="module")
def eye_in_hand_set(tmp_path_factory):
    """14 rendered views (+-35 deg), robot poses with 0.1 mm / 0.01 deg error, as UR pose vectors."""
    root = tmp_path_factory.mktemp("eye_in_hand")
    (root / "images").mkdir()
    rng = np.random.default_rng(11)
    centre = np.array([0.105, 0.075, 0.0])
    lines = ["# x y z rx ry rz (UR pose vector, m and rad), one line per image in natural order"]
    for k, board_T_cam in enumerate(random_board_views(14, 35.0, 0.42, centre, rng)):
        cam_T_board = invert(board_T_cam)
        image = render_board_view(SPEC, K, cam_T_board, SIZE, DIST, noise_sigma=2.0, rng=rng)
        cv2.imwrite(str(root / "images" / f"view{k}.png"), image)
        G = perturb_pose(W @ board_T_cam @ invert(X), 1e-4, 0.01, rng)
        lines.append(" ".join(f"{v:.9f}" for v in [*G[:3, 3], *Rotation.from_matrix(G[:3, :3]).as_rotvec()]))
    (root / "robot_poses.txt").write_text("\n".join(lines) + "\n")
    return root


def _run(capsys, *args) -> tuple[int, str, str]:
    rc = main(["calibrate", "folder", *map(str, args)])
    out, err = capsys.readouterr()
    return rc, out, err


def _errors(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    return (1000.0 * float(np.linalg.norm(A[:3, 3] - B[:3, 3])),
            math.degrees(Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).magnitude()))


def test_simulated_eye_in_hand_folder_calibrates_to_the_truth(eye_in_hand_set, capsys) -> None:
    root = eye_in_hand_set
    rc, out, err = _run(capsys, root / "images", "--poses", root / "robot_poses.txt", "--pose-format", "ur")
    assert rc == 0, err
    assert "14 images paired with the robot poses of" in out and "by sorted order" in out
    out_dir = root / "images" / "calibration"
    result = HandEyeResult.load(out_dir / "handeye.json")
    u = result.uncertainty
    assert u is not None and u.translation_sigma_norm_mm <= 2.0 and u.rotation_sigma_norm_deg <= 0.2
    mm, deg = _errors(result.tcp_T_cam, X)
    assert mm < 3 * u.translation_sigma_norm_mm and deg < 3 * u.rotation_sigma_norm_deg, (mm, deg, u)
    camera = read_camera_json(out_dir / "intrinsics.json", "camera")
    assert abs(camera.fx - K[0, 0]) < 3.0 and abs(camera.cx - K[0, 2]) < 3.0
    assert result.intrinsics_std is not None  # refined jointly (intrinsics calibrated from these images)
    assert (out_dir / "report.md").read_text().startswith("# Calibration report")

    # OpenCV's own chain (its detector, its PnP on our intrinsics, calibrateHandEye) finds the same camera
    board = cv2.aruco.CharucoBoard((7, 5), 0.03, 0.022, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100))
    detector = cv2.aruco.CharucoDetector(board)
    lines = [ln for ln in (root / "robot_poses.txt").read_text().splitlines() if not ln.startswith("#")]
    R_g, t_g, R_c, t_c = [], [], [], []
    for k, line in enumerate(lines):
        corners, ids, _, _ = detector.detectBoard(cv2.imread(str(root / "images" / f"view{k}.png"), cv2.IMREAD_GRAYSCALE))
        if ids is None or len(ids) < 6:
            continue
        obj, img = board.matchImagePoints(corners, ids)
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist_array)
        v = np.array(line.split(), dtype=float)
        R_g.append(Rotation.from_rotvec(v[3:]).as_matrix())
        t_g.append(v[:3])
        R_c.append(cv2.Rodrigues(rvec)[0])
        t_c.append(tvec.reshape(3))
    R_x, t_x = cv2.calibrateHandEye(R_g, t_g, R_c, t_c, method=cv2.CALIB_HAND_EYE_PARK)
    opencv = make_transform(R_x, t_x.reshape(3))
    theirs = _errors(opencv, X)
    assert theirs[0] < 5.0 and theirs[1] < 0.5, theirs
    agree = _errors(opencv, result.tcp_T_cam)
    assert agree[0] < 3 * u.translation_sigma_norm_mm + theirs[0] and agree[1] < 3 * u.rotation_sigma_norm_deg + theirs[1]

    # the same images calibrated as a static camera: the run says which set-up fits
    rc, _, err = _run(capsys, root / "images", "--poses", root / "robot_poses.txt", "--pose-format", "ur",
                      "--eye-to-hand", "--out", root / "wrong")
    assert rc == 2 and "do not fit eye-to-hand" in err and "calibrate without --eye-to-hand" in err


def test_given_intrinsics_are_held_and_limits_are_options(eye_in_hand_set, capsys, tmp_path) -> None:
    root = eye_in_hand_set
    camera = {"camera": {"width": 640, "height": 480, "K": K.tolist(), "dist": DIST.tolist()}}
    (tmp_path / "cam.json").write_text(json.dumps(camera))
    rc, out, err = _run(capsys, root / "images", "--poses", root / "robot_poses.txt", "--pose-format", "ur",
                        "--intrinsics", tmp_path / "cam.json", "--out", tmp_path / "held")
    assert rc == 0, err
    held = HandEyeResult.load(tmp_path / "held" / "handeye.json")
    assert held.intrinsics_std is None and np.allclose(held.K, K)
    rc, _, err = _run(capsys, root / "images", "--poses", root / "robot_poses.txt", "--pose-format", "ur",
                      "--max-sigma-mm", "0.001", "--out", tmp_path / "tight")
    assert rc == 2 and "exceeds the limits 0.001 mm / 0.2 deg" in err and "Dominant cause:" in err
    assert not (tmp_path / "tight" / "handeye.json").exists()


@pytest.mark.parametrize("extra, message", [
    ((), "does not fit|6 numbers are ambiguous"),
    (("--pose-format", "ur", "--squares-x", "5"), "detected in none of the 14 images"),
    (("--pose-format", "ur", "--square-mm", "20", "--marker-mm", "25"), "marker_length_m must be smaller"),
    (("--pose-format", "ur", "--match", "stem"), "not named; pair them by sorted order"),
])
def test_folder_errors_are_one_line(eye_in_hand_set, capsys, tmp_path, extra, message) -> None:
    root = eye_in_hand_set
    rc, _, err = _run(capsys, root / "images", "--poses", root / "robot_poses.txt", *extra, "--out", tmp_path)
    assert rc == 2
    assert len(err.strip().splitlines()) == 1
    assert re.search(message, err), err


def test_options_belong_to_their_action(capsys, tmp_path) -> None:
    from brave6d.calibration import HandEyeOptions
    from brave6d.calibration.cli import DEFAULT_MAX_SIGMA_DEG, DEFAULT_MAX_SIGMA_MM

    assert (HandEyeOptions().max_sigma_mm, HandEyeOptions().max_sigma_deg) == (DEFAULT_MAX_SIGMA_MM, DEFAULT_MAX_SIGMA_DEG)
    assert main(["calibrate", "all", str(tmp_path), "--poses", "p"]) == 2
    assert "options of 'brave6d calibrate folder' only" in capsys.readouterr().err
    assert main(["calibrate", "folder", str(tmp_path)]) == 2
    assert "--poses PATH is required" in capsys.readouterr().err
    assert main(["calibrate", "folder", str(tmp_path), "--poses", "p", "--views", "5"]) == 2
    assert "options of the scene actions" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["calibrate", "folder", str(tmp_path), "--poses", "p", "--max-sigma-mm", "nan"])


def test_duplicate_and_too_few_poses_are_named(eye_in_hand_set, capsys, tmp_path) -> None:
    root = eye_in_hand_set
    lines = [ln for ln in (root / "robot_poses.txt").read_text().splitlines() if not ln.startswith("#")]
    images = tmp_path / "img"
    images.mkdir()
    for k in (0, 1, 2):
        (images / f"view{k}.png").write_bytes((root / "images" / f"view{k}.png").read_bytes())
    (images / "view3.png").write_bytes((root / "images" / "view1.png").read_bytes())
    (tmp_path / "p.txt").write_text("\n".join([lines[0], lines[1], lines[2], lines[1]]))
    rc, _, err = _run(capsys, images, "--poses", tmp_path / "p.txt", "--pose-format", "ur", "--out", tmp_path / "o")
    assert rc == 2 and "duplicated poses: views view1.png and view3.png" in err
    (tmp_path / "p2.txt").write_text("\n".join(lines[:2]))
    (images / "view2.png").unlink()
    (images / "view3.png").unlink()
    rc, _, err = _run(capsys, images, "--poses", tmp_path / "p2.txt", "--pose-format", "ur", "--out", tmp_path / "o")
    assert rc == 2 and ("too few poses" in err or "usable views" in err), err


def test_intrinsics_covariance_json_round_trip() -> None:
    cov = IntrinsicsCovariance(("fx", "cx"), np.array([[4.0, 1.0], [1.0, 9.0]]))
    back = IntrinsicsCovariance.from_json(json.loads(json.dumps(cov.to_json())))
    assert back.names == cov.names and np.allclose(back.matrix, cov.matrix)
    assert back.std() == {"fx": 2.0, "cx": 3.0}
    with pytest.raises(ValueError, match="unknown parameter names"):
        IntrinsicsCovariance(("focal",), np.eye(1))
    assert board_corner_points(SPEC).shape == (24, 3)

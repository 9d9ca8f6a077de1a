"""``brave6d calibrate plan|capture|intrinsics|handeye|all SCENE_DIR``: board capture and calibration;
``brave6d calibrate folder IMAGES --poses POSES``: calibration from any folder.

Registered in ``brave6d/cli.py`` as ``Command("calibrate", "brave6d.calibration.cli", ...)``.
``all`` = plan + capture + intrinsics + hand-eye + report; each action can also run alone
(``handeye`` then uses the intrinsics already in ``calibration/intrinsics.json``). ``folder``
calibrates images taken elsewhere with their robot poses from files, eye-in-hand or eye-to-hand
(:mod:`brave6d.calibration.folder`); the board is described by options. The hand-eye acceptance
limits (``--max-sigma-mm``, ``--max-sigma-deg``) apply to ``handeye``, ``all`` and ``folder``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.core.cli_types import float_in, int_in
from brave6d.core.errors import BraveError
from brave6d.core.run_context import RunContext, Rig

ACTIONS = ("plan", "capture", "intrinsics", "handeye", "all", "folder")
#: Options of 'calibrate folder' only (their defaults are None, so a scene action can refuse them).
FOLDER_ONLY = ("poses", "out", "match", "pose_format", "quaternion_order", "pose_unit", "squares_x", "squares_y",
               "square_mm", "marker_mm", "dictionary", "dictionary_file", "intrinsics", "refine_intrinsics")
#: Today's acceptance limits of a hand-eye result (HandEyeOptions' defaults).
DEFAULT_MAX_SIGMA_MM, DEFAULT_MAX_SIGMA_DEG = 2.0, 0.2
#: The robot error model's starting values (HandEyeOptions' defaults).
DEFAULT_ROBOT_SIGMA_MM, DEFAULT_ROBOT_SIGMA_DEG = 0.1, 0.01


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=ACTIONS, metavar="ACTION",
                        help="plan: plan the board views the robot can reach (calibration/board_capture/plan.json); "
                             "capture: capture them (plans first when there is no plan); intrinsics, handeye: "
                             "calibrate from the board frames; all: every step and the report; folder: calibrate "
                             "from a folder of images and robot pose files made elsewhere (PATH is the image folder)")
    parser.add_argument("scene_dir", type=Path, metavar="PATH",
                        help="scene directory (made by 'brave6d init'); for 'folder': the folder of board images")
    parser.add_argument("--robot", default="sim", help="'sim' or 'ur:HOST' (a UR arm reachable over RTDE)")
    parser.add_argument("--camera", default="sim", help="'sim' or 'oak' (a Luxonis OAK over USB)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted board capture (or reuse a "
                        "complete one) and recalibrate")
    parser.add_argument("--force", action="store_true", help="move an existing board capture aside, plan and "
                        "capture again")
    parser.add_argument("--factory-intrinsics", action="store_true",
                        help="keep the camera's own intrinsics (capture camera.json); only measure their error")
    parser.add_argument("--distortion", default="auto", metavar="MODEL",
                        help="lens distortion model: auto (k1 k2 k3, with p1 p2 only when the data show them; "
                             "default), radial, 0, 4, 5, 8, 12 or 14 (OpenCV coefficient counts)")
    parser.add_argument("--views", type=int, default=None,
                        help="board views to plan (default: 30)")
    parser.add_argument("--max-sigma-mm", type=float_in(0.0, low_open=True), default=DEFAULT_MAX_SIGMA_MM,
                        metavar="MM", help="refuse a hand-eye result whose 1-sigma translation (norm) exceeds this "
                                           f"(default {DEFAULT_MAX_SIGMA_MM:g})")
    parser.add_argument("--max-sigma-deg", type=float_in(0.0, low_open=True), default=DEFAULT_MAX_SIGMA_DEG,
                        metavar="DEG", help="refuse a hand-eye result whose 1-sigma rotation (norm) exceeds this "
                                            f"(default {DEFAULT_MAX_SIGMA_DEG:g})")
    robot = parser.add_argument_group(
        "robot accuracy", "the refinement's model of the robot's pose error (per axis, 1-sigma)")
    robot.add_argument("--robot-sigma-mm", type=float_in(0.0, low_open=True), default=DEFAULT_ROBOT_SIGMA_MM,
                       metavar="MM", help="the robot's position error per axis, the starting value of the estimate "
                                          f"(default {DEFAULT_ROBOT_SIGMA_MM:g}: a UR arm's repeatability)")
    robot.add_argument("--robot-sigma-deg", type=float_in(0.0, low_open=True), default=DEFAULT_ROBOT_SIGMA_DEG,
                       metavar="DEG", help=f"the robot's rotation error per axis (default {DEFAULT_ROBOT_SIGMA_DEG:g})")
    robot.add_argument("--fixed-robot-noise", action="store_true",
                       help="keep --robot-sigma-mm/--robot-sigma-deg as given instead of re-estimating them from "
                            "the refinement's corrections (when the robot's accuracy is known, e.g. from its datasheet)")
    _configure_folder(parser.add_argument_group(
        "calibrate folder", "images of a ChArUco board plus one robot pose (base_T_tcp) per image, from files"))


def _configure_folder(group: argparse._ArgumentGroup) -> None:
    from brave6d.core.spec import BoardSpec

    board = {name: f.default for name, f in BoardSpec.model_fields.items()}  # no instance: --help loads no OpenCV
    group.add_argument("--poses", type=Path, default=None, metavar="PATH",
                       help="robot poses: a folder with one pose file per image, or one file with every pose "
                            "(.txt/.csv/.npy/.json/.yaml): 4x4 matrices, x y z + quaternion, or UR pose vectors")
    group.add_argument("--out", type=Path, default=None, metavar="DIR",
                       help="where to write intrinsics.json, handeye.json and report.md (default: PATH/calibration)")
    group.add_argument("--eye-to-hand", action="store_true",
                       help="static camera, board on the tool: the result is base_T_cam (default: eye-in-hand, the "
                            "camera on the tool, tcp_T_cam)")
    group.add_argument("--match", choices=("auto", "stem", "order"), default=None,
                       help="pair images and poses by file stem (image 0.png <- pose 0) or by sorted order (natural "
                            "order: 2 before 10); auto (default): stem for a folder of pose files or named poses, "
                            "order for a file that lists them")
    group.add_argument("--pose-format", choices=("auto", "matrix", "quaternion", "ur"), default=None,
                       help="auto (default) recognises 4x4 matrices and named quaternions (x y z qx qy qz qw, "
                            "position/orientation); ur: UR pose vectors [x, y, z, rx, ry, rz] (rotation vector, rad)")
    group.add_argument("--quaternion-order", choices=("xyzw", "wxyz"), default=None,
                       help="order of a quaternion given as bare numbers (x y z then 4 numbers): xyzw (ROS, scipy) or "
                            "wxyz (w first); named keys need none")
    group.add_argument("--pose-unit", choices=("m", "mm"), default=None, help="unit of the translations (default m)")
    group.add_argument("--squares-x", type=int_in(3, 50), default=None, metavar="N",
                       help=f"ChArUco squares along x (columns; default {board['squares_x']})")
    group.add_argument("--squares-y", type=int_in(3, 50), default=None, metavar="N",
                       help=f"ChArUco squares along y (rows; default {board['squares_y']})")
    group.add_argument("--square-mm", type=float_in(0.0, 2000.0, low_open=True), default=None, metavar="MM",
                       help=f"square side (default {board['square_length_m'] * 1000:g})")
    group.add_argument("--marker-mm", type=float_in(0.0, 2000.0, low_open=True), default=None, metavar="MM",
                       help=f"ArUco marker side (default {board['marker_length_m'] * 1000:g})")
    group.add_argument("--dictionary", default=None, metavar="NAME",
                       help=f"ArUco dictionary: a predefined OpenCV name (default {board['dictionary']}) or "
                            "custom:MARKERSxBITS:SEED, generated as OpenCV's extendDictionary(MARKERS, BITS, "
                            "randomSeed=SEED) and older OpenCV's Dictionary_create(MARKERS, BITS, SEED) make it "
                            "(e.g. custom:17x5:42)")
    group.add_argument("--dictionary-file", type=Path, default=None, metavar="FILE",
                       help="ArUco dictionary from a file in OpenCV's format (written by "
                            "cv2.aruco.Dictionary.writeDictionary: nmarkers, markersize, marker_0 ...); "
                            "instead of --dictionary")
    group.add_argument("--legacy-pattern", action="store_true",
                       help="a board printed before OpenCV 4.6 with an even number of rows")
    group.add_argument("--intrinsics", type=Path, default=None, metavar="FILE",
                       help="use these intrinsics (a JSON file with a 'camera' field, as intrinsics.json) instead of "
                            "calibrating them from the images; held fixed")
    group.add_argument("--refine-intrinsics", action=argparse.BooleanOptionalAction, default=None,
                       help="refine the intrinsics jointly with the hand-eye transform (default: yes when they are "
                            "calibrated from these images, no with --intrinsics)")


def _check_args(args: argparse.Namespace) -> None:
    from brave6d.calibration.intrinsics import DISTORTION_MODELS

    if args.resume and args.force:
        raise BraveError("--resume and --force exclude each other: resume keeps the board capture, "
                         "force moves it aside")
    if args.distortion != "auto" and args.distortion not in DISTORTION_MODELS:
        raise BraveError(f"--distortion {args.distortion}: unknown model; choose from auto, "
                         f"{', '.join(DISTORTION_MODELS)}")
    if args.views is not None and args.views < 3:
        raise BraveError(f"--views {args.views}: hand-eye calibration needs at least 3 views (30 recommended)")
    if args.action != "folder":
        given = [f"--{n.replace('_', '-')}" for n in FOLDER_ONLY if getattr(args, n) is not None]
        given += [flag for flag, on in (("--eye-to-hand", args.eye_to_hand), ("--legacy-pattern", args.legacy_pattern))
                  if on]
        if given:
            raise BraveError(f"{', '.join(given)}: options of 'brave6d calibrate folder' only (the scene's board is "
                             "in scene.yaml, its robot poses in its capture)")
    else:
        scene_only = [flag for flag, on in (("--robot", args.robot != "sim"), ("--camera", args.camera != "sim"),
                                            ("--resume", args.resume), ("--force", args.force),
                                            ("--factory-intrinsics", args.factory_intrinsics),
                                            ("--views", args.views is not None)) if on]
        if scene_only:
            raise BraveError(f"{', '.join(scene_only)}: options of the scene actions, not of 'calibrate folder'")
        if args.poses is None:
            raise BraveError("calibrate folder: --poses PATH is required (a folder of pose files or one file)")


def _handeye_options(args: argparse.Namespace):  # noqa: ANN202 - HandEyeOptions, imported when a command runs
    from brave6d.calibration.handeye import HandEyeOptions

    return HandEyeOptions(max_sigma_mm=args.max_sigma_mm, max_sigma_deg=args.max_sigma_deg,
                          robot_sigma_mm=args.robot_sigma_mm, robot_sigma_deg=args.robot_sigma_deg,
                          estimate_robot_noise=not args.fixed_robot_noise)


def _dictionary_fields(args: argparse.Namespace) -> dict[str, object]:
    """BoardSpec's dictionary fields from --dictionary / --dictionary-file (a file made absolute;
    both given is the board's own one-line error)."""
    fields: dict[str, object] = {}
    if args.dictionary is not None:
        fields["dictionary"] = args.dictionary
    if args.dictionary_file is not None:
        fields["dictionary_file"] = args.dictionary_file.absolute()
    return fields


def _board(args: argparse.Namespace):  # noqa: ANN202 - BoardSpec
    from pydantic import ValidationError

    from brave6d.core.spec import BoardSpec

    defaults = BoardSpec()
    try:
        return BoardSpec(
            squares_x=args.squares_x or defaults.squares_x, squares_y=args.squares_y or defaults.squares_y,
            square_length_m=(args.square_mm / 1000.0) if args.square_mm else defaults.square_length_m,
            marker_length_m=(args.marker_mm / 1000.0) if args.marker_mm else defaults.marker_length_m,
            legacy_pattern=args.legacy_pattern, **_dictionary_fields(args))
    except ValidationError as exc:
        problems = "; ".join(e["msg"].removeprefix("Value error, ") for e in exc.errors())
        raise BraveError(f"calibrate folder: board options: {problems}") from None


def run_folder(args: argparse.Namespace) -> int:
    """``brave6d calibrate folder``: pair, calibrate, write, print a summary."""
    from brave6d.core.calibration_io import read_camera_json
    from brave6d.calibration.folder import calibrate_folder, folder_summary_lines, write_folder_results
    from brave6d.calibration.pairing import pair_images_with_poses
    from brave6d.calibration.pose_files import PoseFormat

    fmt = PoseFormat(args.pose_format or "auto", args.quaternion_order, args.pose_unit or "m")
    inputs = pair_images_with_poses(args.scene_dir, args.poses, fmt, args.match or "auto")
    print(inputs.description)
    camera = read_camera_json(args.intrinsics, "camera") if args.intrinsics is not None else None
    run = calibrate_folder(inputs, _board(args), eye_to_hand=args.eye_to_hand, camera=camera,
                           distortion=args.distortion, refine_intrinsics=args.refine_intrinsics,
                           options=_handeye_options(args))
    files = write_folder_results(args.out or args.scene_dir / "calibration", run)
    print("\n".join(folder_summary_lines(run)[1:]))
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0


def run(args: argparse.Namespace) -> int:
    from brave6d.calibration.board import export_board
    from brave6d.calibration.board_capture import DEFAULT_VIEWS, capture_board, plan_only
    from brave6d.calibration.pipeline import calibrate_scene, summary_lines

    _check_args(args)
    if args.action == "folder":
        return run_folder(args)
    ctx = RunContext.for_scene(args.scene_dir, rig=Rig(args.robot, args.camera))  # as the pipeline's calibrate stage
    scene, spec, rig = ctx.scene, ctx.spec, ctx.rig
    layout = scene.board_capture
    views = args.views or DEFAULT_VIEWS
    if args.action in ("plan", "all"):
        printable = export_board(spec.board, scene.board_pdf_path)
        print(f"printable board at true scale (print at 100 %): {printable}")
    if args.action == "plan":
        plan = plan_only(layout, spec, rig.robot, rig.camera, views)
        print(f"planned {len(plan.views)} board views at {plan.distance_m:.2f} m "
              f"({len(plan.dropped)} candidates left out); wrote {layout.plan_path}")
        return 0
    if args.action in ("capture", "all"):
        cap = capture_board(layout, spec, rig.robot, rig.camera, views, resume=args.resume, force=args.force)
        print(f"board capture: {cap.written} frames captured now, {cap.total} in all "
              f"({cap.robot_seconds:.1f} s robot time) in {layout.root}")
    if args.action in ("intrinsics", "handeye", "all"):
        result = calibrate_scene(scene, spec, intrinsics=args.action != "handeye",
                                 handeye=args.action != "intrinsics", factory_intrinsics=args.factory_intrinsics,
                                 distortion=args.distortion, options=_handeye_options(args))
        print("\n".join(summary_lines(result)))
    return 0

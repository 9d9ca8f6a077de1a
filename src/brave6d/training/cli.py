"""``brave6d train SCENE_DIR``: train a 3DGS splat from a captured, calibrated scene.

Registered in ``brave6d/cli.py`` as ``Command("train", "brave6d.training.cli", ...)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from brave6d.core.layout import SceneDir
from brave6d.core.progress import format_table
from brave6d.core.run_context import DEVICES
from brave6d.training.run_outcome import budget_stop_line, steps_text


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene_dir", type=Path, help="scene directory with capture/ and calibration/")
    parser.add_argument("--preset", choices=["fast", "default", "quality"], default="default",
                        help="fast: CPU demo (half resolution, minutes); default: Inria-like 30k steps; "
                             "quality: longer, full resolution (default: %(default)s)")
    parser.add_argument("--device", choices=DEVICES, default="auto",
                        help="where to train: auto picks CUDA when available (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=None,
                        help="number of steps; the preset's step schedules (SH, densification, "
                             "checkpoints) are scaled with it")
    parser.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                        help="stop training once the command has run this many seconds, loading and the initial "
                             "points (COLMAP) included; a --resume run gets it again (default: the preset's: fast 840)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the newest checkpoint in splat/checkpoints; without it a new training "
                             "starts, and the previous one's outputs are moved aside (splat/<name>.old-<stamp>) "
                             "once the new one has written its first checkpoint")
    parser.add_argument("--skip-bad-frames", action="store_true",
                        help="leave out missing or corrupt frames (listed in metrics.json) instead of stopping")
    parser.add_argument("--init", choices=["auto", "imported", "colmap", "depth", "random"], default="auto",
                        help="initial points: auto = COLMAP (training views), else an imported capture's sparse "
                             "points, else depth frames, else random; imported = the imported points first (the "
                             "source made them from all its images, holdout included) (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's, 0)")
    parser.add_argument("--skip-pose-check", action="store_true",
                        help="train even when cameras do not see the scene (the check names them; not recommended)")


def run(args: argparse.Namespace) -> int:
    from brave6d.training.demo import run_preset
    from brave6d.training.pipeline import require_capture, train_scene

    # no RunContext: training reads capture/ and calibration/ only, and a scene directory without a
    # scene.yaml (a capture made elsewhere) trains too; the preset is resolved as the pipeline's stage does
    scene = SceneDir(args.scene_dir)
    require_capture(scene)
    preset = run_preset(args.preset)
    if args.steps is not None:
        preset = preset.with_steps(args.steps)
    preset = preset.with_overrides(seed=args.seed)
    if args.time_budget is not None:
        preset = preset.with_overrides(time_budget_s=args.time_budget)
    metrics = train_scene(scene, preset, device=args.device, resume=args.resume,
                          skip_bad_frames=args.skip_bad_frames, init_method=args.init,
                          check_poses=not args.skip_pose_check)
    print(summary(metrics))
    line = budget_stop_line(metrics, args.scene_dir, args.preset, args.steps)
    if line:
        print(line)
    print(f"\nsplat: {metrics['outputs']['ply']}\nmetrics: {scene.metrics_path}")
    previous = metrics["outputs"].get("previous_training") or []
    if previous:
        print("previous training kept as: " + ", ".join(previous))
    return 0


def summary(metrics: dict) -> str:
    """The run's line, the pose check's result and the holdout table (overall and per distance level)."""
    hold = metrics["holdout"]
    rows = [(f"level {lvl} ({m['distance_m']:.2f} m)", m["n_views"], f"{m['psnr']:.2f}", f"{m['ssim']:.4f}")
            for lvl, m in hold["per_level"].items()]
    rows.append(("all", hold["n_views"], f"{hold['psnr']:.2f}", f"{hold['ssim']:.4f}"))
    # a resumed run's training time and CPU time count from step 0; the command's own times are this run's
    resumed = metrics.get("resumed_from_step")
    since = f", from step 0: this command resumed at step {resumed}" if resumed else ""
    head = (f"preset {metrics['preset']} on {metrics['device']}: {steps_text(metrics)} in "
            f"{metrics['train_time_s']:.0f} s of training ({metrics['train_cpu_s']:.0f} CPU-s{since}); this command "
            f"{metrics['total_time_s']:.0f} s in all, {metrics['init_time_s']:.0f} s of it loading and initial points; "
            f"{metrics['num_gaussians']} Gaussians, {metrics['images']['metrics_resolution']} images")
    if metrics.get("pose_check"):
        head += "\n" + metrics["pose_check"]
    return head + "\n" + format_table(["holdout", "views", "PSNR [dB]", "SSIM"], rows)

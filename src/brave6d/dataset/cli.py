"""``brave6d dataset run DATASET.yaml WORKDIR``, ``brave6d dataset status WORKDIR`` and
``brave6d dataset report WORKDIR``."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from brave6d.core.errors import BraveError
from brave6d.core.run_context import DEVICES


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    run_p = sub.add_parser("run", help="run every stage of every scene (resumable; finished stages are not redone)",
                           description="Init, calibrate, capture, annotate, train and export every scene of a "
                           "dataset, one submitit job per scene. A captured scene ('dir:' in DATASET.yaml) is "
                           "trained and exported where it lies; its calibration, capture and annotation must be "
                           "there (a scene that misses one is named, with what it misses, and the others go on). "
                           "Once per run (not per scene) the dataset's object library gets its learned model: a "
                           "synthetic train_pbr of the library and the learned estimator trained on it, in "
                           "WORKDIR/learned/ (release build ships it). Slurm options, the training preset and the "
                           "learn options default to the dataset's 'cluster' block; a flag overrides it.")
    run_p.add_argument("dataset", type=Path, metavar="DATASET.yaml")
    run_p.add_argument("workdir", type=Path, metavar="WORKDIR")
    run_p.add_argument("--quick", action="store_true", help="miniature run (few views and steps), what CI runs")
    run_p.add_argument("--device", choices=DEVICES, default="auto")
    run_p.add_argument("--preset", metavar="NAME",
                       help="training preset of every scene: fast, default or quality (default: cluster.preset, "
                            "else fast, the CPU demo's; a GPU cluster wants default)")
    run_p.add_argument("--learn-preset", metavar="NAME",
                       help="learn preset of the dataset's learned model: fast, paper or tiny (default: "
                            "cluster.learn_preset, else fast; --quick: tiny)")
    run_p.add_argument("--learn-images", type=int, metavar="N",
                       help="train_pbr images rendered for it (default: cluster.learn_images, else 300; --quick: 24)")
    run_p.add_argument("--no-learn", action="store_true",
                       help="train no learned model (default: cluster.learn, else one per dataset)")
    run_p.add_argument("--executor", choices=["local", "slurm"], default=None,
                       help="local: child processes on this machine; slurm: one job array (default: cluster.executor)")
    run_p.add_argument("--scenes", nargs="+", metavar="NAME", help="run only these scenes")
    run_p.add_argument("--mesh-dir", type=Path, action="append", default=[], metavar="DIR",
                       help="also accept meshes (and scene specs) of DATASET.yaml that lie under DIR (repeatable); "
                            "by default every file it names must lie in its own folder")
    run_p.add_argument("--scene-dir", type=Path, action="append", default=[], metavar="DIR",
                       help="also accept captured scene directories of DATASET.yaml ('dir:') that lie under DIR "
                            "(repeatable); they are trained and exported into where they lie, so by default "
                            "each must lie in the dataset's folder")
    slurm = run_p.add_argument_group("Slurm (defaults: the dataset's cluster block)")
    slurm.add_argument("--partition")
    slurm.add_argument("--time-min", type=int, help="time limit per scene job, minutes (also the local limit)")
    slurm.add_argument("--gpus-per-task", type=int)
    slurm.add_argument("--cpus-per-task", type=int)
    slurm.add_argument("--mem-gb", type=float)
    slurm.add_argument("--array-parallelism", type=int,
                       help="scene jobs running at once (local: default 1 unless the cluster block says otherwise)")
    slurm.add_argument("--account")
    slurm.add_argument("--qos")
    status_p = sub.add_parser("status", help="print the scene x stage table of a work directory")
    status_p.add_argument("workdir", type=Path, metavar="WORKDIR")
    report_p = sub.add_parser("report", help="the accuracy-vs-time report of every scene, with a cross-scene index",
                              description="Run 'brave6d report' on every scene of WORKDIR into "
                              "WORKDIR/report/<scene>/ (resumable: cached measurements are reused) and write "
                              "WORKDIR/report/README.md, linking them with one cross-scene table.")
    report_p.add_argument("workdir", type=Path, metavar="WORKDIR")
    report_p.add_argument("--mode", choices=["quick", "full"], default="full",
                          help="sweep sizes: quick (CI's miniature) or full (default: %(default)s)")
    report_p.add_argument("--only", nargs="+", metavar="SECTION",
                          help="measure only these sections; the others come from each scene's cache")
    report_p.add_argument("--refresh", action="store_true", help="measure again instead of reusing the caches")
    report_p.add_argument("--device", choices=DEVICES, default="auto")


def run(args: argparse.Namespace) -> int:
    if args.action == "status":
        return _status(args.workdir)
    if args.action == "report":
        return _report(args)
    from brave6d.core.dataset_spec import load_dataset_spec
    from brave6d.core.extras import require

    require("submitit", "cluster", "brave6d dataset run")  # the executor of the scene jobs, local or Slurm
    from brave6d.dataset.executor import ExecutorOptions
    from brave6d.dataset.learn import learn_options
    from brave6d.dataset.runner import run_dataset

    cluster = load_dataset_spec(args.dataset, args.mesh_dir, args.scene_dir).spec.cluster
    learn = learn_options(cluster, args.quick, skip=args.no_learn, preset=args.learn_preset, images=args.learn_images)
    options = ExecutorOptions.from_cluster(
        cluster, executor=args.executor, partition=args.partition, time_min=args.time_min,
        gpus_per_task=args.gpus_per_task, cpus_per_task=args.cpus_per_task, mem_gb=args.mem_gb,
        array_parallelism=args.array_parallelism, account=args.account, qos=args.qos)
    if options.executor == "local" and args.array_parallelism is None:
        options = dataclasses.replace(options, array_parallelism=1)  # one scene at a time on this machine
    summary = run_dataset(args.dataset, args.workdir, quick=args.quick, device=args.device, options=options,
                          scenes=args.scenes, mesh_dirs=args.mesh_dir, scene_dirs=args.scene_dir, preset=args.preset,
                          learn=learn or False)
    print()
    print(summary.table)
    print(f"\n{len(summary.ran)} scene job(s) ran in {summary.seconds:.1f} s (training preset: "
          f"{summary.preset or 'the default, fast'}{', quick' if args.quick else ''}); work directory: {args.workdir}")
    for scene, (stage, error) in summary.failed.items():
        print(f"FAILED {scene} at {stage}: {error}")
    for scene, (stage, error) in summary.missing.items():
        print(f"NOT READY {scene} ({stage}): {error}")
    for scene, holder in summary.busy.items():
        print(f"NOT STARTED {scene}: its job still runs on {holder}; run again once it has ended")
    learn_failed = summary.learn is not None and not summary.learned.startswith("done")
    if summary.learn is not None:
        print(f"{'FAILED ' if learn_failed else ''}learned model ({summary.learn.preset}, {summary.learn.images} "
              f"train_pbr images; {args.workdir / 'learned' / 'model'}): {summary.learned}")
    return 1 if summary.failed or summary.missing or summary.busy or learn_failed else 0


def _status(workdir: Path) -> int:
    from brave6d.dataset.status import status_table, write_summary
    from brave6d.dataset.workdir import WORKDIR_DATASET, load_workdir_dataset

    path = workdir / WORKDIR_DATASET
    if not path.is_file():
        raise BraveError(f"{path}: not found; is {workdir} a work directory of 'brave6d dataset run'?")
    dataset = load_workdir_dataset(workdir)
    ids = [(s.scene_id, s.name) for s in dataset.scenes]
    write_summary(workdir, dataset.spec.name, ids)
    print(f"dataset {dataset.spec.name} {dataset.spec.version}: {workdir}")
    print(status_table(workdir, ids))
    return 0


def _report(args: argparse.Namespace) -> int:
    from brave6d.core.runtime import quiet_openmp

    quiet_openmp()  # before torch / numba load: spinning OpenMP threads distort the timings
    from brave6d.dataset.report import report_dataset

    done = report_dataset(args.workdir, quick=args.mode == "quick", only=tuple(args.only or ()),
                          refresh=args.refresh, device=args.device)
    for s in done.scenes:
        print(f"{s.scene:<24} " + (", ".join(f"{k} {v}" for k, v in s.statuses.items()) or s.note))
    print(f"\nindex: {done.index}")
    return 0

"""What the learned baseline's accuracy costs: held-out AR and the learned agents' AR against the
number of train_pbr images (and the synth time to render them) and the training steps (time).

    python benchmarks/learned_cost.py SPEC MODELS OUT [--bundle BUNDLE] [--points 100:500,300:1000]
        [--episodes-per-object 3] [--device cpu]

Renders (or completes) a train_pbr of SPEC's objects with as many images as the largest point
asks for (``OUT/synth``, resumable; its measured images/s prices every point's synth time), then
for each ``images:steps`` point trains the fast preset with that many steps per network on the
first ``images`` images (``OUT/model-<images>-<steps>``, reused when unchanged), scores it on the
held-out images and, with ``--bundle``, plays the four learned agents on it. Prints one row per
point and writes ``OUT/learned_cost.json`` and ``OUT/learned_cost.png`` (AR against training time).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("spec", type=Path, help="scene or dataset spec whose objects the split shows")
    parser.add_argument("models", type=Path, help="BOP models folder of those objects")
    parser.add_argument("out", type=Path)
    parser.add_argument("--bundle", type=Path, default=None, help="a bundle to play the learned agents on")
    parser.add_argument("--points", default="100:500,300:500,300:1000", help="images:steps,...")
    parser.add_argument("--episodes-per-object", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)

    from brave6d.evaluation.demo import learned_agent_scores
    from brave6d.evaluation.learned import LearnedEstimator, get_learn_preset, resolve_precision, score_heldout, \
        train_learned, training_seconds
    from brave6d.synth import SynthOptions, synthesize

    points = [tuple(int(x) for x in p.split(":")) for p in args.points.split(",")]
    fast = resolve_precision(get_learn_preset("fast"), args.device)  # each point at the steps it names
    total = max(n for n, _ in points)
    synth = synthesize(args.spec, args.out / "synth", SynthOptions(images=total, seed=0, workers=args.workers))
    rate = synth.images_per_s
    if rate == 0:
        rate = json.loads((args.out / "learned_cost.json").read_text()).get("synth_images_per_s", 0) \
            if (args.out / "learned_cost.json").is_file() else 0
    rows = []
    for images, steps in points:
        preset = fast.with_overrides(detector_steps=steps, pose_steps=steps)
        out = args.out / f"model-{images}-{steps}"
        t0 = time.perf_counter()
        result = train_learned(args.out / "synth", args.models, out, preset, args.device, show_progress=False,
                               max_images=images)
        wall = time.perf_counter() - t0
        assert result.model is not None and result.data is not None
        estimator = LearnedEstimator.load(out, models_dir=args.models)
        held = score_heldout(estimator, result.data, args.models, show_progress=False)
        summary = held.detection_summary()
        row = {"images": images, "steps": steps, "synth_s": images / rate if rate else None,
               "train_s": training_seconds(result.seconds) if result.trained
               else None, "wall_s": wall, "heldout_images": held.images,
               "heldout_ar": held.pose_ar, "recall_min": summary["recall_min"], "recall": summary["recall"]}
        if args.bundle is not None:
            row["agents"] = learned_agent_scores(args.bundle, out, args.out / f"episodes-{images}-{steps}",
                                                 args.episodes_per_object, args.device)
        rows.append(row)
        print(json.dumps(row), flush=True)
    report = {"synth_images_per_s": rate, "workers": args.workers, "points": rows}
    (args.out / "learned_cost.json").write_text(json.dumps(report, indent=2))
    _plot(rows, args.out / "learned_cost.png")
    _table(rows)
    return 0


def _table(rows: list[dict]) -> None:
    head = "| images | steps | synth s | train s | held-out AR true box (RGB / + depth) | detected (RGB / + depth) | recall min |"
    print(head + (" learned static / active (+ depth) |" if rows and "agents" in rows[0] else ""))
    for r in rows:
        a = r["heldout_ar"]
        line = (f"| {r['images']} | {r['steps']} | {r['synth_s'] or 0:.0f} | {r['train_s'] or 0:.0f} | "
                f"{a['true_box_rgb']:.3f} / {a['true_box_depth']:.3f} | {a['detected_rgb']:.3f} / "
                f"{a['detected_depth']:.3f} | {r['recall_min']:.2f} |")
        if "agents" in r:
            g = r["agents"]
            line += (f" {g['learned-static']:.3f} / {g['learned-active']:.3f} ({g['learned-static-depth']:.3f} / "
                     f"{g['learned-active-depth']:.3f}) |")
        print(line)


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for key, label in (("true_box_rgb", "true box, RGB"), ("true_box_depth", "true box, + depth"),
                       ("detected_depth", "detected, + depth")):
        ax.plot([(r["train_s"] or 0) + (r["synth_s"] or 0) for r in rows], [r["heldout_ar"][key] for r in rows],
                "o-", label=label)
    for r in rows:
        ax.annotate(f"{r['images']} img, {r['steps']} st", ((r["train_s"] or 0) + (r["synth_s"] or 0),
                                                           r["heldout_ar"]["true_box_depth"]), fontsize=7)
    ax.set_xlabel("synth + training time (s)")
    ax.set_ylabel("held-out BOP AR")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())

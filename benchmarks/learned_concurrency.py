"""The learned estimator's two networks trained one after the other on every thread against at once,
one phase per thread on half the threads (what ``train_learned`` does on a CPU): the same batches,
interleaved repeats, median seconds and the ratio.

Each repeat runs ``--steps`` detector steps and ``--steps`` coordinate-net steps of the ``fast``
preset's sizes from fresh networks, both ways in turn (one after the other, at once, ...).

    python benchmarks/learned_concurrency.py TRAIN_PBR MODELS_DIR [--steps 60] [--repeats 2] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any


def _loops(data: Any, steps: int) -> dict[str, Any]:
    """One function per phase that trains ``steps`` steps of a fresh network on its own seeded batches."""
    import numpy as np
    import torch

    from brave6d.evaluation.learned import get_learn_preset
    from brave6d.evaluation.learned.networks import CoordinateNet, Detector
    from brave6d.evaluation.learned.training import phase_loss

    p = get_learn_preset("fast")
    classes = len(data.objects)
    nets = {"detector": lambda: Detector(classes, p.detector_width), "pose": lambda: CoordinateNet(classes, p.pose_width)}
    pools = {"detector": data.split(False), "pose": data.instances_of(False)}
    rates = {"detector": p.detector_lr, "pose": p.pose_lr}

    def loop(phase: str, seed: int) -> None:
        net, rng = nets[phase](), np.random.default_rng(seed)
        opt = torch.optim.AdamW(net.parameters(), rates[phase])
        for _ in range(steps):
            loss = phase_loss(phase, net, data, pools[phase], rng, p, "cpu")
            opt.zero_grad()
            loss.backward()
            opt.step()

    return {"detector": lambda: loop("detector", 0), "pose": lambda: loop("pose", 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("train_pbr", type=Path)
    parser.add_argument("models", type=Path)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    import torch

    from brave6d.evaluation.learned import get_learn_preset, load_training_data

    p = get_learn_preset("fast")
    data = load_training_data(args.train_pbr, args.models, p.work_width, p.heldout_every,
                              crop_width=p.crop_source_width)
    loops = _loops(data, args.steps)
    threads = torch.get_num_threads()
    times: dict[str, list[float]] = {"one after the other": [], "at once": []}
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        loops["detector"]()
        loops["pose"]()
        times["one after the other"].append(time.perf_counter() - t0)
        torch.set_num_threads(max(1, threads // 2))
        try:
            t0 = time.perf_counter()
            workers = [threading.Thread(target=f) for f in loops.values()]
            for w in workers:
                w.start()
            for w in workers:
                w.join()
            times["at once"].append(time.perf_counter() - t0)
        finally:
            torch.set_num_threads(threads)
    result = {"steps_per_network": args.steps, "threads": threads,
              "median_s": {k: statistics.median(v) for k, v in times.items()}, "all_s": times}
    result["speedup"] = result["median_s"]["one after the other"] / result["median_s"]["at once"]
    print(json.dumps(result, indent=1))
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

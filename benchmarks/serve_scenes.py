"""Scene switching of a multi-scene server: how long a reset on another scene takes, and what memory
the loaded scenes hold against the catalog's estimate.

Serves a release (``--release``: a release folder or an unzipped one) or several bundle folders
(``--bundles A B ...``, served as scenes named after their folders' parents) through
``brave6d.serve.open_scenes`` / ``brave6d.serve.SceneCatalog`` and the real ``EpisodeManager`` on the CPU, and measures:

* **first use**: the first reset on each scene (a release: its bundle zip is checked and unpacked
  into a fresh cache; then the bundle is verified, the splat and the visibility structures loaded),
  after the process's one-time costs (torch, Open3D, the CPU kernels) were paid on a small
  synthetic scene (reported apart);
* **cold switch**: with ``max_loaded=1``, a reset on the next scene (evict + load from the cache),
  cycling ``--rounds`` times over the scenes;
* **warm switch**: with every scene loaded, a reset on the next scene (no load);
* **memory**: the process's resident memory (VmRSS) after each load against the catalog's
  estimate, and the peak RSS while cycling with ``max_loaded=1`` (the bound) and with every scene
  loaded.

Prints a table of medians (and p90) and writes ``--json``. The cold/warm switch times are what an
agent sees when it moves between the scenes of a release.

    python benchmarks/serve_scenes.py --release RELEASE [--rounds 3] [--json out.json]
    python benchmarks/serve_scenes.py --bundles runs/a/scene/bundle runs/b/scene/bundle
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def rss_mb() -> float:
    """Resident memory of this process (MB) from /proc (Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def catalog_for(args: argparse.Namespace, cache: Path, max_loaded: int | None) -> Any:
    from brave6d.commands.scenes import scene_sources
    from brave6d.serve import SceneCatalog, SceneSource, bundle_scene_source, open_scenes

    if args.release is not None:
        return open_scenes(scene_sources(args.release, cache), device="cpu", max_loaded=max_loaded)
    sources = []
    for i, folder in enumerate(args.bundles):
        s = bundle_scene_source(folder, i + 1)
        sources.append(SceneSource(f"{Path(folder).resolve().parent.parent.name}_{i + 1}", i + 1, s.objects,
                                   s.memory_bytes, s.locate, s.origin))
    return SceneCatalog(sources, device="cpu", max_loaded=max_loaded)


def warm_up_process(folder: Path) -> float:
    """Pay the once-per-process costs (torch, Open3D, the compiled CPU kernels) on a small
    synthetic scene, so that the first use of each real scene measures the scene alone."""
    from brave6d.serve import EpisodeManager, SceneCatalog, bundle_scene_source, make_synthetic_bundle

    t0 = time.perf_counter()
    catalog = SceneCatalog([bundle_scene_source(make_synthetic_bundle(folder, n_gaussians=2000))], device="cpu")
    manager = EpisodeManager(catalog, None)
    manager.close(manager.reset(seed=0, width=64, height=48).episode_id)
    return time.perf_counter() - t0


def timed_reset(manager: Any, scene: str, size: tuple[int, int]) -> float:
    t0 = time.perf_counter()
    r = manager.reset(scene=scene, seed=0, width=size[0], height=size[1])
    dt = time.perf_counter() - t0
    manager.close(r.episode_id)
    return dt


def stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "n": int(a.size)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--release", type=Path, help="a release folder (zips) or an unzipped release")
    what.add_argument("--bundles", type=Path, nargs="+", help="bundle folders served as the scenes of one server")
    parser.add_argument("--rounds", type=int, default=3, help="cycles over the scenes for the switch times")
    parser.add_argument("--size", default="320x240", help="observation size of each reset")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    from brave6d.core.runtime import prepare_process

    prepare_process()
    from brave6d.serve import EpisodeManager

    size = tuple(int(v) for v in args.size.split("x"))
    out: dict[str, Any] = {"source": str(args.release or [str(b) for b in args.bundles]), "size": args.size}
    with tempfile.TemporaryDirectory(prefix="brave6d-bench-cache-") as tmp:
        cache = Path(tmp)
        out["process_warm_up_s"] = warm_up_process(cache / "warm-up")
        # first use and the bound: one scene at a time
        catalog = catalog_for(args, cache, max_loaded=1)
        names = catalog.names()
        manager = EpisodeManager(catalog, None, max_episodes=4)
        base = rss_mb()
        first, loads = {}, []
        for name in names:
            before = rss_mb()
            first[name] = timed_reset(manager, name, size)
            loads.append({"scene": name, "estimate_mb": catalog.source(name).memory_bytes / 2**20,
                          "rss_before_mb": before, "rss_after_mb": rss_mb()})
        cold = []
        bound_peak = rss_mb()
        for _ in range(args.rounds):
            for name in names:
                cold.append(timed_reset(manager, name, size))
                gc.collect()
                bound_peak = max(bound_peak, rss_mb())
        out["first_use_s"] = first
        out["cold_switch_s"] = stats(cold)
        out["rss_one_scene_loaded_max_mb"] = bound_peak
        out["rss_start_mb"] = base
        out["loads"] = loads
        del manager, catalog
        gc.collect()
        # every scene loaded
        catalog = catalog_for(args, cache, max_loaded=None)
        manager = EpisodeManager(catalog, None, max_episodes=4)
        for name in names:
            timed_reset(manager, name, size)
        all_loaded = rss_mb()
        warm = []
        for _ in range(args.rounds):
            for name in names:
                warm.append(timed_reset(manager, name, size))
        out["warm_switch_s"] = stats(warm)
        out["rss_all_loaded_mb"] = all_loaded
        out["estimate_all_mb"] = catalog.loaded_bytes() / 2**20
        out["peak_rss_mb"] = peak_rss_mb()
        out["gaussians"] = {s.bundle.name: s.renderer.num_gaussians for s in catalog.loaded_scenes()}

    from brave6d.core.progress import format_table

    print(f"process warm-up (torch, Open3D, kernels; once per server): {out['process_warm_up_s']:.2f} s")
    rows = [[n, f"{first[n]:.2f}"] for n in names]
    print(format_table(["scene", "first use s (unpack + load)"], rows))
    print()
    print(format_table(["switch", "median s", "p90 s", "n"], [
        ["cold (evict + load, max_loaded=1)", f"{out['cold_switch_s']['median']:.3f}",
         f"{out['cold_switch_s']['p90']:.3f}", out["cold_switch_s"]["n"]],
        ["warm (scene loaded)", f"{out['warm_switch_s']['median']:.3f}", f"{out['warm_switch_s']['p90']:.3f}",
         out["warm_switch_s"]["n"]]]))
    print()
    print(format_table(["memory", "MB"], [
        ["RSS at start", f"{base:.0f}"],
        ["RSS max while cycling, max_loaded=1", f"{bound_peak:.0f}"],
        [f"RSS with all {len(names)} scenes loaded", f"{all_loaded:.0f}"],
        ["catalog estimate, all scenes", f"{out['estimate_all_mb']:.0f}"],
        ["per-scene RSS growth on first load (median)",
         f"{np.median([l['rss_after_mb'] - l['rss_before_mb'] for l in loads]):.0f}"],
        ["per-scene estimate (median)", f"{np.median([l['estimate_mb'] for l in loads]):.0f}"],
        ["peak RSS (VmHWM)", f"{out['peak_rss_mb']:.0f}"]]))
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

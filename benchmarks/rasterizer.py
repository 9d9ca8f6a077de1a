"""Rasterizer benchmark (issue 5): CPU kernel vs the pure-torch reference (and CUDA if present).

Prints median forward and forward+backward times for 20k Gaussians at 320x240 and 100k /
300k Gaussians at 640x480, the speed-up over the pure-torch reference on the 20k case, and
the one-time JIT cost (cold compile into an empty Numba cache, and the first call of a new
process that loads the on-disk cache).

    python benchmarks/rasterizer.py            # full run (a few minutes on 2 cores)
    python benchmarks/rasterizer.py --quick    # smoke run
    python benchmarks/rasterizer.py --json out.json

OpenMP threads that spin-wait after each parallel region (libgomp's default) steal the
cores from the other threads whenever the machine runs anything else; on a busy 2-core
machine that alone made the CPU kernel 3-10x slower.  The benchmark therefore sets
``OMP_WAIT_POLICY=PASSIVE`` before torch and numba start, unless the variable is already set
or ``--omp-default`` is given.  The policy changes how idle threads wait, not what they
compute; the same setting is recommended for CPU training on shared machines.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))

if "--omp-default" not in sys.argv:  # must happen before torch / numba load libgomp
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch

CASES = [  # (name, Gaussians, width, height)
    ("20k@320x240", 20_000, 320, 240),
    ("100k@640x480", 100_000, 640, 480),
    ("300k@640x480", 300_000, 640, 480),
]
REFERENCE_CASE = "20k@320x240"
TARGET_SPEEDUP = 30.0
TARGET_100K_FWD_BWD_S = 2.0


def make_scene(n: int, width: int, height: int, seed: int = 0, device: str = "cpu") -> dict:
    """Random but plausible scene: Gaussians spread over the view frustum 2-6 m in front of
    the camera, screen-space sigma 1-8 px (3.33 sigma radii of ~3-27 px), opacity 0.1-0.9."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width
    z = 2.0 + 4.0 * torch.rand(n, generator=g)
    u = torch.rand(n, generator=g) * width
    v = torch.rand(n, generator=g) * height
    means = torch.stack([(u - width / 2) / f * z, (v - height / 2) / f * z, z], dim=-1)
    sigma_px = torch.exp(torch.rand(n, 3, generator=g) * math.log(8.0))
    scene = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": sigma_px * z[:, None] / f,
        "opacities": 0.1 + 0.8 * torch.rand(n, generator=g),
        "colors": torch.rand(n, 3, generator=g),
        "viewmats": torch.eye(4)[None],
        "Ks": torch.tensor([[[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]]]),
        "backgrounds": torch.rand(1, 3, generator=g),
        "target": torch.rand(1, height, width, 3, generator=g),
    }
    return {k: t.to(device) for k, t in scene.items()}


def make_steps(render: Callable, scene: dict, width: int, height: int):
    """Forward-only and forward+backward closures (loss: L1 to a target + depth + alpha)."""
    names = ("means", "quats", "scales", "opacities", "colors")
    params = {k: scene[k].clone().requires_grad_(True) for k in names}

    def call():
        return render(*(params[k] for k in names), scene["viewmats"], scene["Ks"], width, height,
                      backgrounds=scene["backgrounds"])

    def forward():
        with torch.no_grad():
            call()

    def forward_backward():
        rgb, depth, alpha, _ = call()
        loss = (rgb - scene["target"]).abs().mean() + 0.01 * depth.mean() + alpha.mean()
        loss.backward()
        for p in params.values():
            p.grad = None

    return forward, forward_backward


def median_time(fn: Callable, repeats: int, sync: Callable = lambda: None) -> dict:
    fn()  # warm-up (JIT already paid, caches filled)
    sync()
    times: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(times), "min_s": min(times), "repeats": repeats}


def interleaved(kernel: Callable, reference: Callable, rounds: int) -> dict:
    """Alternate kernel and reference runs so that both see the same machine load.

    Each round times the reference once and the kernel three times (median); the result
    holds the medians over rounds and the median of the per-round ratios."""
    kernel()
    reference()
    t_kernel: list[float] = []
    t_ref: list[float] = []
    for _ in range(rounds):
        runs = []
        for _ in range(3):
            t0 = time.perf_counter()
            kernel()
            runs.append(time.perf_counter() - t0)
        t_kernel.append(statistics.median(runs))
        t0 = time.perf_counter()
        reference()
        t_ref.append(time.perf_counter() - t0)
    ratios = [r / k for r, k in zip(t_ref, t_kernel)]
    return {
        "kernel_median_s": statistics.median(t_kernel),
        "reference_median_s": statistics.median(t_ref),
        "ratio": statistics.median(ratios),
        "ratio_min": min(ratios),
        "ratio_max": max(ratios),
        "rounds": rounds,
    }


_JIT_PROBE = r"""
import time, torch
t0 = time.perf_counter()
from brave6d.training.rasterizer import rasterize
n = 64
g = torch.Generator().manual_seed(0)
p = [torch.randn(n, 3, generator=g) + torch.tensor([0.0, 0.0, 3.0]), torch.randn(n, 4, generator=g),
     0.1 * torch.rand(n, 3, generator=g), torch.rand(n, generator=g), torch.randn(n, 16, 3, generator=g)]
p = [t.requires_grad_(True) for t in p]
vm = torch.eye(4)[None]
K = torch.tensor([[[40.0, 0.0, 32.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]]])
for deg, colors in ((None, p[4][:, 0]), (3, p[4])):
    rgb, depth, alpha, info = rasterize(*p[:4], colors, vm, K, 64, 48, sh_degree=deg)
    (rgb.sum() + depth.sum() + alpha.sum()).backward()
print(time.perf_counter() - t0)
"""


def first_call_seconds(cache_dir: str | None) -> float:
    """Seconds for import + first forward/backward (RGB and SH) in a fresh process."""
    env = dict(os.environ)
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = cache_dir
    out = subprocess.run([sys.executable, "-c", _JIT_PROBE], cwd=REPO, env=env, check=True,
                         capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="few repeats, no cold-JIT probe")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats per case")
    parser.add_argument("--reference-repeats", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None, help="also write results here")
    parser.add_argument("--omp-default", action="store_true",
                        help="do not set OMP_WAIT_POLICY=PASSIVE (see the module docstring)")
    args = parser.parse_args(argv)
    repeats = args.repeats or (2 if args.quick else 7)
    ref_repeats = args.reference_repeats or (1 if args.quick else 5)

    import numba

    from brave6d.training.rasterizer import rasterize
    from brave6d.training.rasterizer.reference import rasterize_reference
    from brave6d.training.rasterizer.simd import REPORTED_FEATURES, target_cpu

    cpu = target_cpu()

    report: dict = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "numba_threads": numba.get_num_threads(),
            "numba_threading_layer": None,
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "numba": numba.__version__,
            "loadavg_start": os.getloadavg(),
            "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "(unset)"),
            "numba_target_cpu": cpu.name,
            "simd_features": sorted(cpu.features & set(REPORTED_FEATURES)),
            "float32_lanes_per_register": cpu.float32_lanes,
        },
        "jit": {},
        "cases": {},
    }

    print(f"== SIMD target (Numba) ==\n{cpu.summary()}\n"
          "the compositing row loops are 16 lanes wide: one register with AVX-512, two with AVX2",
          flush=True)
    print("\n== one-time JIT cost ==", flush=True)
    if not args.quick:
        with tempfile.TemporaryDirectory() as empty:
            cold = first_call_seconds(empty)
        report["jit"]["cold_compile_s"] = cold
        print(f"cold compile (empty Numba cache), import + first fwd/bwd: {cold:7.2f} s", flush=True)
    warm = first_call_seconds(None)
    report["jit"]["cached_first_call_s"] = warm
    print(f"new process with on-disk cache,   import + first fwd/bwd: {warm:7.2f} s", flush=True)

    backends = [("cpu", lambda *a, **k: rasterize(*a, backend="cpu", **k), "cpu")]
    if torch.cuda.is_available():
        backends.append(("cuda", lambda *a, **k: rasterize(*a, backend="cuda", **k), "cuda"))

    print("\n== timings (median of repeats, seconds) ==", flush=True)
    header = f"{'case':<14} {'backend':<10} {'forward':>9} {'fwd+bwd':>9}   {'fwd min':>8} {'f+b min':>8}"
    print(header)
    print("-" * len(header))
    for name, n, width, height in CASES:
        row = report["cases"].setdefault(name, {})
        runs = list(backends)
        if name == REFERENCE_CASE:
            runs.append(("reference", rasterize_reference, "cpu"))
        for backend, render, device in runs:
            scene = make_scene(n, width, height, device=device)
            fwd, fwd_bwd = make_steps(render, scene, width, height)
            sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
            reps = ref_repeats if backend == "reference" else repeats
            res = {"forward": median_time(fwd, reps, sync),
                   "forward_backward": median_time(fwd_bwd, reps, sync)}
            row[backend] = res
            print(f"{name:<14} {backend:<10} {res['forward']['median_s']:9.4f} "
                  f"{res['forward_backward']['median_s']:9.4f}   {res['forward']['min_s']:8.4f} "
                  f"{res['forward_backward']['min_s']:8.4f}", flush=True)
            del scene, fwd, fwd_bwd
    report["machine"]["numba_threading_layer"] = numba.threading_layer()

    # the acceptance ratio: kernel and reference alternated, so both see the same load
    _, n_ref, w_ref, h_ref = next(c for c in CASES if c[0] == REFERENCE_CASE)
    scene = make_scene(n_ref, w_ref, h_ref)
    _, k_fb = make_steps(backends[0][1], scene, w_ref, h_ref)
    _, r_fb = make_steps(rasterize_reference, scene, w_ref, h_ref)
    same = interleaved(k_fb, r_fb, ref_repeats)
    report["machine"]["loadavg_end"] = os.getloadavg()
    ref = report["cases"][REFERENCE_CASE]
    speed_fwd = ref["reference"]["forward"]["median_s"] / ref["cpu"]["forward"]["median_s"]
    speed_fb = (ref["reference"]["forward_backward"]["median_s"]
                / ref["cpu"]["forward_backward"]["median_s"])
    t100 = report["cases"]["100k@640x480"]["cpu"]["forward_backward"]["median_s"]
    report["ratios"] = {"reference_over_cpu_forward": speed_fwd,
                        "reference_over_cpu_forward_backward": speed_fb,
                        "interleaved_forward_backward": same}
    report["acceptance"] = {
        "speedup_fwd_bwd_20k": same["ratio"],
        "speedup_ok": same["ratio"] >= TARGET_SPEEDUP,
        "fwd_bwd_100k_s": t100,
        "fwd_bwd_100k_ok": t100 < TARGET_100K_FWD_BWD_S,
    }
    print(f"\n== {REFERENCE_CASE}: pure-torch reference / CPU kernel ==")
    print(f"forward (medians above):          {speed_fwd:6.1f} x")
    print(f"forward+backward (medians above): {speed_fb:6.1f} x")
    print(f"forward+backward, interleaved:    {same['ratio']:6.1f} x   (kernel "
          f"{same['kernel_median_s']:.4f} s, reference {same['reference_median_s']:.4f} s; "
          f"target >= {TARGET_SPEEDUP:.0f} x: {'PASS' if same['ratio'] >= TARGET_SPEEDUP else 'FAIL'})")
    print(f"  per round: {same['ratio_min']:.1f} - {same['ratio_max']:.1f} x over {same['rounds']} rounds "
          "(the spread is the machine's noise: compare medians)")
    print(f"100k@640x480 CPU forward+backward: {t100:.3f} s   (target < {TARGET_100K_FWD_BWD_S} s: "
          f"{'PASS' if t100 < TARGET_100K_FWD_BWD_S else 'FAIL'})")
    m = report["machine"]
    print(f"SIMD target: {cpu.summary()}")
    print(f"threads: numba {m['numba_threads']} ({m['numba_threading_layer']}), torch "
          f"{m['torch_threads']}; OMP_WAIT_POLICY={m['OMP_WAIT_POLICY']}; load average start "
          f"{m['loadavg_start'][0]:.2f}, end {m['loadavg_end'][0]:.2f}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

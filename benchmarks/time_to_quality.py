"""Time to quality of two training configurations, interleaved on one machine (issue #22).

Trains configuration A and configuration B on the same scene, alternating chunks of ``--chunk``
steps (A, B, A, B, ...; only one of them trains at any moment) so that both see the same machine
load; each keeps its own wall and CPU clocks of training steps only (holdout evaluation, every
``--every`` steps, is not counted). Before its clocks start, each configuration runs one untimed
warm-up step on a throwaway copy of its model (same data and preset, the global RNG restored), so
that compiling the numba kernels (forward, backward, loss) does not land in its first timed chunk.
It reports, per configuration: wall and CPU time to reach 27 dB and 30 dB holdout PSNR (and the
other configuration's final PSNR), final holdout PSNR and SSIM, Gaussians and Gaussians per
pixel, the model's parameter + optimiser memory, and the ratio that matters: **time for A to
reach its final PSNR / time for B to reach that PSNR** (> 1: B gets there faster). Times to a
level are interpolated linearly between evaluations; a level not reached is reported as such.
Writes a JSON table and one PNG with both PSNR-vs-time curves (what the report's training
section plots).

Configurations are ``NAME=PRESET[,field=value...]`` with any :class:`brave6d.training.Preset` field, by
its name or its path (``max_gaussians=70000`` or ``densification.max_gaussians=70000``; the names are
those of the flat presets before issue 33, so one configuration works in older trees too):

    python benchmarks/time_to_quality.py runs/demo/scene [--a old=fast-3000] [--b new=fast,steps=1000] \\
        [--every 250] [--chunk 50] [--json out.json]

``fast-3000`` is the ``fast`` preset before issue 22 (:data:`brave6d.training.presets.FAST_3000`), ``fast-2000``
today's without its learning-rate annealing (:data:`brave6d.training.presets.FAST_2000`).

``--a-source REV_OR_DIR`` trains A with the code of another source tree, so that per-step code
speed-ups count too: a git revision of this repository (extracted with ``git archive`` into a
temporary directory, removed at the end) or a directory holding a checkout. A then runs in a
worker process (this file with ``--worker``, importing ``training`` and ``brave6d`` from that
tree), driven chunk by chunk over pipes, still strictly alternating with B (in this process).
A's preset is looked up in that tree's presets and its fields are checked against that tree's
``Preset``; without ``--a`` it is ``old=fast``. Issue 22's target, the ``fast`` preset as it was
when the issue was filed (main at ``a83a1a6``) against the new one:

    python benchmarks/time_to_quality.py runs/demo/scene --a-source a83a1a6 --a old=fast --b new=fast
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import math
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import IO, Any

REPO = Path(__file__).resolve().parent.parent
#: Set by the parent in a worker's environment: the source tree whose ``training`` and ``brave6d``
#: the worker imports (first on ``sys.path``, ahead of this repository and of an editable install).
SOURCE_ENV = "BRAVE6D_TTQ_SOURCE"
CODE_ROOT = Path(os.environ[SOURCE_ENV]).resolve() if os.environ.get(SOURCE_ENV) else REPO


def code_path(root: Path) -> Path:
    """Where a source tree's packages import from: its ``src/`` (the layout since issue 33), else the
    tree itself (older trees: top-level ``training`` beside the kernel ``brave6d``)."""
    return root / "src" if (root / "src" / "brave6d").is_dir() else root


#: An older tree's modules under the names this file imports (``alias_old_layout``).
OLD_LAYOUT = {"brave6d.core": "brave6d", "brave6d.core.runtime": "brave6d.runtime",
              "brave6d.core.layout": "brave6d.layout", "brave6d.core.atomic": "brave6d.atomic",
              "brave6d.core.progress": "brave6d.progress", "brave6d.training": "training",
              "brave6d.training.presets": "training.presets", "brave6d.training.trainer": "training.trainer",
              "brave6d.training.colmap_init": "training.colmap_init",
              "brave6d.training.holdout_eval": "training.evaluate"}


def alias_old_layout() -> None:
    """In a worker on a tree before the src layout, make ``brave6d.training...`` and ``brave6d.core...``
    name that tree's own modules (the same module objects, so classes stay one and the same)."""
    import importlib

    for new, old in OLD_LAYOUT.items():
        sys.modules[new] = importlib.import_module(old)


if __name__ == "__main__":
    # the code root first, also when PYTHONPATH lists it, and not benchmarks/ (sys.path[0] for a
    # script), whose training.py would shadow an older tree's package
    sys.path[:] = [str(code_path(CODE_ROOT))] + [
        p for p in sys.path if p != str(code_path(CODE_ROOT)) and (not p or Path(p).resolve() != REPO / "benchmarks")]
elif str(REPO / "src") not in sys.path:  # imported (tests): leave the importer's path as it is
    sys.path.insert(0, str(REPO / "src"))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

LEVELS_DB = (27.0, 30.0)
WORKER_STDERR_LINES = 30  # how many of a worker's last stderr lines an error shows


def preset_fields() -> tuple[set[str], list[str]]:
    """The keys a configuration may set in this tree's ``Preset`` (names and paths such as
    ``densification.max_gaussians``), and the paths to list in an error. A tree from before the
    composed presets (issue 33) has flat fields only: their names are the same."""
    from brave6d.training import Preset

    probe = Preset(name="fields")
    if not hasattr(probe, "paths"):  # an older tree
        names = [f.name for f in dataclasses.fields(Preset)]
        return set(names), sorted(names)
    paths = probe.paths()
    return set(paths) | {p.rpartition(".")[2] for p in paths}, paths


def parse_config(text: str) -> tuple[str, str, dict[str, Any]]:
    """``NAME=PRESET[,field=value...]`` -> (name, preset name, overrides with typed values)."""
    name, _, rest = text.partition("=")
    if not name or not rest:
        raise SystemExit(f"--a/--b: expected NAME=PRESET[,field=value...], got {text!r}")
    preset, *pairs = rest.split(",")
    keys, listed = preset_fields()
    overrides: dict[str, Any] = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if key not in keys:
            raise SystemExit(f"{text}: {key!r} is not a Preset field (fields: {', '.join(listed)})")
        overrides[key] = typed_value(value)
    return name, preset, overrides


def typed_value(value: str) -> Any:
    """A configuration's value: ``none``, a JSON list or object, an integer, a float, else the text
    itself (``antialiasing=mip``); the preset checks it and names the field when it is wrong."""
    if value.lower() == "none":
        return None
    if value[:1] in "[{":
        return json.loads(value)
    for number in (int, float):
        try:
            return number(value)
        except ValueError:
            pass
    return value


def time_to(points: list[dict[str, float]], level: float, clock: str) -> float | None:
    """The ``clock`` time (``time_s`` or ``cpu_s``) at which holdout PSNR first reaches ``level``
    (linear between evaluations), or None when it never does."""
    for prev, cur in zip(points, points[1:]):
        if cur["psnr"] >= level:
            if prev["psnr"] >= level:
                return prev[clock]
            f = (level - prev["psnr"]) / (cur["psnr"] - prev["psnr"])
            return prev[clock] + f * (cur[clock] - prev[clock])
    if points and points[0]["psnr"] >= level:
        return points[0][clock]
    return None


def jit_signatures() -> int:
    """How many numba signatures the loaded ``training`` modules' kernels hold: a count that grows
    when a kernel compiles (or loads from its cache) for a new type signature."""
    try:
        from numba.core.dispatcher import Dispatcher
    except ImportError:
        return 0
    modules = {id(m): m for name, m in list(sys.modules.items())  # an older tree's modules are also aliased
               if name.startswith(("training.", "brave6d.training.")) or name in ("training", "brave6d.training")}
    return sum(len(v.signatures) for m in modules.values() for v in list(vars(m).values()) if isinstance(v, Dispatcher))


def configure(base: Any, overrides: dict[str, Any]) -> Any:
    """``base`` (a Preset) with ``overrides`` applied, ``None`` values included (``max_gaussians=none``
    means no limit; ``Preset.with_overrides`` would ignore it). A tree from before the composed presets
    has flat fields: ``dataclasses.replace`` sets them."""
    if hasattr(base, "with_values"):
        return base.with_values(**overrides)
    return dataclasses.replace(base, **overrides)


class Run:
    """One configuration's trainer and its evaluations (in this process)."""

    def __init__(self, name: str, preset: Any, scene: Any, every: int, device: Any, init_method: str) -> None:
        from brave6d.training import GaussianModel, load_scene
        from brave6d.training.colmap_init import initial_points
        from brave6d.training.trainer import Trainer

        # no time budget: the benchmark measures the time to quality of the whole schedule
        self.name, self.preset = name, configure(preset, {"eval_every": every, "time_budget_s": None})
        values = self.preset.to_json()  # flat names in any tree, before and after the composed presets
        self.data = load_scene(scene, values["downscale"])
        init = initial_points(scene, self.data, max_points=values["max_init_points"], seed=values["seed"],
                              method=init_method)
        points = init.points
        # training in the scene's frame, as brave6d train does; a revision before the training frame (issue 67)
        # trains in world units, as it did
        if hasattr(self.data, "in_frame"):
            frame = self.data.training_frame()
            self.data, points = self.data.in_frame(frame), frame.points(init.points)
        model = GaussianModel.from_points(points, init.colors, values["sh_degree"], values["init_opacity"],
                                          values["init_scale"], device=device)
        self.points: list[dict[str, float]] = []
        self.trainer = Trainer(self.data, model, self.preset, None, device, show_progress=False,
                               eval_callback=self.evaluate)
        self.evaluate(self.trainer)
        self.warmup_s = self.warm_up()
        self.jit_baseline = jit_signatures()  # main resets it once every run of the process is set up

    def warm_up(self) -> float:
        """One untimed training step on a throwaway copy of the model (same data and preset), so that
        compiling the kernels of a step (numba's forward, backward and loss; on a GPU, gsplat's) does
        not land in the first timed chunk. The trainer is left as it was, and so is the global RNG
        (the copy's constructor reseeds it). Returns the seconds it took."""
        import torch

        from brave6d.training import GaussianModel
        from brave6d.training.trainer import Trainer

        t0 = time.perf_counter()
        device = self.trainer.device
        rng = torch.get_rng_state()
        cuda_rng = torch.cuda.get_rng_state_all() if device.type == "cuda" else None
        m = self.trainer.model
        copy = GaussianModel.from_tensors({k: v.detach().clone() for k, v in m.params.items()}, m.sh_degree, device)
        Trainer(self.data, copy, self.preset, None, device, show_progress=False).train_step()
        torch.set_rng_state(rng)
        if cuda_rng is not None:
            torch.cuda.set_rng_state_all(cuda_rng)
        return time.perf_counter() - t0

    def evaluate(self, trainer: Any) -> float:
        from brave6d.training import evaluate_holdout

        m = evaluate_holdout(trainer.model, self.data)
        self.points.append({"step": trainer.step, "time_s": trainer.elapsed, "cpu_s": trainer.cpu_elapsed,
                            "psnr": m.psnr, "ssim": m.ssim, "gaussians": trainer.model.num_gaussians})
        return m.psnr

    @property
    def steps(self) -> int:
        return self.preset.steps

    @property
    def step(self) -> int:
        return self.trainer.step

    @property
    def done(self) -> bool:
        return self.trainer.step >= self.preset.steps

    def advance(self, chunk: int) -> None:
        self.trainer.train(max_steps=self.trainer.step + chunk)
        if self.done and self.points[-1]["step"] != self.trainer.step:
            self.evaluate(self.trainer)

    def summary(self, other_final_psnr: float) -> dict[str, Any]:
        last = self.points[-1]
        cam = self.data.camera
        params = self.trainer.model.params
        param_bytes = sum(p.numel() * p.element_size() for p in params.values())
        return {
            "name": self.name, "preset": self.preset.to_json(), "steps": self.trainer.step,
            "final_psnr": last["psnr"], "final_ssim": last["ssim"], "gaussians": last["gaussians"],
            "image_size": [cam.width, cam.height],
            "gaussians_per_pixel": last["gaussians"] / (cam.width * cam.height),
            "train_s": self.trainer.elapsed, "train_cpu_s": self.trainer.cpu_elapsed,
            "warmup_s": self.warmup_s,
            # kernels compiled after the warm-up, i.e. possibly inside the timed steps (should be 0)
            "jit_compiles_while_timed": jit_signatures() - self.jit_baseline,
            "model_mb": param_bytes * 3 / 2**20,  # parameters + Adam's two moments
            "time_to_db": {f"{lv:g}": time_to(self.points, lv, "time_s") for lv in LEVELS_DB},
            "cpu_to_db": {f"{lv:g}": time_to(self.points, lv, "cpu_s") for lv in LEVELS_DB},
            "time_to_other_final": time_to(self.points, other_final_psnr, "time_s"),
            "time_to_own_final": time_to(self.points, last["psnr"], "time_s"),
            "points": self.points,
        }

    def close(self) -> None:
        pass


def local_run(config: str, scene: Any, every: int, device: Any, init_method: str) -> Run:
    """A :class:`Run` in this process of the configuration ``NAME=PRESET[,field=value...]``."""
    from brave6d.training import get_preset
    from brave6d.training.presets import BENCHMARK_PRESETS

    name, preset_name, overrides = parse_config(config)
    return Run(name, configure(get_preset(preset_name, BENCHMARK_PRESETS), overrides), scene, every, device,
               init_method)


def interleave(runs: list[Any], chunk: int, desc: str = "interleaved training") -> None:
    """Train ``runs`` (:class:`Run` or :class:`RemoteRun`) to their ends, ``chunk`` steps each in turn
    (A, B, A, B, ...), so that all see the same machine load; a progress bar with ETA counts the steps."""
    from brave6d.core.progress import progress_bar

    bar = progress_bar(total=sum(r.steps for r in runs), desc=desc, unit="step",
                       initial=sum(r.step for r in runs))
    try:
        while not all(r.done for r in runs):
            for r in runs:  # one at a time: a worker trains only between a command and its answer
                if not r.done:
                    before = r.step
                    r.advance(chunk)
                    bar.update(r.step - before)
    finally:
        bar.close()


# ----------------------------------------------------------------------------- A from another source tree
class Source:
    """The source tree that trains configuration A (``--a-source``): its ``root``, the ``label`` the
    summary line names it by (the revision as given, or the directory), ``info`` for the JSON
    (``{"rev", "commit"}`` or ``{"dir"}``) and the temporary directory it was extracted into, if any."""

    def __init__(self, root: Path, label: str, info: dict[str, str],
                 tmp: tempfile.TemporaryDirectory[str] | None = None) -> None:
        self.root, self.label, self.info, self.tmp = root, label, info, tmp

    def cleanup(self) -> None:
        if self.tmp is not None:
            self.tmp.cleanup()
            self.tmp = None


def resolve_source(value: str) -> Source:
    """An existing directory as it is, else a git revision of this repository extracted (``git
    archive``) into a temporary directory that :meth:`Source.cleanup` removes."""
    path = Path(value).expanduser()
    if path.is_dir():
        return Source(path.resolve(), str(path.resolve()), {"dir": str(path.resolve())})
    try:
        sha = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet", f"{value}^{{commit}}"],
                             capture_output=True, text=True, check=True).stdout.strip()
    except (subprocess.CalledProcessError, FileNotFoundError):
        raise SystemExit(f"--a-source {value!r}: neither a directory nor a git revision of {REPO}") from None
    tmp = tempfile.TemporaryDirectory(prefix=f"ttq-{sha[:10]}-")
    git = subprocess.Popen(["git", "-C", str(REPO), "archive", "--format=tar", sha], stdout=subprocess.PIPE)
    tar = subprocess.run(["tar", "-x", "-C", tmp.name], stdin=git.stdout, capture_output=True, text=True)
    assert git.stdout is not None
    git.stdout.close()
    if git.wait() != 0 or tar.returncode != 0:
        tmp.cleanup()
        raise SystemExit(f"--a-source {value!r}: could not extract {sha} into a temporary directory: {tar.stderr}")
    return Source(Path(tmp.name), value, {"rev": value, "commit": sha}, tmp)


def _json_default(obj: Any) -> Any:
    return obj.item() if hasattr(obj, "item") else str(obj)  # numpy / torch scalars


class RemoteRun:
    """Configuration A trained by a worker process running another source tree (``--a-source``).

    The worker is this file with ``--worker``; it imports ``training`` and ``brave6d`` from
    ``source.root``. It reads one JSON command per line on its stdin (``advance`` N steps,
    ``summary``) and answers each with one JSON line on its stdout, which carries nothing else
    (all its logging goes to stderr, which this side keeps the last lines of and echoes). It trains
    only between a command and its answer, so A and B still alternate strictly. A worker that dies,
    reports an error, or does not answer within ``timeout_s`` stops the benchmark with a
    :class:`SystemExit` naming the source tree and showing the worker's last stderr lines.
    """

    def __init__(self, config: str, source: Source, scene_dir: Path, every: int, device: Any, init_method: str,
                 timeout_s: float | None = None) -> None:
        self.name, _, rest = config.partition("=")
        if not self.name or not rest:
            raise SystemExit(f"--a: expected NAME=PRESET[,field=value...], got {config!r}")
        self.preset_name = rest.split(",")[0]
        self.source, self.timeout_s = source, timeout_s
        self.stderr_tail: collections.deque[str] = collections.deque(maxlen=WORKER_STDERR_LINES)
        self.replies: queue.Queue[str | None] = queue.Queue()
        env = {**os.environ, "PYTHONPATH": str(source.root), SOURCE_ENV: str(source.root)}
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(Path(scene_dir).resolve()),
               "--config", config, "--every", str(every), "--device", str(device), "--init", init_method]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=env, bufsize=1)
        self._threads = [threading.Thread(target=self._pump_replies, daemon=True),
                         threading.Thread(target=self._pump_stderr, daemon=True)]
        for t in self._threads:
            t.start()
        ready = self._receive("while setting up")
        self.steps, self.step, self.done = int(ready["steps"]), int(ready["step"]), bool(ready["done"])
        self.points: list[dict[str, float]] = list(ready["points"])
        self.modules: dict[str, str] = ready["modules"]
        self.memory: dict[str, float] = {}

    def _pump_replies(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.replies.put(line)
        self.replies.put(None)  # EOF: the worker exited (or closed its answer pipe)

    def _pump_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            line = line.rstrip("\n")
            self.stderr_tail.append(line)
            print(f"[{self.name} worker] {line}", file=sys.stderr, flush=True)

    def _fail(self, what: str) -> None:
        try:
            rc: int | None = self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            rc = None
        self.close()
        self._threads[1].join(timeout=5)  # the rest of its stderr
        tail = "\n".join(f"    {line}" for line in self.stderr_tail) or "    (none)"
        code = f" (exit code {rc})" if rc is not None else ""
        where = self.source.label if self.source.label == str(self.source.root) else \
            f"{self.source.label} ({self.source.root})"
        raise SystemExit(f"configuration A ({self.name}): the worker running the source tree {where} "
                         f"{what}{code}; its last stderr lines:\n{tail}")

    def _receive(self, doing: str) -> dict[str, Any]:
        deadline = None if self.timeout_s is None else time.monotonic() + self.timeout_s
        while True:
            try:
                line = self.replies.get(timeout=0.5)
                break
            except queue.Empty:
                if deadline is not None and time.monotonic() > deadline:
                    self._fail(f"did not answer within {self.timeout_s:g} s {doing}")
        if line is None:
            self._fail(f"exited {doing}")
        try:
            msg = json.loads(line)
        except ValueError:
            self._fail(f"wrote a line that is not a JSON answer {doing}: {line[:200]!r}")
        if not isinstance(msg, dict):
            self._fail(f"wrote an answer that is not a JSON object {doing}: {line[:200]!r}")
        if "error" in msg:
            self._fail(f"failed {doing}: {msg['error']}")
        return msg

    def _request(self, command: dict[str, Any], doing: str) -> dict[str, Any]:
        try:
            assert self.proc.stdin is not None
            self.proc.stdin.write(json.dumps(command) + "\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError, ValueError):
            self._fail(f"could not be sent a command {doing} (its input pipe is closed)")
        return self._receive(doing)

    def advance(self, chunk: int) -> None:
        reply = self._request({"cmd": "advance", "steps": chunk}, f"training steps {self.step + 1}-{self.step + chunk}")
        self.points += reply["points"]
        self.step, self.done = int(reply["step"]), bool(reply["done"])

    def summary(self, other_final_psnr: float) -> dict[str, Any]:
        reply = self._request({"cmd": "summary", "other_final_psnr": other_final_psnr}, "summarising")
        self.memory = reply["memory"]
        return dict(reply["summary"])

    def close(self) -> None:
        """Ask the worker to stop (closing its input), then make sure it has."""
        if self.proc.poll() is None:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.close()
            except OSError:
                pass
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._threads[0].join(timeout=5)


def worker_main(argv: list[str]) -> int:
    """The worker side of :class:`RemoteRun`: configuration A on the tree in ``$BRAVE6D_TTQ_SOURCE``."""
    parser = argparse.ArgumentParser(prog="time_to_quality.py --worker")
    parser.add_argument("scene_dir", type=Path)
    parser.add_argument("--config", required=True)
    parser.add_argument("--every", type=int, required=True)
    parser.add_argument("--device", required=True)
    parser.add_argument("--init", required=True)
    args = parser.parse_args(argv)
    # the answer pipe is a duplicate of stdout; fd 1 itself (Python's and C libraries' prints) goes to stderr
    answers: IO[str] = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    sys.stdout = sys.stderr

    def send(msg: dict[str, Any]) -> None:
        answers.write(json.dumps(msg, default=_json_default) + "\n")
        answers.flush()

    try:
        old_layout = code_path(CODE_ROOT) == CODE_ROOT and (CODE_ROOT / "training").is_dir()
        import importlib

        importlib.import_module("brave6d.runtime" if old_layout else "brave6d.core.runtime").prepare_process()
        if old_layout:
            alias_old_layout()  # after prepare_process: the aliased modules may load torch
        import brave6d
        from brave6d import training

        modules = {m.__name__: str(Path(m.__file__ or "?").resolve()) for m in (training, brave6d)}
        strays = [f"{name} from {file}" for name, file in modules.items() if not Path(file).is_relative_to(CODE_ROOT)]
        if strays:
            raise SystemExit(f"imported {', '.join(strays)}, not from the source tree {CODE_ROOT} "
                             "(it holds no such package)")
        print(f"worker: training from {modules[training.__name__]}, brave6d from {modules['brave6d']}", file=sys.stderr)
        import brave6d.training.presets as presets
        from brave6d.core.layout import SceneDir
        from brave6d.training import resolve_device
        from brave6d.training.holdout_eval import peak_memory_mb

        name, preset_name, overrides = parse_config(args.config)  # checked against this tree's Preset
        known = getattr(presets, "BENCHMARK_PRESETS", presets.PRESETS)
        if preset_name not in known:
            raise SystemExit(f"{args.config}: no preset {preset_name!r} in {CODE_ROOT} (it has {', '.join(known)})")
        device = resolve_device(args.device)
        run = Run(name, configure(known[preset_name], overrides), SceneDir(args.scene_dir), args.every, device,
                  args.init)
        send({"steps": run.steps, "step": run.step, "done": run.done, "points": run.points, "modules": modules})
        for line in sys.stdin:
            command = json.loads(line)
            if command["cmd"] == "advance":
                seen = len(run.points)
                run.advance(int(command["steps"]))
                send({"step": run.step, "done": run.done, "points": run.points[seen:]})
            elif command["cmd"] == "summary":
                send({"summary": run.summary(float(command["other_final_psnr"])), "memory": peak_memory_mb(device)})
            else:
                raise ValueError(f"unknown command {command!r}")
        return 0
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which stops with it
        traceback.print_exc(file=sys.stderr)
        try:
            send({"error": f"{type(exc).__name__}: {exc}"})
        except OSError:
            pass
        return 1


def plot(path: Path, runs: list[dict[str, Any]], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from brave6d.core.atomic import atomic_write

    fig, ax = plt.subplots(figsize=(7, 4))
    for r in runs:
        ax.plot([p["time_s"] for p in r["points"]], [p["psnr"] for p in r["points"]], "o-", ms=3,
                label=f"{r['name']}: {r['final_psnr']:.2f} dB, {r['gaussians']:,} G, {r['train_s']:.0f} s")
    for lv in LEVELS_DB:
        ax.axhline(lv, color="0.7", lw=0.8, ls="--")
    ax.set_xlabel("training time [s] (evaluation excluded)")
    ax.set_ylabel("holdout PSNR [dB]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_write(path, lambda handle: fig.savefig(handle, format="png", dpi=110))
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--worker"]:
        return worker_main(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene_dir", type=Path, help="a captured scene directory (e.g. runs/demo/scene)")
    parser.add_argument("--a", default=None,
                        help="configuration A (default: old=fast-3000, the fast preset before issue 22; "
                             "with --a-source: old=fast)")
    parser.add_argument("--b", default="new=fast", help="configuration B (default: new=fast), e.g. new=fast,steps=1000")
    parser.add_argument("--a-source", default=None, metavar="REV_OR_DIR",
                        help="train A with the code of another source tree: a git revision of this repository "
                             "(e.g. a83a1a6, main before issue 22) or a directory holding a checkout; A then runs "
                             "in a worker process, still alternating with B")
    parser.add_argument("--every", type=int, default=250, help="holdout evaluation every K steps (default 250)")
    parser.add_argument("--chunk", type=int, default=50, help="steps per turn when interleaving (default 50)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--init", choices=["auto", "colmap", "depth", "random"], default="auto")
    parser.add_argument("--worker-timeout", type=float, default=3600.0,
                        help="with --a-source: stop when A's worker does not answer within this many seconds "
                             "(setup or one chunk; default 3600)")
    parser.add_argument("--json", type=Path, default=None, help="output JSON (default: <scene>/splat/time_to_quality.json)")
    args = parser.parse_args(argv)
    a_config = args.a or ("old=fast" if args.a_source else "old=fast-3000")

    from brave6d.core.atomic import atomic_write_json
    from brave6d.core.layout import SceneDir
    from brave6d.core.progress import format_table
    from brave6d.core.runtime import prepare_process

    prepare_process()
    from brave6d.training import resolve_device
    from brave6d.training.holdout_eval import json_safe, peak_memory_mb

    scene = SceneDir(args.scene_dir)
    device = resolve_device(args.device)
    here = {"dir": str(REPO)}

    def local(text: str) -> Run:
        return local_run(text, scene, args.every, device, args.init)

    source = resolve_source(args.a_source) if args.a_source else None
    runs: list[Run | RemoteRun] = []
    try:
        # set up one after the other: both write the scene's sparse/0 (the initial points)
        runs.append(RemoteRun(a_config, source, scene.root, args.every, device, args.init, args.worker_timeout)
                    if source is not None else local(a_config))
        runs.append(local(args.b))
        for r in runs:
            if isinstance(r, Run):  # B's warm-up ran after A's: count from here
                r.jit_baseline = jit_signatures()
        interleave(runs, args.chunk)
        a, b = runs
        sa, sb = a.summary(b.points[-1]["psnr"]), b.summary(a.points[-1]["psnr"])
    finally:
        for r in runs:
            r.close()
        if source is not None:
            source.cleanup()
    sa["source"] = {**source.info, "modules": a.modules} if isinstance(a, RemoteRun) else here
    sb["source"] = here
    a_own = sa["time_to_own_final"]
    ratio = (a_own / sb["time_to_other_final"]) if a_own and sb["time_to_other_final"] else None
    out = {"scene": str(scene.root), "device": str(device), "every": args.every, "chunk": args.chunk,
           "memory": peak_memory_mb(device), "a": sa, "b": sb,
           "ratio_time_to_a_final": ratio,
           "note": "ratio = time for A to reach its final holdout PSNR / time for B to reach it (> 1: B is faster)"}
    if isinstance(a, RemoteRun):
        out["memory_a_worker"] = a.memory

    def cell(v: float | None, fmt: str = "{:.0f}") -> str:
        return "not reached" if v is None or not math.isfinite(v) else fmt.format(v)

    def origin(s: dict[str, Any], run: Run | RemoteRun) -> str:
        where = run.source.label if isinstance(run, RemoteRun) else "this tree"
        return f"{s['name']} ({s['preset']['name']} at {where})"

    rows = [[s["name"], s["steps"], cell(s["train_s"]), cell(s["train_cpu_s"]), cell(s["time_to_db"]["27"]),
             cell(s["time_to_db"]["30"]), f"{s['final_psnr']:.2f}", f"{s['final_ssim']:.4f}", f"{s['gaussians']:,}",
             f"{s['gaussians_per_pixel']:.2f}", f"{s['model_mb']:.0f}"] for s in (sa, sb)]
    print(f"A = {origin(sa, a)}, B = {origin(sb, b)}")
    print(format_table(["config", "steps", "train s", "CPU s", "s to 27 dB", "s to 30 dB", "PSNR", "SSIM",
                        "Gaussians", "G / px", "model MB"], rows))
    print(f"\ntime to A's final PSNR ({sa['final_psnr']:.2f} dB): A {cell(a_own, '{:.1f} s')}, "
          f"B {cell(sb['time_to_other_final'], '{:.1f} s')} -> ratio A/B = {cell(ratio, '{:.2f}')}")
    print(f"untimed warm-up step (kernel compilation): A {sa['warmup_s']:.1f} s, B {sb['warmup_s']:.1f} s; "
          f"kernels compiled after it: A {sa['jit_compiles_while_timed']}, B {sb['jit_compiles_while_timed']}")
    if isinstance(a, RemoteRun):
        print(f"peak RSS: this process (B) {out['memory']['peak_rss_mb']:.0f} MB, "
              f"A's worker {a.memory['peak_rss_mb']:.0f} MB")
    else:
        print(f"peak RSS of the process (both runs): {out['memory']['peak_rss_mb']:.0f} MB")
    path = args.json or scene.splat_dir / "time_to_quality.json"
    atomic_write_json(path, json_safe(out))
    plot(path.with_suffix(".png"), [sa, sb], f"{scene.root.name}: {sa['name']} vs {sb['name']} on {device}")
    print(f"{path}\n{path.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

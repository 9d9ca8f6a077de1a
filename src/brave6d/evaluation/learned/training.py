"""``brave6d learn train``: train the detector, then the coordinate net, on a train_pbr split.

The two networks are independent, so on a CPU with two or more threads they train at once, each
phase in its own thread on half the threads (small convolutions do not keep two threads busy:
1.25x the throughput of one phase after the other on the 2-core box, docs/BENCHMARKS.md); on a GPU
one after the other, with each phase's batches made ahead by a thread (``learned/batches.py``) and
its losses read every ``_GPU_READ_EVERY`` steps, so that the device does not wait on the host: the
same batches and, on a CPU, the same weights as the CPU's way (tested).

Seeded and resumable: each phase has its own NumPy generator (drawing its batches), network and
optimiser; each phase's snapshot is taken every ``checkpoint_every`` of its steps and both go into
``checkpoint.pt`` (written atomically); ``resume=True`` continues each phase from its snapshot and
ends with the same weights as an uninterrupted run (CPU, same machine and thread count). A finished
model whose inputs (train_pbr digest, models, preset, device kind) are unchanged is not trained
again. A non-finite loss stops the run naming the network and the step; the last checkpoint stays.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.core.errors import BraveError
from brave6d.evaluation.learned.data import TrainingData, load_training_data, split_digest
from brave6d.evaluation.learned.model_file import CHECKPOINT, FORMAT, MODEL, LearnedModel, ObjectNorm, load_torch, \
    save_torch, write_model
from brave6d.evaluation.learned.presets import LearnPreset

log = logging.getLogger(__name__)
_WARMUP = 50
#: a GPU's steps between reads of their losses (each read waits for the device)
_GPU_READ_EVERY = 10
#: Raised whenever a change to the training (targets, augmentation, losses, networks) gives other
#: weights for the same inputs, so that a model trained by older code is not reused as current.
TRAINING_REVISION = 4
PHASES = ("detector", "pose")


@dataclass(frozen=True)
class LearnResult:
    """What a run did: the model folder, whether it was trained now (False: up to date), seconds
    per phase, the final losses and the model (None when ``stop_after_steps`` stopped the run
    early: its checkpoint is in ``out``, and ``resume=True`` continues it)."""

    out: Path
    trained: bool
    seconds: dict[str, float]
    losses: dict[str, float]
    model: LearnedModel | None
    data: TrainingData | None


def inputs_key(train_pbr_digest: str, models_dir: Path, preset: LearnPreset, device_kind: str) -> str:
    """The digest a finished model is reused by: the split, the models, the preset, the device kind and
    the training code's revision."""
    models_digest, _ = split_digest(models_dir)
    text = json.dumps({"train_pbr": train_pbr_digest, "models": models_digest, "preset": preset.to_json(),
                       "device": device_kind, "format": FORMAT, "revision": TRAINING_REVISION}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def train_learned(train_pbr: Path | str, models_dir: Path | str, out: Path | str, preset: LearnPreset,
                  device: str = "auto", resume: bool = False, show_progress: bool = True,
                  stop_after_steps: int | None = None, max_images: int | None = None,
                  data: TrainingData | None = None, ahead: int | None = None) -> LearnResult:
    """Train (or reuse, or resume) the learned estimator of ``train_pbr`` into ``out`` (module
    docstring); ``stop_after_steps`` stops after that many steps of this call with a checkpoint
    (a job with a time slot; the tests' interruption); ``max_images`` trains on the split's first n
    images only (the benchmarks' accuracy against the split's size); ``data``: the split already
    read by :func:`load_training_data` with this preset's widths (``train_pbr`` and ``max_images``
    are then not read: the GPU checks carry it to a machine without Open3D); ``ahead``: batches made
    ahead in a background thread (:mod:`~brave6d.evaluation.learned.batches`; default 3 on a GPU,
    none on a CPU), the same batches either way."""
    import torch

    from brave6d.core.atomic import move_aside
    from brave6d.evaluation.learned.model_file import read_model
    from brave6d.training import resolve_device

    dev = resolve_device(device)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise BraveError(f"{out}: --out is a file; give a folder")
    t0 = time.perf_counter()
    if data is None:
        data = load_training_data(train_pbr, models_dir, preset.work_width, preset.heldout_every, max_images=max_images,
                                  show_progress=show_progress, crop_width=preset.crop_source_width)
    preset = resolve_precision(preset, dev)
    key = inputs_key(f"{data.digest}:{len(data.images)}", Path(models_dir), preset, dev.type)
    seconds = {"read": time.perf_counter() - t0}
    if (out / MODEL).is_file():
        existing = read_model(out)
        if existing.inputs_key == key:
            log.info("%s: the model is up to date with its inputs; not trained again", out)
            return LearnResult(out, False, seconds, {}, existing, data)
        if not resume:
            moved = move_aside(out, "replaced")
            log.warning("%s: trained from other inputs; moved aside to %s", out, moved)
    state = _resume_state(out, key) if resume else None
    if state is None and (out / CHECKPOINT).is_file():
        moved = move_aside(out / CHECKPOINT, "stale")
        log.warning("%s: a checkpoint from an earlier run was moved aside to %s (use --resume to continue one)",
                    out, moved)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(preset.seed)
    trainer = _Trainer(data, preset, dev, out, key, show_progress, stop_after_steps, ahead)
    finished = trainer.run(state)
    seconds.update(trainer.seconds)
    if not finished:
        trainer.save()
        return LearnResult(out, True, seconds, trainer.losses, None, data)
    model = LearnedModel(preset.to_json(), _norms(data), _cpu_state(trainer.detector), _cpu_state(trainer.pose), key)
    write_model(out, model)
    (out / CHECKPOINT).unlink(missing_ok=True)
    return LearnResult(out, True, seconds, trainer.losses, model, data)


def _norms(data: TrainingData) -> dict[int, ObjectNorm]:
    return {o.obj_id: ObjectNorm(o.obj_id, o.class_index, o.centre_mm, o.radius_mm, o.diameter_mm)
            for o in data.objects.values()}


def _cpu_state(module: Any) -> dict[str, Any]:
    return {k: v.detach().to("cpu").clone() for k, v in module.state_dict().items()}


def _resume_state(out: Path, key: str) -> dict[str, Any] | None:
    path = out / CHECKPOINT
    if not path.is_file():
        log.info("%s: no checkpoint to resume; training from the start", out)
        return None
    state = load_torch(path)
    if state.get("inputs_key") != key:
        raise BraveError(f"{path}: the checkpoint was made from other inputs (train_pbr, models, preset or device); "
                         "train without --resume to start again (the checkpoint is moved aside)")
    return state


def learning_rate(step: int, steps: int, base: float) -> float:
    """Linear warm-up over the first 50 steps, then a cosine decay to 5 % of ``base``."""
    if step < _WARMUP:
        return base * (step + 1) / _WARMUP
    progress = (step - _WARMUP) / max(1, steps - _WARMUP)
    return base * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * min(progress, 1.0))))


def phase_batch(phase: str, data: TrainingData, pool: list[int], rng: np.random.Generator,
                preset: LearnPreset) -> dict[str, Any]:
    """One training batch of ``phase`` (``detector`` or ``pose``) drawn by ``rng`` from ``pool`` (image
    indices for the detector, instance indices for the pose network), as NumPy arrays."""
    from brave6d.evaluation.learned.targets import detector_batch, pose_batch

    if phase == "detector":
        return detector_batch(data, pool, rng, preset.detector_batch, preset.detector_patch)
    return pose_batch(data, pool, rng, preset.pose_batch, preset.crop_px, preset.crop_px_min)


def batch_loss(phase: str, net: Any, batch: dict[str, Any], preset: LearnPreset) -> Any:
    """``net``'s loss on ``batch`` (tensors on the net's device)."""
    import torch

    from brave6d.evaluation.learned.losses import detector_loss, pose_loss

    images, extra, loss = ("images", (), detector_loss) if phase == "detector" else ("crops", ("classes",), pose_loss)
    low = preset.precision == "bf16"
    device_type = batch[images].device.type
    with torch.autocast(device_type, dtype=torch.bfloat16, enabled=low):
        x = batch[images]
        if channels_last(preset, x.device):
            x = x.contiguous(memory_format=torch.channels_last)
        out = net(x, *(batch[k] for k in extra))
    return loss(*(o.float() for o in out), batch)


def phase_loss(phase: str, net: Any, data: TrainingData, pool: list[int], rng: np.random.Generator,
               preset: LearnPreset, device: Any) -> Any:
    """One batch of ``phase`` drawn by ``rng`` (:func:`phase_batch`) and ``net``'s loss on it."""
    import torch

    batch = phase_batch(phase, data, pool, rng, preset)
    return batch_loss(phase, net, {k: torch.from_numpy(v).to(device) for k, v in batch.items()}, preset)


def channels_last(preset: LearnPreset, device: Any) -> bool:
    """Whether the networks train on channels-last tensors: on a CPU always (oneDNN's convolutions run
    1.3x faster so in float32 on an AVX2 CPU, docs/BENCHMARKS.md), on a GPU in bfloat16 (tensor cores)."""
    return device.type == "cpu" or preset.precision == "bf16"


def loss_reads(device: Any) -> int:
    """Steps between reads of the losses: every step on a CPU (checked before the step is taken),
    every ``_GPU_READ_EVERY`` on a GPU (a read waits for the device)."""
    return 1 if device.type == "cpu" else _GPU_READ_EVERY


def native_bf16(device: Any) -> bool:
    """Whether ``device`` computes in bfloat16 natively: a GPU that supports it, a CPU with AVX512-BF16
    or AMX (elsewhere torch emulates it, slower than float32)."""
    import torch

    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    if not cpu_kernels_may_use_bf16():
        return False
    cpu = getattr(torch, "cpu", None)
    checks = [getattr(cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    return any(bool(check()) for check in checks if check is not None)


#: oneDNN's instruction-set caps (``ONEDNN_MAX_CPU_ISA``) under which it has no bfloat16 instructions
_ONEDNN_ISAS_WITHOUT_BF16 = ("SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX512_CORE", "AVX512_CORE_VNNI")


def cpu_kernels_may_use_bf16() -> bool:
    """False where torch's or oneDNN's CPU kernels are capped below bfloat16 (``ATEN_CPU_CAPABILITY``
    under AVX512, ``ONEDNN_MAX_CPU_ISA`` under AVX512_CORE_BF16): such a process runs as a CPU without
    it would, so it trains as one (docs/GUIDE.md: measuring as an AVX2-only CPU)."""
    import os

    import torch

    if not str(torch.backends.cpu.get_cpu_capability()).upper().startswith("AVX512"):
        return False
    return os.environ.get("ONEDNN_MAX_CPU_ISA", os.environ.get("DNNL_MAX_CPU_ISA", "ALL")).strip().upper() \
        not in _ONEDNN_ISAS_WITHOUT_BF16


def resolve_precision(preset: LearnPreset, device: Any) -> LearnPreset:
    """``preset`` as it will run on ``device`` (``auto``, ``cpu``, ``cuda`` or a torch device): ``auto``
    -> ``bf16`` where the device has it natively, else ``fp32``, the same steps either way (the card and
    the reuse checksum record what ran); an explicit ``bf16`` without native support runs, with a warning."""
    from brave6d.training import resolve_device

    device = resolve_device(device)
    if preset.precision == "auto":
        return preset.with_overrides(precision="bf16" if native_bf16(device) else "fp32")
    if preset.precision == "bf16" and not native_bf16(device):
        log.warning("learn: precision bf16 on a %s without native bfloat16 (AVX512-BF16 or AMX): it is emulated "
                    "and may be slower than fp32 (set precision=fp32 or auto)", device.type.upper())
    return preset


class _Trainer:
    """Both phases, each with its own generator, network and optimiser; at once on a CPU (module
    docstring); checkpoint and resume per phase."""

    def __init__(self, data: TrainingData, preset: LearnPreset, device: Any, out: Path, key: str,
                 show_progress: bool, stop_after_steps: int | None = None, ahead: int | None = None) -> None:
        import torch

        from brave6d.evaluation.learned.batches import GPU_AHEAD
        from brave6d.evaluation.learned.networks import CoordinateNet, Detector

        self.data, self.preset, self.device, self.out, self.key = data, preset, device, out, key
        self.show_progress = show_progress
        classes = len(data.objects)
        self.nets = {"detector": Detector(classes, preset.detector_width).to(device),
                     "pose": CoordinateNet(classes, preset.pose_width).to(device)}
        if channels_last(preset, device):
            self.nets = {k: net.to(memory_format=torch.channels_last) for k, net in self.nets.items()}
        self.opts = {"detector": torch.optim.AdamW(self.nets["detector"].parameters(), lr=preset.detector_lr,
                                                   weight_decay=1e-4),
                     "pose": torch.optim.AdamW(self.nets["pose"].parameters(), lr=preset.pose_lr, weight_decay=1e-4)}
        seeds = np.random.SeedSequence(preset.seed).spawn(len(PHASES))
        self.rngs = {phase: np.random.default_rng(seed) for phase, seed in zip(PHASES, seeds)}
        # each generator's state after the last batch trained (batches made ahead have moved it on)
        self.rng_states = {phase: rng.bit_generator.state for phase, rng in self.rngs.items()}
        self.ahead = (GPU_AHEAD if device.type == "cuda" else 0) if ahead is None else ahead
        self.steps = {phase: 0 for phase in PHASES}
        self.seconds: dict[str, float] = {phase: 0.0 for phase in PHASES}
        self.losses: dict[str, float] = {}
        self.budget = stop_after_steps
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._snapshots: dict[str, dict[str, Any]] = {}

    @property
    def detector(self) -> Any:
        return self.nets["detector"]

    @property
    def pose(self) -> Any:
        return self.nets["pose"]

    def run(self, state: dict[str, Any] | None) -> bool:
        """Train what is left; False when the step budget stopped it first."""
        import torch

        if state is not None:
            self._load(state)
        pools = {"detector": self.data.split(False), "pose": self.data.instances_of(False)}
        totals = {"detector": self.preset.detector_steps, "pose": self.preset.pose_steps}
        left = [phase for phase in PHASES if self.steps[phase] < totals[phase]]
        for phase in PHASES:  # a checkpoint written while the other phase runs holds its last consistent state
            if phase not in self._snapshots:
                self._snapshot(phase)
        t0 = time.perf_counter()
        threads = torch.get_num_threads()
        if self.device.type == "cpu" and threads >= 2 and len(left) == 2:
            torch.set_num_threads(max(1, threads // 2))  # process-wide: each phase's ops on half the threads
            try:
                with ThreadPoolExecutor(max_workers=2, thread_name_prefix="learn") as pool:
                    futures = [pool.submit(self._phase, phase, totals[phase], pools[phase], position)
                               for position, phase in enumerate(left)]
                    for future in futures:
                        future.result()  # a phase's error (a non-finite loss) is raised here
            finally:
                torch.set_num_threads(threads)
        else:
            for phase in left:
                if not self._phase(phase, totals[phase], pools[phase], None):
                    break
        self.seconds["training"] = self.seconds.get("training", 0.0) + time.perf_counter() - t0
        return all(self.steps[p] >= totals[p] for p in PHASES)

    def _take_step(self) -> bool:
        """Whether the step budget (shared by the phases) allows one more step."""
        with self._lock:
            if self._stop.is_set():
                return False
            if self.budget is None:
                return True
            if self.budget <= 0:
                return False
            self.budget -= 1
            return True

    def _phase(self, phase: str, steps: int, pool: list[int], position: int | None) -> bool:
        from brave6d.core.progress import progress_bar
        from brave6d.evaluation.learned.batches import BatchSource

        net, opt, rng = self.nets[phase], self.opts[phase], self.rngs[phase]
        base_lr = self.preset.detector_lr if phase == "detector" else self.preset.pose_lr
        net.train()
        bar = progress_bar(steps, desc=f"learn: {phase}", unit="step", initial=self.steps[phase],
                           position=position) if self.show_progress else None
        # a CPU checks each loss before its step; a GPU reads them every few steps (each read waits
        # for the device), and a non-finite one stops the run there, before any checkpoint
        read_every = loss_reads(self.device)
        source = BatchSource(lambda r: phase_batch(phase, self.data, pool, r, self.preset), rng,
                             steps - self.steps[phase], self.device, self.ahead)
        recent: list[float] = []
        pending: list[tuple[int, Any]] = []
        start = time.perf_counter()
        try:
            while self.steps[phase] < steps and self._take_step():
                step = self.steps[phase]
                for group in opt.param_groups:
                    group["lr"] = learning_rate(step, steps, base_lr)
                batch, self.rng_states[phase] = source.next()
                loss = batch_loss(phase, net, batch, self.preset)
                pending.append((step, loss.detach()))
                if read_every == 1:
                    recent = (recent + self._read(phase, pending))[-50:]
                    pending = []
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                self.steps[phase] += 1
                done = self.steps[phase]
                checkpoint = done % self.preset.checkpoint_every == 0 and done < steps
                if pending and (len(pending) >= read_every or checkpoint or done >= steps):
                    recent = (recent + self._read(phase, pending))[-50:]
                    pending = []
                if bar is not None:
                    bar.update(1)
                    if done % 10 == 0 and recent:
                        bar.set_postfix(loss=f"{np.mean(recent):.3f}")
                if checkpoint:
                    self.seconds[phase] += time.perf_counter() - start
                    start = time.perf_counter()
                    self.losses[phase] = float(np.mean(recent))
                    self._snapshot(phase)
                    self.save()
            if pending:  # the step budget stopped the phase between reads
                recent = (recent + self._read(phase, pending))[-50:]
        finally:
            source.close()
            if bar is not None:
                bar.close()
        self.seconds[phase] += time.perf_counter() - start
        if recent:
            self.losses[phase] = float(np.mean(recent))
        self.losses.setdefault(phase, float("nan"))
        self._snapshot(phase)
        net.eval()
        return self.steps[phase] >= steps

    def _read(self, phase: str, pending: list[tuple[int, Any]]) -> list[float]:
        """The losses of ``pending`` (step, loss on the device) as floats, one wait for the device;
        a non-finite one stops the training naming the network and the step."""
        import torch

        values = torch.stack([loss for _, loss in pending]).float().cpu().tolist()
        for (step, _), value in zip(pending, values):
            if not math.isfinite(value):
                self._stop.set()
                raise BraveError(f"learn: the {phase} loss is {value} at step {step}; training stopped "
                                 f"(the last checkpoint is {self.out / CHECKPOINT}; lower the learning rate "
                                 f"'{phase}_lr' of preset {self.preset.name!r})")
        return values

    def _snapshot(self, phase: str) -> None:
        """This phase's state as of now (its own thread takes it between steps, so it is consistent)."""
        snap = {"step": self.steps[phase], "net": _cpu_state(self.nets[phase]),
                "opt": copy.deepcopy(self.opts[phase].state_dict()),
                "rng": json.dumps(self.rng_states[phase]), "seconds": self.seconds[phase],
                "loss": self.losses.get(phase, float("nan"))}
        with self._lock:
            self._snapshots[phase] = snap

    def save(self) -> None:
        """Write the checkpoint (atomically): each phase's latest snapshot (its start when it has none yet)."""
        for phase in PHASES:
            if phase not in self._snapshots:
                self._snapshot(phase)
        with self._lock:
            save_torch(self.out / CHECKPOINT, {"format": FORMAT, "inputs_key": self.key,
                                               "phases": dict(self._snapshots),
                                               "training_seconds": self.seconds.get("training", 0.0)})

    def _load(self, state: dict[str, Any]) -> None:
        phases = state.get("phases")
        if not isinstance(phases, dict) or set(phases) != set(PHASES):
            raise BraveError(f"{self.out / CHECKPOINT}: not a checkpoint of this training code (no per-phase "
                             "snapshots); train without --resume to start again")
        for phase, snap in phases.items():
            self.nets[phase].load_state_dict(snap["net"])
            self.opts[phase].load_state_dict(snap["opt"])
            self.rngs[phase].bit_generator.state = json.loads(snap["rng"])
            self.rng_states[phase] = self.rngs[phase].bit_generator.state
            self.steps[phase] = int(snap["step"])
            self.seconds[phase] = float(snap["seconds"])
            if math.isfinite(float(snap["loss"])):
                self.losses[phase] = float(snap["loss"])
            self._snapshots[phase] = snap
        self.seconds["training"] = float(state.get("training_seconds", 0.0))
        log.info("%s: resuming at detector step %d, pose step %d", self.out, self.steps["detector"], self.steps["pose"])

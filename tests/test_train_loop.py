"""The training loop on a tiny synthetic scene: learning, NaN guard, resume, determinism."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import DataError
from brave6d.training.views import TrainingData
from brave6d.training.holdout_eval import evaluate_holdout
from brave6d.training.model import GaussianModel
from brave6d.training.presets import Preset
from brave6d.training.toy_scenes import gaussian_ring_data, random_gaussians
from brave6d.training.trainer import Trainer, TrainingDiverged, list_checkpoints, means_lr, read_checkpoint

CAM = PinholeCamera(48, 36, 40.0, 40.0, 23.5, 17.5)


@pytest.fixture(scope="module")
def tiny_data() -> TrainingData:
    """12 views of 150 random Gaussians rendered by the rasterizer itself (2 rings)."""
    return gaussian_ring_data(CAM)


def init_model(seed: int = 0) -> GaussianModel:
    gt = random_gaussians(150, seed=1, extent=0.08)
    rng = np.random.default_rng(seed)
    pts = gt["means"].numpy() + rng.normal(0, 0.01, (150, 3))
    return GaussianModel.from_points(pts, None, sh_degree=1, init_opacity=0.3)


def tiny_preset(**kw) -> Preset:
    base = {"name": "tiny", "steps": 60, "sh_degree": 1, "sh_degree_interval": 20, "refine_start": 10,
            "refine_stop": 45, "refine_every": 8, "reset_every": 30, "checkpoint_every": 10, "keep_checkpoints": 10,
            "curve_every": 5, "grow_grad2d": 1e-4, "max_gaussians": 400}
    base.update(kw)
    return Preset(name=base.pop("name")).with_values(**base)


def params_of(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in trainer.model.params.items()}


def test_training_lowers_the_loss_and_raises_psnr(tiny_data: TrainingData, tmp_path: Path) -> None:
    model = init_model()
    before = evaluate_holdout(model, tiny_data).psnr
    trainer = Trainer(tiny_data, model, tiny_preset(steps=120, refine_stop=90), tmp_path / "ck", show_progress=False)
    result = trainer.train()
    after = evaluate_holdout(trainer.model, tiny_data).psnr
    assert result.steps == 120 and result.stopped_by == "steps"
    losses = [c["loss"] for c in result.curve if np.isfinite(c["loss"])]
    assert np.mean(losses[-3:]) < 0.7 * losses[0]
    assert after > before + 3.0, (before, after)
    assert result.num_gaussians != 150  # densification ran (clone/split/prune)
    assert [c["step"] for c in result.curve][:3] == [0.0, 5.0, 10.0]
    assert not trainer.model.non_finite()


def test_means_lr_schedule_is_inria() -> None:
    p = tiny_preset(steps=100)
    assert means_lr(0, p, 2.0) == pytest.approx(2.0 * 1.6e-4)
    assert means_lr(100, p, 2.0) == pytest.approx(2.0 * 1.6e-6)
    assert means_lr(50, p, 1.0) == pytest.approx(1.6e-5)  # log-linear midpoint


def test_nan_stops_with_a_clear_message_and_keeps_the_last_good_checkpoint(tiny_data: TrainingData,
                                                                           tmp_path: Path) -> None:
    def inject(trainer: Trainer, step: int) -> None:
        if step == 13:
            with torch.no_grad():
                trainer.model.params["scales"][3, 1] = float("nan")

    ck = tmp_path / "ck"
    trainer = Trainer(tiny_data, init_model(), tiny_preset(), ck, show_progress=False, step_callback=inject)
    with pytest.raises(TrainingDiverged, match=r"step 14: parameter\(s\) scales hold NaN/inf.*ckpt_000010\.pt"):
        trainer.train()
    assert [p.name for p in list_checkpoints(ck)] == ["ckpt_000010.pt"]
    ckpt = read_checkpoint(ck / "ckpt_000010.pt")  # tensors and plain values only
    assert ckpt["step"] == 10
    assert all(torch.isfinite(t).all() for t in ckpt["params"].values())


def test_nan_loss_is_caught(tiny_data: TrainingData, monkeypatch: pytest.MonkeyPatch) -> None:
    import brave6d.training.trainer as tr

    real = tr.photometric_loss
    calls = {"n": 0}

    def poisoned(render, target, lam):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        loss, l1, s = real(render, target, lam)
        return (loss * float("inf"), l1, s) if calls["n"] == 4 else (loss, l1, s)

    monkeypatch.setattr(tr, "photometric_loss", poisoned)
    trainer = Trainer(tiny_data, init_model(), tiny_preset(), None, show_progress=False)
    with pytest.raises(TrainingDiverged, match=r"step 4: the loss is inf.*no checkpoint"):
        trainer.train()


def test_resume_equals_uninterrupted_run(tiny_data: TrainingData, tmp_path: Path) -> None:
    preset = tiny_preset()  # densification, an opacity reset and SH growth all happen in 60 steps
    full = Trainer(tiny_data, init_model(), preset, tmp_path / "a", show_progress=False)
    full.train()

    def interrupt(trainer: Trainer, step: int) -> None:
        if step == 27:
            raise KeyboardInterrupt

    first = Trainer(tiny_data, init_model(), preset, tmp_path / "b", show_progress=False, step_callback=interrupt)
    with pytest.raises(KeyboardInterrupt):
        first.train()
    torch.manual_seed(12345)  # the resumed run must not depend on the process's RNG state
    second = Trainer(tiny_data, init_model(seed=99), preset, tmp_path / "b", show_progress=False)
    result = second.train(resume=True)
    assert result.resumed_from == 20
    a, b = params_of(full), params_of(second)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert [c["step"] for c in full.curve] == [c["step"] for c in second.curve]


def test_same_seed_same_result_other_seed_differs(tiny_data: TrainingData) -> None:
    runs = []
    for seed in (7, 7, 8):
        t = Trainer(tiny_data, init_model(), tiny_preset(steps=25, seed=seed), None, show_progress=False)
        t.train()
        runs.append(params_of(t))
    assert all(torch.equal(runs[0][k], runs[1][k]) for k in runs[0])
    assert any(runs[0][k].shape != runs[2][k].shape or not torch.equal(runs[0][k], runs[2][k]) for k in runs[0])


def test_resume_refuses_other_views(tiny_data: TrainingData, tmp_path: Path) -> None:
    Trainer(tiny_data, init_model(), tiny_preset(steps=10), tmp_path / "c", show_progress=False).train()
    other = TrainingData(CAM, tiny_data.train[1:], tiny_data.test)
    with pytest.raises(Exception, match="other views"):
        Trainer(other, init_model(), tiny_preset(steps=20), tmp_path / "c", show_progress=False).train(resume=True)


def test_time_budget_stops_training(tiny_data: TrainingData, tmp_path: Path) -> None:
    trainer = Trainer(tiny_data, init_model(), tiny_preset(steps=10_000, time_budget_s=1.0), tmp_path / "d",
                      show_progress=False)
    result = trainer.train()
    assert result.stopped_by == "time budget"
    assert 0 < result.steps < 10_000
    assert list_checkpoints(tmp_path / "d")[-1].name == f"ckpt_{result.steps:06d}.pt"


class RunsCode:
    """Unpickling this runs code: it writes ``marker`` (what a crafted checkpoint would do)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):  # type: ignore[no-untyped-def]
        return (exec, (f"open({str(self.marker)!r}, 'w').write('ran')",))


@pytest.mark.parametrize("writer", ["torch.save", "pickle.dumps"])
def test_a_crafted_checkpoint_is_refused_not_run(tiny_data: TrainingData, tmp_path: Path, writer: str) -> None:
    ck = tmp_path / "ck"
    ck.mkdir()
    marker = tmp_path / "marker"
    payload = {"version": 1, "step": 10, "params": RunsCode(marker)}
    path = ck / "ckpt_000010.pt"
    if writer == "torch.save":
        torch.save(payload, path)
    else:
        path.write_bytes(pickle.dumps(payload, protocol=2))
    pickle.loads(pickle.dumps(RunsCode(tmp_path / "proof")))  # the payload does run code when unpickled
    assert (tmp_path / "proof").read_text() == "ran"
    trainer = Trainer(tiny_data, init_model(), tiny_preset(steps=20), ck, show_progress=False)
    with pytest.raises(DataError, match=r"ckpt_000010\.pt: refused to load this checkpoint: it needs exec to load .*could run code"):
        trainer.train(resume=True)
    assert not marker.exists()
    assert trainer.step == 0 and list_checkpoints(ck) == [path]


def test_resume_skips_a_torn_checkpoint_but_never_starts_over_silently(tiny_data: TrainingData,
                                                                      tmp_path: Path) -> None:
    ck = tmp_path / "ck"
    Trainer(tiny_data, init_model(), tiny_preset(steps=20), ck, show_progress=False).train()
    (ck / "ckpt_000020.pt").write_bytes(b"torn")
    resumed = Trainer(tiny_data, init_model(), tiny_preset(steps=20), ck, show_progress=False).train(resume=True)
    assert resumed.resumed_from == 10 and resumed.steps == 20
    for path in list_checkpoints(ck):
        path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(DataError, match=r"ck: none of the 2 checkpoint\(s\) can be read; start again without"):
        Trainer(tiny_data, init_model(), tiny_preset(steps=20), ck, show_progress=False).train(resume=True)


def test_a_checkpoint_missing_a_field_is_named(tiny_data: TrainingData, tmp_path: Path) -> None:
    ck = tmp_path / "ck"
    ck.mkdir()
    torch.save({"version": 1, "step": 10}, ck / "ckpt_000010.pt")
    with pytest.raises(DataError, match=r"ckpt_000010\.pt: not a usable brave6d checkpoint \(KeyError: 'train_views'\)"):
        Trainer(tiny_data, init_model(), tiny_preset(steps=20), ck, show_progress=False).train(resume=True)

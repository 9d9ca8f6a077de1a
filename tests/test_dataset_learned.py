"""A dataset run's learned model (issue 43, item 6): one model for the dataset's object library,
trained once for every scene, resumable and not redone; its options follow the flags, then the
``cluster`` block, then the defaults."""

from __future__ import annotations

from pathlib import Path

import pytest

from brave6d.core.dataset_spec import ClusterSpec
from brave6d.core.errors import BraveError
from brave6d.dataset import JOB_STAGES, LearnOptions, LibraryLearnJob, learn_options, learned_model_dir, run_dataset
from brave6d.dataset.learn import learn_fingerprint, learn_is_done, read_learn_status, write_library_spec
from brave6d.dataset.status import mark, read_scene_status
from brave6d.dataset.workdir import prepare_workdir
from brave6d.evaluation.learned import PRESETS, read_card, read_model

ROOT = Path(__file__).resolve().parent.parent
DEMO_DATASET = ROOT / "data" / "demo" / "dataset.yaml"


def test_learn_options_follow_the_flags_then_the_cluster_block_then_the_defaults() -> None:
    assert learn_options(ClusterSpec(), quick=False) == LearnOptions("fast", 300)
    assert learn_options(ClusterSpec(), quick=True) == LearnOptions("tiny", 24, 320, 200)
    block = ClusterSpec(learn_preset="paper", learn_images=2000)
    assert learn_options(block, quick=False) == LearnOptions("paper", 2000)
    assert learn_options(block, quick=False, preset="fast", images=50) == LearnOptions("fast", 50)
    assert learn_options(ClusterSpec(learn=False), quick=False) is None
    assert learn_options(ClusterSpec(), quick=False, skip=True) is None
    with pytest.raises(BraveError, match="--learn-preset: no learn preset named 'huge'"):
        learn_options(ClusterSpec(), quick=False, preset="huge")
    with pytest.raises(BraveError, match="cluster.learn_preset"):
        learn_options(ClusterSpec(learn_preset="huge"), quick=False)


@pytest.mark.slow
def test_one_model_for_the_library_trained_once_and_not_redone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The demo dataset (two scenes, six library objects): the step renders a train_pbr of the whole
    library and trains one model on it; a run whose scenes are done and whose step is recorded done for
    the same options submits no job and leaves the model as it was; other options are not "done"."""
    work = tmp_path / "work"
    dataset, inits = prepare_workdir(DEMO_DATASET, work, quick=True)
    assert set(inits.values()) == {"done"}
    # the tiny preset, shortened: this test checks the wiring, not the accuracy (the learned tests do)
    monkeypatch.setitem(PRESETS, "tiny", PRESETS["tiny"].with_overrides(
        detector_steps=4, pose_steps=4, detector_batch=2, pose_batch=4, checkpoint_every=2, heldout_every=2))
    options = LearnOptions("tiny", 4, 320, 200)
    write_library_spec(work)
    fingerprint = learn_fingerprint(work, options, "cpu")
    outcome = LibraryLearnJob(work, options, "cpu", fingerprint)()
    assert outcome.error is None, outcome.error
    model_dir = learned_model_dir(work)
    library = sorted(dataset.spec.obj_ids().values())
    card = read_card(model_dir)
    assert card["objects"] == library == sorted(read_model(model_dir).objects)  # every object, both scenes'
    assert card["images"] == 4 and card["preset"]["name"] == "tiny"
    assert read_learn_status(work)["state"] == "done" and learn_is_done(work, fingerprint)
    stamp = (model_dir / "model.pt").stat().st_mtime_ns

    for s in dataset.scenes:  # every scene finished: only the learn step could run
        status = read_scene_status(work, s.name, s.scene_id)
        for stage in JOB_STAGES:
            mark(work, status, stage, "done", seconds=0.0)
    summary = run_dataset(DEMO_DATASET, work, quick=True, device="cpu", learn=options, echo=False)
    assert summary.ran == [] and summary.learned == "done earlier, not redone"
    assert (model_dir / "model.pt").stat().st_mtime_ns == stamp
    assert not learn_is_done(work, learn_fingerprint(work, LearnOptions("tiny", 5, 320, 200), "cpu"))
